"""Choosing the forward network's structure from the data (`mrrig train --features auto`).

Cross-validation on the TRAINING rows only: the hold-out of every candidate (the last part
of each run, `fit.block_split`) is set aside first; with several tests each fold is whole
tests (`crossval.fold_of_groups`: a structure is judged on tests it never saw), with one test
the rest of each run is cut into `FOLDS` contiguous blocks. Each candidate is fitted on the
other folds (a coverage subsample of `equal_work_rows`: the LM work of `SEARCH_FIT_ROWS` rows
of a 12-30-1 network whatever the candidate's size, so that a larger one is not favoured by
more work; at most `SEARCH_EPOCHS` LM epochs)
and scored by Et on each fold in turn. The search is staged, each stage keeping the best so
far: the command input (as commanded, or lagged with the time constant `features.fit_lag_tau`
finds), then the history (depth in time, and its signals; then twice the taps over the best
span), then the hidden size. A candidate whose real-time inversion
(`inversion.ScalarInverter.solve`, one sample, as the daemon solves) takes more than
`INVERSION_BUDGET_US` median is not chosen. Measured force is never an input: past force
would make the inversion for the present current ill-posed.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from mrrig.loop.inversion import ScalarInverter
from mrrig.loop.mlp import MLP
from mrrig.offline.datasets import Series
from mrrig.offline.metrics import error_norm
from mrrig.offline.training.crossval import fold_of_groups
from mrrig.offline.training.data import run_ids, sample_period, stretch_bounds, stretches
from mrrig.offline.training.features import (
    COIL_LAG_TAU_S,
    feature_names,
    feature_rows,
    features,
    fit_lag_tau,
)
from mrrig.offline.training.fit import HOLDOUT_FRACTION, block_split, coverage_subsample
from mrrig.offline.training.lm import train_lm
from mrrig.offline.training.report import predict

log = logging.getLogger(__name__)

FOLDS = 3
SEARCH_FIT_ROWS = 3000
SEARCH_WORK = SEARCH_FIT_ROWS * 421**2  # LM work, rows x weights^2 (a 12-30-1 MLP has 421)
SEARCH_MIN_ROWS, SEARCH_MAX_ROWS = 1500, 12771
SEARCH_EPOCHS = 120
INVERSION_BUDGET_US = 20.0
INVERSION_REPEATS = 7  # each row's inversion timed so often, its smallest time kept
INVERSION_ROUNDS = 3  # rounds of repeats at most before a candidate is over the budget
# history depth in time, taps over this span (the longer ones for slow data: 100 Hz sines)
HISTORY_SPANS_S = (0.01, 0.02, 0.04, 0.08, 0.16)
HISTORY_TAPS = 4
HISTORY_SIGNAL_SETS = (("x", "xd"), ("x", "xd", "current"))
HIDDEN_SIZES = (20, 30, 40)
SEARCH_BUDGET_S = 900.0  # candidates left when this is spent are not tried (the report says)
COMMAND_VARIES_FRACTION = 0.01  # a run's command spread over this fraction of the range


@dataclass(frozen=True)
class Candidate:
    current_input: str = "commanded"
    lag_tau_s: float = COIL_LAG_TAU_S
    history_samples: int = 0
    history_signals: tuple[str, ...] = ("x", "xd")
    history_stride: int = 1
    hidden: int = 30

    def label(self, dt_s: float) -> str:
        cur = (
            f"lagged {self.lag_tau_s * 1e3:.2f} ms"
            if self.current_input == "lagged"
            else "commanded"
        )
        hist = "no history"
        if self.history_samples:
            span = self.history_samples * self.history_stride * dt_s * 1e3
            hist = (
                f"history {self.history_samples} taps over {span:.0f} ms of"
                f" {','.join(self.history_signals)}"
            )
        return f"{cur}, {hist}, {self.hidden} hidden"

    def depth(self) -> int:
        return self.history_samples * self.history_stride


def equal_work_rows(cand: Candidate, work: float, low: int, high: int) -> int:
    """LM rows for the candidate's network that cost `work` (rows x weights^2, an LM epoch's
    cost), within [low, high]."""
    weights = cand.hidden * (4 + cand.history_samples * len(cand.history_signals) + 2) + 1
    return int(np.clip(work // weights**2, low, high))


def command_varies(series: Series) -> bool:
    """Whether the command changes within runs (random or stepped commands) rather than being
    held per run (the characterization matrix): only then do its lag and past matter."""
    span = float(np.ptp(series.current)) if len(series) else 0.0
    if span == 0.0:
        return False
    first, length = stretch_bounds(stretches(run_ids(series)))
    for f, n in zip(first.tolist(), length.tolist(), strict=True):
        if np.std(series.current[f : f + n]) > COMMAND_VARIES_FRACTION * span:
            return True
    return False


def _inversion_us(
    model: MLP,
    X: np.ndarray,
    y: np.ndarray,
    repeats: int = INVERSION_REPEATS,
    budget_us: float = INVERSION_BUDGET_US,
    rounds: int = INVERSION_ROUNDS,
) -> tuple[float, float]:
    """(real-time, full) median CPU time (us) of one inversion by `ScalarInverter` (continuity
    0.03, from the previous answer) over up to 300 consecutive rows. Each row is solved
    `repeats` times and its smallest time kept: the machine's other load (and a VM's stolen
    time, which counts as this thread's) only adds. A real-time median over `budget_us` is
    measured again, up to `rounds` rounds in all, each row's smallest over all of them kept:
    on a busy machine the load can last as long as a round. Real-time is the daemon's
    per-frame path: the solve prepared ahead (`prepare`, while it waits for the frame) on a
    prediction, here the previous row's state with this row's force (a worse prediction than
    the daemon's Kalman one), then `solve` on the row. Full is `solve` without anything
    prepared."""
    c = model.current_index
    rows = np.arange(min(300, X.shape[0]))
    feats = np.delete(X[rows], c, axis=1)
    f_des = y[rows].tolist()
    i_max = float(max(X[:, c].max(), 1e-9))
    times = np.full((2, rows.size - 1), np.inf)
    for _ in range(rounds):
        for _ in range(repeats):
            for j, ahead in enumerate((True, False)):
                inv = ScalarInverter(model, i_max, continuity=0.03)
                prev = 0.0
                for k in range(1, rows.size):
                    if ahead:
                        inv.prepare(feats[k - 1], f_des[k], prev)
                    t0 = time.thread_time()
                    prev = inv.solve(feats[k], f_des[k], prev)
                    times[j, k - 1] = min(times[j, k - 1], time.thread_time() - t0)
        med = np.median(times, axis=1) * 1e6
        if med[0] <= budget_us:
            break
    return float(med[0]), float(med[1])


def _series_rows(series: Series, cand: Candidate) -> tuple[np.ndarray, np.ndarray]:
    """(series index of each feature row, stretch of each) for a candidate."""
    rows = feature_rows(series, cand.history_samples, cand.history_stride)
    return rows, stretches(run_ids(series))[rows]


def _folds(
    series: Series,
    cands: list[Candidate],
    fraction: float,
    tests: np.ndarray | None = None,
    seed: int = 0,
) -> np.ndarray:
    """Fold number (0..FOLDS-1) of each series sample, -1 for samples outside the search:
    any candidate's hold-out, and rows without the deepest candidate's history. With
    several tests (`tests`: each sample's), a fold is whole tests (`FOLDS` folds of tests
    dealt at random, or one per test where fewer), else a time block of each run."""
    n = len(series)
    usable = np.zeros(n, dtype=bool)
    usable[_series_rows(series, max(cands, key=Candidate.depth))[0]] = True
    for c in cands:
        rows, st = _series_rows(series, c)
        usable[rows[block_split(st, fraction).val]] = False
    fold = np.full(n, -1)
    if tests is not None and np.unique(tests).size >= 2:
        by_test = fold_of_groups(int(tests.max()) + 1, FOLDS, seed)
        fold[usable] = by_test[tests[usable]]
        return fold
    idx = np.flatnonzero(usable)
    first, length = stretch_bounds(stretches(run_ids(series))[idx])
    for f, m in zip(first.tolist(), length.tolist(), strict=True):
        fold[idx[f : f + m]] = np.minimum(np.arange(m) * FOLDS // max(m, 1), FOLDS - 1)
    return fold


def _score(series: Series, cand: Candidate, fold: np.ndarray, seed: int) -> dict[str, Any]:
    """Blocked CV Et of a candidate (mean over folds), with the last fold's model's timing."""
    opts = (
        cand.current_input,
        cand.lag_tau_s,
        cand.history_samples,
        cand.history_signals,
        cand.history_stride,
    )
    X, y = features(series, *opts)
    rows, _ = _series_rows(series, cand)
    f_of = fold[rows]
    names, units = feature_names(
        cand.history_samples, cand.history_signals, cand.history_stride, series.current_unit
    )
    ets, model = [], None
    t0 = time.perf_counter()
    for k in range(int(fold.max()) + 1):
        test = np.flatnonzero(f_of == k)
        train = np.flatnonzero((f_of >= 0) & (f_of != k))
        rows = equal_work_rows(cand, SEARCH_WORK, SEARCH_MIN_ROWS, SEARCH_MAX_ROWS)
        fit = coverage_subsample(X, train, rows, seed)
        stop = test[np.linspace(0, test.size - 1, min(test.size, 2000)).astype(int)]
        model, _ = train_lm(
            X[fit],
            y[fit],
            names,
            units,
            "force",
            "N",
            hidden=cand.hidden,
            validation=(X[stop], y[stop]),
            max_epochs=SEARCH_EPOCHS,
            seed=seed,
        )
        ets.append(error_norm(y[test], predict(model, X[test])))
    assert model is not None
    return {
        "et_folds": ets,
        "et": float(np.mean(ets)),
        "seconds": time.perf_counter() - t0,
        "model": model,
        "X": X,
        "y": y,
    }


def choose_features(
    series: Series,
    seed: int = 0,
    holdout_fraction: float = HOLDOUT_FRACTION,
    budget_s: float = SEARCH_BUDGET_S,
    tests: np.ndarray | None = None,
) -> tuple[Candidate, dict[str, Any]]:
    """The structure chosen by CV on the training blocks (module docstring) and the report:
    every candidate's fold Ets, mean, inversion time and whether it was in budget. With
    several tests (`tests`: each sample's test), the folds leave whole tests out."""
    t_start = time.perf_counter()
    first, length = stretch_bounds(stretches(run_ids(series)))
    dt = sample_period(series.t[first[0] : first[0] + length[0]]) if len(series) > 1 else 1.0
    varies = command_varies(series)
    base = Candidate()
    # all candidates' depths are known up front: the folds exclude every one's hold-out
    strides = {s: max(1, round(s / HISTORY_TAPS / dt)) for s in HISTORY_SPANS_S}
    hist = list(  # spans that give the same taps at this rate are one candidate
        dict.fromkeys(
            (HISTORY_TAPS, sig, strides[s])
            for s in HISTORY_SPANS_S
            for sig in HISTORY_SIGNAL_SETS
            if varies or "current" not in sig
        )
    )
    deepest = max(
        [base]
        + [Candidate(history_samples=h, history_signals=g, history_stride=st) for h, g, st in hist],
        key=Candidate.depth,
    )
    fold = _folds(series, [base, deepest], holdout_fraction, tests, seed)
    n_folds = int(fold.max()) + 1
    results: list[dict[str, Any]] = []
    skipped: list[str] = []

    def trial(c: Candidate) -> dict[str, Any] | None:
        if time.perf_counter() - t_start > budget_s:
            skipped.append(c.label(dt))
            log.info("search budget spent: %s not tried", c.label(dt))
            return None
        r = _score(series, c, fold, seed)
        r["candidate"] = c
        r["inversion_us"], r["inversion_full_us"] = _inversion_us(r["model"], r["X"], r["y"])
        r["in_budget"] = r["inversion_us"] <= INVERSION_BUDGET_US
        results.append(r)
        log.info(
            "candidate %s: blocked-CV Et %.4f (folds %s), inversion %.1f us (full %.1f), %.0f s",
            c.label(dt),
            r["et"],
            " ".join(f"{e:.4f}" for e in r["et_folds"]),
            r["inversion_us"],
            r["inversion_full_us"],
            r["seconds"],
        )
        return r

    def best_of(rs: list[dict[str, Any] | None]) -> dict[str, Any]:
        ok = [r for r in rs if r is not None]
        pool = [r for r in ok if r["in_budget"]] or ok
        return min(pool, key=lambda r: r["et"])

    lag = None
    stage = [trial(base)]
    if varies:
        fit_idx = np.flatnonzero(fold >= 0)
        tau, resid = fit_lag_tau(series, fit_idx, seed)
        lag = {"tau_s": tau, "proxy_rmse_n": resid}
        log.info(
            "command lag fitted by 1-D search: tau %.2f ms (proxy RMSE %.1f N)", tau * 1e3, resid
        )
        stage.append(trial(replace(base, current_input="lagged", lag_tau_s=tau)))
    best = best_of(stage)
    stage = [best] + [
        trial(replace(best["candidate"], history_samples=h, history_signals=g, history_stride=st))
        for h, g, st in hist
    ]
    best = best_of(stage)
    b = best["candidate"]
    if b.history_samples and b.history_stride > 1:  # the same span, twice the taps
        more = replace(
            b, history_samples=2 * b.history_samples, history_stride=b.history_stride // 2
        )
        best = best_of([best, trial(more)])
    stage = [best] + [
        trial(replace(best["candidate"], hidden=h))
        for h in HIDDEN_SIZES
        if h != best["candidate"].hidden
    ]
    best = best_of(stage)
    chosen: Candidate = best["candidate"]
    report = {
        "method": (
            f"{n_folds}-fold cross-validation over whole tests"
            if tests is not None and np.unique(tests).size >= 2
            else f"blocked {n_folds}-fold cross-validation"
        )
        + f" on the training blocks ({SEARCH_MIN_ROWS}-{SEARCH_MAX_ROWS} LM rows, the work of"
        f" {SEARCH_FIT_ROWS} of a 12-30-1 network, <= {SEARCH_EPOCHS} epochs"
        " per fit); hold-out unused",
        "command_varies": varies,
        "lag_fit": lag,
        "inversion_budget_us": INVERSION_BUDGET_US,
        "candidates": [
            {
                "label": r["candidate"].label(dt),
                **asdict(r["candidate"]),
                "cv_et": r["et"],
                "cv_et_folds": r["et_folds"],
                "inversion_us": r["inversion_us"],
                "inversion_full_us": r["inversion_full_us"],
                "in_budget": r["in_budget"],
            }
            for r in results
        ],
        "not_tried": skipped,
        "chosen": {"label": chosen.label(dt), **asdict(chosen), "cv_et": best["et"]},
        "seconds": time.perf_counter() - t_start,
    }
    return chosen, report
