"""Judging a model on tests it never saw: cross-validation that leaves whole tests out.

A file is a test (`stream.test_ids`). Each fold leaves its tests out whole: one test per fold
(leave-one-test-out) up to `MAX_FOLDS` tests, else `MAX_FOLDS` folds of tests dealt at random
(k-fold over tests, so the time stays bounded). The model is trained on the other tests by
the final model's own procedure (`fit.train_forward`: the time-block split and early stopping
on its block; one start, where the final model keeps the best of its restarts by the inverse,
not by the force) and scored by forward Et (eqs 41-43) on each left-out test.

A single test has no other test to judge on: it is cut into `SEGMENTS` contiguous segments,
each left out whole in turn. That is still the same test, its signals and its conditions, so
the figure is optimistic too; only another test (`mrrig train --validate FILE`) tells how a
model holds elsewhere, and the report says so.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from mrrig.loop.mlp import MLP
from mrrig.offline.datasets import Series
from mrrig.offline.training.data import run_ids, select
from mrrig.offline.training.features import features
from mrrig.offline.training.fit import train_forward
from mrrig.offline.training.report import EtSum, predict

log = logging.getLogger(__name__)

MAX_FOLDS = 40  # leave-one-test-out up to so many tests; k-fold over tests beyond
SEGMENTS = 4  # a single test is cut into so many segments, each left out in turn


def subset(series: Series, mask: np.ndarray) -> Series:
    """The samples of `mask`, a run with a hole becoming two runs (nothing, history or lag,
    carries across what was left out)."""
    idx = np.flatnonzero(mask)
    rid = run_ids(series)[idx]
    new = np.concatenate([[True], (np.diff(idx) > 1) | (rid[1:] != rid[:-1])])[: idx.size]
    return replace(select(series, idx), run_id=(np.cumsum(new) - 1).astype(int))


def leave_out_groups(
    series: Series, tests: np.ndarray, names: Sequence[str]
) -> tuple[np.ndarray, list[str], str]:
    """(group of each sample, the groups' labels, "test" or "segment"): the tests, or for a
    single test its `SEGMENTS` contiguous segments."""
    if len(names) >= 2:
        return np.asarray(tests, dtype=int), [str(n) for n in names], "test"
    n = len(series)
    group = np.arange(n) * SEGMENTS // max(n, 1)
    labels = []
    for j in range(SEGMENTS):
        t = series.t[group == j]
        span = f"{t[0]:.2f}-{t[-1]:.2f} s" if t.size else "empty"
        labels.append(f"{names[0] if names else series.name} segment {j + 1} ({span})")
    return group, labels, "segment"


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
) -> dict[str, Any]:
    """`cross_validate` of any forward model: `train(series)` fits one on the other tests,
    `forces(model, held)` gives the (measured, predicted) force of a left-out test's rows."""
    t0 = time.perf_counter()
    group, labels, kind = leave_out_groups(series, tests, names)
    fold = fold_of_groups(len(labels), max_folds, seed)
    n_folds = int(fold.max()) + 1 if fold.size else 0
    per = [EtSum() for _ in labels]
    overall = EtSum()
    for k in range(n_folds):
        out = np.isin(group, np.flatnonzero(fold == k))
        if out.all() or not out.any():
            continue
        model = train(subset(series, ~out))
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
    rows = [{kind: label, **s.numbers()} for label, s in zip(labels, per, strict=True)]
    ets = [r["et"] for r in rows if r["n"] and math.isfinite(r["et"])]
    folds_text = (
        f"leave-one-{kind}-out ({n_folds} folds)"
        if n_folds == len(labels)
        else f"{n_folds}-fold over {len(labels)} {kind}s (dealt at random, seed {seed})"
    )
    return {
        "kind": kind,
        "method": folds_text
        + ": each fold trained on the others as the model is (one start), scored on the"
        f" {kind}s it left out",
        "optimistic": kind == "segment",
        "folds": n_folds,
        "per_group": rows,
        "overall": overall.numbers(),
        "mean_et": float(np.mean(ets)) if ets else math.nan,
        "seconds": time.perf_counter() - t0,
    }
