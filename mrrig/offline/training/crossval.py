"""Judging a model on tests it never saw: cross-validation that leaves whole tests out.

A file is a test (`stream.test_ids`). Each fold leaves its tests out whole: one test per fold
(leave-one-test-out) up to `MAX_FOLDS` tests, else `MAX_FOLDS` folds of tests dealt at random
(k-fold over tests, so the time stays bounded). The model is trained on the other tests by
the final model's own procedure (`fit.train_forward`: the time-block split and early stopping
on its block; one start, where the final model keeps the best of its restarts by the inverse,
not by the force) and scored by forward Et (eqs 41-43) on each left-out test.

A single test has no other test to judge on: it is cut into `SEGMENTS` contiguous segments,
each described by its character (`segment_character`: the displacement's amplitude, its
frequency, the command's level), and the segments are dealt into `SEGMENT_GROUPS` groups of
like character (ranked along the character's main direction), each group left out in turn: a
model is judged on a character it was not fitted on. Training never takes the neighbours of a
left-out segment: `GUARD_FRACTION` of a segment on each side of it is left out of that fold's
training too (`guard`). That is still the same test, its sensors and its conditions, so the
figure is optimistic too, if less than a block hold-out; only another test (`mrrig train
--validate FILE`) tells how a model holds elsewhere, and the report says so.

A single test of `MIN_RUNS` runs or more (a characterization matrix: one run per amplitude,
frequency and current) is left out run by run instead: its runs are dealt by the same
character into `SEGMENT_GROUPS` folds, and each run is scored and named in the report by its
place in the file and its condition (`run 7 (10 mm, 2.00 Hz, command 1 A)`). A run ends where
the next begins, so no guard is needed between them.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from mrrig.errors import MrrigError
from mrrig.loop.mlp import MLP
from mrrig.offline.datasets import Series
from mrrig.offline.training.data import run_ids, select
from mrrig.offline.training.features import features
from mrrig.offline.training.fit import train_forward
from mrrig.offline.training.report import EtSum, predict

log = logging.getLogger(__name__)

MAX_FOLDS = 40  # leave-one-test-out up to so many tests; k-fold over tests beyond
SEGMENTS = 8  # a single test is cut into so many segments,
SEGMENT_GROUPS = 4  # dealt by character into so many groups, each left out in turn
GUARD_FRACTION = 0.25  # of a segment, on each side of a left-out one, kept out of training
MIN_RUNS = SEGMENTS  # a single test of so many runs or more is left out run by run


def subset(series: Series, mask: np.ndarray) -> Series:
    """The samples of `mask`, a run with a hole becoming two runs (nothing, history or lag,
    carries across what was left out)."""
    idx = np.flatnonzero(mask)
    rid = run_ids(series)[idx]
    new = np.concatenate([[True], (np.diff(idx) > 1) | (rid[1:] != rid[:-1])])[: idx.size]
    return replace(select(series, idx), run_id=(np.cumsum(new) - 1).astype(int))


def segment_character(series: Series, group: np.ndarray, n: int) -> np.ndarray:
    """Each of the `n` segments' character (rows): the displacement's amplitude (standard
    deviation), its frequency (the velocity's RMS over the displacement's, rad/s) and the
    command's mean level."""
    out = np.zeros((n, 3))
    for j in range(n):
        m = group == j
        if not m.any():
            continue
        amp = float(np.std(series.x[m]))
        freq = float(np.sqrt(np.mean((series.xd[m] - series.xd[m].mean()) ** 2)))
        out[j] = (amp, freq / amp if amp > 0 else 0.0, float(np.mean(series.current[m])))
    return out


def character_groups(character: np.ndarray, groups: int) -> np.ndarray:
    """The group of each segment: ranked along the main direction of the standardized
    character (its first principal component) and dealt in runs of like character, so that a
    group left out differs from the segments trained on."""
    z = character - character.mean(axis=0)
    sd = z.std(axis=0)
    z = z[:, sd > 0] / sd[sd > 0]
    if z.shape[1] == 0:
        score = np.arange(len(character), dtype=float)
    else:
        score = z @ np.linalg.svd(z, full_matrices=False)[2][0]
    group = np.empty(len(character), dtype=int)
    group[np.argsort(score, kind="stable")] = np.arange(len(character)) * groups // len(character)
    return group


def one_test_unit(series: Series) -> str:
    """What a single test is left out by: "run" where it holds `MIN_RUNS` runs or more (a
    characterization matrix), else "segment"."""
    return "run" if np.unique(run_ids(series)).size >= MIN_RUNS else "segment"


