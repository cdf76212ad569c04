"""Choosing the kind of forward model (`mrrig train`'s default, `--features auto`) among the
kinds of `kinds`, by how each holds on data it never saw, for every kind of data.

Each kind is judged by the other-test estimate (`crossval.cross_validate_with`): where several
tests are given (a file is a test), leave one test out (up to `max_folds` tests, k-fold over
tests beyond); on one test, its segments dealt by character (amplitude, frequency, command
level) into groups, each left out in turn with its neighbours kept out of training (a test of
`crossval.MIN_RUNS` runs or more, a characterization matrix: its runs). Beside it, each kind's
block hold-out (the fold fit on the training blocks, scored on the last part of each run) is
printed, the optimistic alternative, and the kind it would have chosen. The choice (search and
folds) runs within `budget_s` (`CHOICE_BUDGET_S` by default): a kind whose folds would not end
within what is left (projected from its first folds, or from the least a fold of it needs:
`kinds.GRU_MIN_FOLD_S`, `kinds.TWIN_MIN_FOLD_S`) is not tried, with why; the first kind is
scored whatever the budget. A kind whose daemon controller's work per frame
(`model_fit.frame_cost_s`, the check the daemon makes when it loads the model) is over the
loop's budget is not chosen; among the others the lowest other-test Et wins.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from mrrig.loop.model_fit import COST_BUDGET_S, frame_cost_s
from mrrig.offline.datasets import Series
from mrrig.offline.training.crossval import (
    MAX_FOLDS,
    OverBudget,
    cross_validate_with,
    fold_count,
    one_test_unit,
)
from mrrig.offline.training.fit import HOLDOUT_FRACTION, STOP_EVERY
from mrrig.offline.training.kinds import (
    COST_DT_S,
    FOLD_EPOCHS,
    FOLD_MAX_ROWS,
    FOLD_ROWS,
    ModelKind,
    block_holdout,
)
from mrrig.offline.training.report import EtSum

log = logging.getLogger(__name__)

CHOICE_BUDGET_S = 300.0  # the choice's time (search and folds) by default, s


@dataclass
class KindScore:
    name: str
    label: str
    et: float  # the other-test estimate (pooled over the left-out rows)
    per_group: list[dict[str, Any]]
    frame_cost_us: float
    in_budget: bool
    seconds: float
    model: Any = None  # the last model fitted (a fold's)
    other_tests: dict[str, Any] | None = None  # the cross-validation's own report
    block_et: float = math.nan  # the fold fit on the training blocks, on the block hold-out
    folds: int = 0  # the cross-validation's folds


def _block_et(kind: ModelKind, series: Series, holdout_fraction: float, seconds: float) -> float:
    """The kind's block hold-out Et: its fold fit on the training blocks (the last part of
    each run kept out), scored on that last part."""
    fit = kind.fit_fold if kind.block_fit is None else kind.block_fit
    model = fit(series, seconds)
    rows, y, f = kind.forces(model, series)
    val = block_holdout(series, rows, holdout_fraction)
    s = EtSum()
    s.add(y[val], f[val])
    return float(s.numbers()["et"])


def _score_kind(
    kind: ModelKind,
    series: Series,
    tests: np.ndarray,
    names: list[str],
    *,
    holdout_fraction: float,
    max_folds: int,
    seed: int,
    deadline: float,
    cost_budget_s: float = COST_BUDGET_S,
) -> KindScore:
    """The kind's other-test estimate within `deadline` (OverBudget where it would not end),
    then its block hold-out and its work per frame against `cost_budget_s`."""
    t0 = time.perf_counter()
    max_folds = min(max_folds, kind.max_folds or max_folds)
    n_folds = fold_count(len(names), max_folds)
    fold_s = (deadline - t0) / (n_folds + 1)
    if fold_s < kind.min_fold_s:
        raise OverBudget(
            f"its {n_folds} folds and the block fit need at least {kind.min_fold_s:.0f} s each,"
            f" {kind.min_fold_s * (n_folds + 1):.0f} s; {max(deadline - t0, 0.0):.0f} s of the"
            " budget were left"
        )
    last: list[Any] = []

    def train(part: Series) -> Any:
        last[:] = [kind.fit_fold(part, fold_s)]
        return last[0]

    def held(model: Any, part: Series) -> tuple[np.ndarray, np.ndarray]:
        _, y, f = kind.forces(model, part)
        return y, f

    cv = cross_validate_with(
        series,
        tests,
        names,
        train,
        held,
        max_folds=max_folds,
        seed=seed,
        deadline=deadline,
        how="cut down to the time budget (the kind choice says how)",
    )
    model = last[0]
    block = _block_et(kind, series, holdout_fraction, fold_s)
    cost_s, _ = frame_cost_s(kind.controller(model), COST_DT_S)
    return KindScore(
        kind.name,
        kind.label,
        float(cv["overall"]["et"]),
        cv["per_group"],
        cost_s * 1e6,
        cost_s <= cost_budget_s,
        time.perf_counter() - t0,
        model,
        cv,
        block,
        n_folds,
    )


def choose_kind(
    series: Series,
    tests: np.ndarray,
    names: list[str],
    kinds: list[ModelKind],
    *,
    holdout_fraction: float = HOLDOUT_FRACTION,
    max_folds: int = MAX_FOLDS,
    seed: int = 0,
    deadline: float | None = None,
    started: float | None = None,
    not_built: dict[str, str] | None = None,
    cost_budget_s: float = COST_BUDGET_S,
) -> tuple[KindScore, dict[str, Any]]:
    """Each kind's other-test Et (module docstring), and the chosen one with the report: every
    kind's Et, per test, block hold-out, work per frame and why the winner won. `deadline`
    (`time.perf_counter()`'s; default `CHOICE_BUDGET_S` from now): a kind that would not be
    scored by then is not tried (the first kind is scored whatever the budget); `started`: when
    the budget began (the report's budget and time spent count from it; default now).
    `not_built`: kinds left out and why (listed in the report); `cost_budget_s`: the work per
    frame a kind may take to be chosen (the daemon's: it refuses a model over it)."""
    t_start = time.perf_counter() if started is None else started
    end = t_start + CHOICE_BUDGET_S if deadline is None else deadline
    several = len(names) >= 2
    unit = one_test_unit(series)
    scores: list[KindScore] = []
    not_tried = dict(not_built or {})
    for kind in kinds:
        log.info("kind %s (%s): fitting and scoring", kind.name, kind.label)
        try:
            sc = _score_kind(
                kind,
                series,
                tests,
                names,
                holdout_fraction=holdout_fraction,
                max_folds=max_folds,
                seed=seed,
                deadline=end if scores else math.inf,  # the first kind is always scored
                cost_budget_s=cost_budget_s,
            )
        except OverBudget as exc:
            not_tried[kind.name] = f"not within the time budget: {exc}"
            log.info("kind %s: not tried (%s)", kind.name, exc)
            continue
        log.info(
            "kind %s: Et %.4f on the %s left out (block hold-out %.4f), work per frame %.0f us,"
            " %.0f s",
            sc.name,
            sc.et,
            "tests" if several else f"{unit}s",
            sc.block_et,
            sc.frame_cost_us,
            sc.seconds,
        )
        scores.append(sc)
    budget_us = cost_budget_s * 1e6
    best, why = pick_kind(scores, several, unit=unit, budget_us=budget_us)
    by_block, _ = (
        pick_kind(scores, several, key="block_et", unit=unit, budget_us=budget_us)
        if scores
        else (best, "")
    )
    folds = fold_count(len(names), max_folds)
    method = (
        f"{'leave-one-test-out' if len(names) <= max_folds else f'{max_folds}-fold over tests'}"
        f" over {len(names)} tests: each kind fitted on the other tests, scored on the test"
        " left out"
        if several
        else f"one test: its {unit}s of different character (amplitude, frequency, command"
        f" level) in {folds} groups, each left out in turn"
        + (" with its neighbours not trained on" if unit == "segment" else "")
        + "; each kind fitted on the rest (optimistic still: the same test)"
    )
    members = max((k.members for k in kinds), default=1)
    report = {
        "method": method,
        "estimate": "other tests" if several else f"{unit}s of different character",
        "fold_fit": f"MLPs {FOLD_ROWS}-{FOLD_MAX_ROWS} LM rows (the same work whatever the"
        f" size, each member's), <= {FOLD_EPOCHS} epochs,"
        + (
            f" the mean of {members} starts, each its own rows and stopping tests,"
            if members > 1
            else " one start,"
        )
        + f" early-stopped on every {STOP_EVERY}th"
        " test (segment) of the fold's training data; the GRU"
        " the seconds a fold may take; the twin as fitted",
        "optimistic": not several,
        "budget_s": end - t_start,
        "budget_us": cost_budget_s * 1e6,
        "kinds": [
            {
                "kind": s.name,
                "label": s.label,
                "et": s.et,
                "block_et": s.block_et,
                "per_group": s.per_group,
                "frame_cost_us": s.frame_cost_us,
                "in_budget": s.in_budget,
                "seconds": s.seconds,
                "folds": s.folds,
            }
            for s in scores
        ],
        "not_tried": not_tried,
        "chosen": {"kind": best.name, "label": best.label, "et": best.et, "why": why},
        "block_holdout_would_choose": by_block.name,
        "seconds": time.perf_counter() - t_start,
    }
    return best, report


def pick_kind(
    scores: list[KindScore],
    several: bool,
    key: str = "et",
    unit: str = "segment",
    budget_us: float = COST_BUDGET_S * 1e6,
) -> tuple[KindScore, str]:
    """The kind of the lowest Et (`key`: the other-test estimate, or "block_et") among those
    within the loop's budget (of all, where none is), and why it won; `unit`: what a single
    test is left out by (`crossval.one_test_unit`)."""
    scored = [s for s in scores if math.isfinite(getattr(s, key))]
    if not scored:
        raise ValueError("no kind of model could be scored")
    pool = [s for s in scored if s.in_budget] or scored
    best = min(pool, key=lambda s: getattr(s, key))
    return best, _why(best, scored, "test" if several else unit, budget_us)


def _why(best: KindScore, scored: list[KindScore], unit: str, budget_us: float) -> str:
    where = f"on the {unit}s left out"
    others = sorted((s for s in scored if s is not best), key=lambda s: s.et)
    text = f"the lowest Et {where} ({best.et:.4f})"
    in_budget = [s for s in others if s.in_budget]
    over = [s for s in others if not s.in_budget and s.et < best.et]
    if not best.in_budget:
        return text + " of kinds all over the loop's budget (the daemon refuses it)"
    text += f" of the kinds within the {budget_us:.0f} us work per frame"
    if in_budget:
        text += f"; next {in_budget[0].name} {in_budget[0].et:.4f}"
    if over:
        text += "; lower but over the budget: " + ", ".join(
            f"{s.name} {s.et:.4f} ({s.frame_cost_us:.0f} us)" for s in over
        )
    return text