def run_label(series: Series, rows: np.ndarray, k: int) -> str:
    """A run's name in the report: its place in the file (from 0, as `mrrig characterize`
    numbers its runs) and its condition: the displacement's peak amplitude (half its range,
    mm), its frequency (the velocity's RMS over the displacement's, Hz) and the command's mean
    level in its unit."""
    x, xd = series.x[rows], series.xd[rows]
    amp_mm = 0.5 * float(np.ptp(x)) * 1e3 if x.size else 0.0
    sx = float(np.std(x))
    freq = float(np.std(xd)) / sx / (2 * np.pi) if sx > 0 else 0.0
    level = float(np.mean(series.current[rows])) if rows.size else 0.0
    return f"run {k} ({amp_mm:.3g} mm, {freq:.2f} Hz, command {level:.3g} {series.current_unit})"


def leave_out_groups(
    series: Series, tests: np.ndarray, names: Sequence[str]
) -> tuple[np.ndarray, list[str], str]:
    """(group of each sample, the groups' labels, "test", "run" or "segment"): the tests; for
    a single test of `MIN_RUNS` runs or more, its runs (`run_label`; `run_folds` deals them
    into folds); else its `SEGMENTS` contiguous segments dealt by character into
    `SEGMENT_GROUPS`."""
    if len(names) >= 2:
        return np.asarray(tests, dtype=int), [str(n) for n in names], "test"
    name = names[0] if names else series.name
    if one_test_unit(series) == "run":
        _, run = np.unique(run_ids(series), return_inverse=True)
        labels = [
            f"{name} {run_label(series, np.flatnonzero(run == k), k)}"
            for k in range(int(run.max()) + 1)
        ]
        return run, labels, "run"
    n = len(series)
    segment = np.arange(n) * SEGMENTS // max(n, 1)
    char = segment_character(series, segment, SEGMENTS)
    by = character_groups(char, SEGMENT_GROUPS)
    labels = []
    for g in range(SEGMENT_GROUPS):
        parts = []
        for j in np.flatnonzero(by == g).tolist():
            t = series.t[segment == j]
            a, w, c = char[j]
            parts.append(
                f"{t[0]:.2f}-{t[-1]:.2f} s (amplitude {a:.3g}, {w / (2 * np.pi):.2f} Hz,"
                f" command {c:.3g})"
                if t.size
                else "empty"
            )
        labels.append(f"{name} segments {'; '.join(parts)}")
    return by[segment], labels, "segment"


def run_folds(series: Series, run: np.ndarray, n_runs: int, max_folds: int) -> np.ndarray:
    """Fold of each of a single test's runs (`leave_out_groups`' "run"): dealt by character
    (`segment_character`, `character_groups`) into `SEGMENT_GROUPS` folds, at most
    `max_folds`, so that a fold leaves out a character the others were not fitted on."""
    return character_groups(segment_character(series, run, n_runs), min(SEGMENT_GROUPS, max_folds))


def guard(out: np.ndarray, width: int) -> np.ndarray:
    """`out` (a mask over samples in time order) widened by `width` samples on each side: the
    neighbours of the left-out rows, kept out of training."""
    if width <= 0 or not out.any():
        return out
    edge = np.flatnonzero(np.diff(np.concatenate([[0], out.astype(np.int8), [0]])))
    wide = np.zeros(out.size + 1, dtype=np.int64)
    for a, b in zip(edge[0::2].tolist(), edge[1::2].tolist(), strict=True):
        wide[max(a - width, 0)] += 1
        wide[min(b + width, out.size)] -= 1
    return np.cumsum(wide[:-1]) > 0


class OverBudget(MrrigError):
    """A cross-validation whose folds would not end within its deadline (the message: the
    projection from the folds so far)."""


def fold_count(n_tests: int, max_folds: int = MAX_FOLDS) -> int:
    """The folds of `cross_validate_with` over `n_tests` tests (one: its segment groups)."""
    return min(n_tests, max_folds) if n_tests >= 2 else min(SEGMENT_GROUPS, max_folds)


def fold_of_groups(n_groups: int, max_folds: int = MAX_FOLDS, seed: int = 0) -> np.ndarray:
    """Fold of each group: its own up to `max_folds` groups, else dealt at random into
    `max_folds` folds."""
    if n_groups <= max_folds:
        return np.arange(n_groups)
    fold = np.empty(n_groups, dtype=int)
    fold[np.random.default_rng(seed).permutation(n_groups)] = np.arange(n_groups) % max_folds
    return fold


def cross_validate(
    series: Series,
    tests: np.ndarray,
    names: Sequence[str],
    options: dict[str, Any],
    *,
    max_folds: int = MAX_FOLDS,
    seed: int = 0,
    max_epochs: int = 1000,
) -> dict[str, Any]:
    """The other-test estimate (module docstring): Et of each left-out test (or segment) and
    overall (pooled over every left-out row: eqs 41-43 on them all; and the mean of the
    tests'). `options`: the feature and fit options of `train_forward` (current_input,
    lag_tau_s, history_samples, history_signals, history_stride, hidden, split,
    holdout_fraction)."""
    feat = {
        k: options[k]
        for k in (
            "current_input",
            "lag_tau_s",
            "history_samples",
            "history_signals",
            "history_stride",
        )
    }
    fit = {k: options[k] for k in ("split", "holdout_fraction", "history_stride", "hidden")}

    def train(part: Series) -> MLP:
        model, _ = train_forward(
            part,
            seed=seed,
            max_epochs=max_epochs,
            current_input=feat["current_input"],
            lag_tau_s=feat["lag_tau_s"],
            history_samples=feat["history_samples"],
            history_signals=feat["history_signals"],
            **fit,
        )
        return model

    def forces(model: MLP, held: Series) -> tuple[np.ndarray, np.ndarray]:
        X, y = features(held, **feat)
        return y, predict(model, X)

    return cross_validate_with(series, tests, names, train, forces, max_folds=max_folds, seed=seed)


def cross_validate_with(
    series: Series,
    tests: np.ndarray,
    names: Sequence[str],
    train: Callable[[Series], Any],
    forces: Callable[[Any, Series], tuple[np.ndarray, np.ndarray]],
    *,
    max_folds: int = MAX_FOLDS,
    seed: int = 0,
    deadline: float | None = None,
    how: str = "as the model is (one start)",
) -> dict[str, Any]:
    """`cross_validate` of any forward model: `train(series)` fits one on the other tests,
    `forces(model, held)` gives the (measured, predicted) force of a left-out test's rows.
    `deadline` (`time.perf_counter()`'s): after each fold, OverBudget is raised where the
    folds left, at the mean time of those done, would end after it. `how`: how each fold is
    trained, for the report."""
    t0 = time.perf_counter()
    group, labels, kind = leave_out_groups(series, tests, names)
    gap = round(GUARD_FRACTION * len(series) / SEGMENTS)
    if kind == "run":
        fold = run_folds(series, group, len(labels), max_folds)
    else:
        fold = fold_of_groups(len(labels), max_folds, seed)
    n_folds = int(fold.max()) + 1 if fold.size else 0
    per = [EtSum() for _ in labels]
    overall = EtSum()
    for k in range(n_folds):
        out = np.isin(group, np.flatnonzero(fold == k))
        if out.all() or not out.any():
            continue
        kept_out = guard(out, gap) if kind == "segment" else out
        if kept_out.all():
            continue
        model = train(subset(series, ~kept_out))
        for j in np.flatnonzero(fold == k).tolist():
            held = subset(series, group == j)
            if len(held) == 0:
                continue
            y, f = forces(model, held)
            per[j].add(y, f)
            overall.add(y, f)
        log.info(
            "fold %d of %d (%s left out): %s",
            k + 1,
            n_folds,
            ", ".join(labels[j] for j in np.flatnonzero(fold == k)),
            " ".join(f"{per[j].numbers()['et']:.4f}" for j in np.flatnonzero(fold == k)),
        )
        spent, left = time.perf_counter() - t0, n_folds - k - 1
        each = spent / (k + 1)
        if deadline is not None and left and time.perf_counter() + each * left > deadline:
            raise OverBudget(
                f"its {n_folds} folds would take about {each * n_folds:.0f} s"
                f" ({each:.0f} s each), over the budget"
                f" ({max(deadline - t0, 0.0):.0f} s were left for it)"
            )
    rows = [{kind: label, **s.numbers()} for label, s in zip(labels, per, strict=True)]
    ets = [r["et"] for r in rows if r["n"] and math.isfinite(r["et"])]
    if kind == "run":
        folds_text = (
            f"{n_folds} folds over the {len(labels)} runs of one test (dealt by character:"
            " amplitude, frequency and command level)"
        )
    elif n_folds == len(labels):
        folds_text = f"leave-one-{kind}-out ({n_folds} folds)"
    else:
        folds_text = f"{n_folds}-fold over {len(labels)} {kind}s (dealt at random, seed {seed})"
    method = (
        folds_text + f": each fold trained on the others {how}, scored on the {kind}s it left out"
    )
    if kind == "segment":
        method += (
            f" ({SEGMENTS} segments dealt by character, amplitude, frequency and command"
            f" level, into {len(labels)} groups; {GUARD_FRACTION:.0%} of a segment each side"
            " of the left-out ones not trained on)"
        )
    return {
        "kind": kind,
        "method": method,
        "optimistic": kind != "test",
        "folds": n_folds,
        "per_group": rows,
        "overall": overall.numbers(),
        "mean_et": float(np.mean(ets)) if ets else math.nan,
        "seconds": time.perf_counter() - t0,
    }
