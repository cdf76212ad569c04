"""The files around the fit: measured data in (the training stage's readers, its bad-stretch
exclusion), the fit (`fit`: bounded, from several starts), Et per test, and the plant file out
(`damper.plant_file`).

The data is used as measured: the displacement and velocity of the file (velocity by the
Kalman filter only where the file has none), the command in its own unit. Where tests are
held out (`holdout`), Et on each is the figure to judge the twin by. Without them, each test is
cut into segments as `mrrig train`'s other-test estimate on one test cuts it
(`training.crossval`: `SEGMENTS` contiguous segments dealt by character, the displacement's
amplitude, its frequency and the command's level, into `SEGMENT_GROUPS` groups); the group most
unlike the others (`most_unlike`) is left out of the fit, with `GUARD_FRACTION` of a segment on
each side of its segments (the guard bands: their neighbours are not fitted either), and the
fitted set's Et on it is the estimate printed: a character the fit never saw, still the same
test's sensors and conditions (optimistic next to another test, and labelled so).

Et is scored with the twin run open loop over each whole run from rest, a run that starts
moving scored after its warm-up stretch (`fit.warm_rows`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from damper.plant import BoucWenParams
from damper.plant_file import Plant, load_plant
from mrrig.offline.datasets import Series
from mrrig.offline.identify.fit import (
    BOUNDS,
    FREE,
    STARTS,
    WARMUP_S,
    Run,
    fit,
    run_force,
    warm_rows,
)
from mrrig.offline.metrics import error_norm
from mrrig.offline.training.crossval import (
    GUARD_FRACTION,
    SEGMENT_GROUPS,
    SEGMENTS,
    character_groups,
    guard,
    segment_character,
)
from mrrig.offline.training.data import (
    estimate_derivatives,
    exclude_bad_stretches,
    load_file,
    run_ids,
)
from mrrig.offline.training.report import EtSum
from mrrig.offline.training.select import COMMAND_VARIES_FRACTION

log = logging.getLogger(__name__)

SUBSTEP_S = 1e-4  # the simulator's sub-step (configs/sim.toml damper.substep_s)


@dataclass
class Test:
    """One data file: its runs (bad stretches cut out), which rows the fit may use, and which
    are scored as not fitted (the segments left out; every row of a test held out)."""

    path: Path
    runs: list[Run]
    fit_rows: list[np.ndarray]
    held_rows: list[np.ndarray]
    command_unit: str
    excluded: dict[str, Any]
    held_label: str = ""  # the segments left out, where they are

    @property
    def samples(self) -> int:
        return sum(r.t.size for r in self.runs)


def most_unlike(character: np.ndarray, group: np.ndarray) -> int:
    """The group whose segments' mean standardized character (`crossval.segment_character`)
    lies farthest from the other segments' mean; the last where the character does not vary."""
    z = character - character.mean(axis=0)
    sd = z.std(axis=0)
    z = z[:, sd > 0] / sd[sd > 0]
    groups = int(group.max()) + 1
    if z.shape[1] == 0:
        return groups - 1
    gap = [
        float(np.linalg.norm(z[group == g].mean(0) - z[group != g].mean(0))) for g in range(groups)
    ]
    return int(np.argmax(gap))


def left_out_segments(series: Series) -> tuple[np.ndarray, np.ndarray, str]:
    """(rows held out, rows the fit may use, what was held out) of one test: its `SEGMENTS`
    segments dealt by character into `SEGMENT_GROUPS` groups, the `most_unlike` group held
    out and `GUARD_FRACTION` of a segment each side of its segments kept out of the fit."""
    n = len(series)
    segment = np.arange(n) * SEGMENTS // n
    char = segment_character(series, segment, SEGMENTS)
    group = character_groups(char, SEGMENT_GROUPS)
    out = most_unlike(char, group)
    held = np.isin(segment, np.flatnonzero(group == out))
    fit_rows = ~guard(held, round(GUARD_FRACTION * n / SEGMENTS))
    parts = []
    for j in np.flatnonzero(group == out).tolist():
        t = series.t[segment == j]
        a, w, c = char[j]
        parts.append(
            f"{t[0]:.2f}-{t[-1]:.2f} s (amplitude {a * 1e3:.3g} mm, {w / (2 * np.pi):.2f} Hz,"
            f" command {c:.3g} {series.current_unit})"
        )
    return held, fit_rows, "; ".join(parts)


def load_test(path: Path, fit: bool, segments: bool = True) -> Test:
    """A file as runs in SI units; with `fit`, the fit's rows are all but its segments left
    out and their guard bands (`left_out_segments`; all of them without `segments`), else the
    whole test is held out."""
    s = load_file(path)
    if s.xd is None:
        s = estimate_derivatives(s)
    s, excluded = exclude_bad_stretches(s)
    if len(s) < 3:
        raise ValueError(f"{path}: fewer than 3 samples left after the bad stretches")
    if fit and segments:
        if len(s) < 3 * SEGMENTS:
            raise ValueError(
                f"{path}: {len(s)} samples, too few to hold {SEGMENTS} segments out of the fit"
                " (give a longer test, or tests to --holdout)"
            )
        held, fit_mask, label = left_out_segments(s)
    elif fit:
        held, fit_mask, label = np.zeros(len(s), dtype=bool), np.ones(len(s), dtype=bool), ""
    else:
        held, fit_mask, label = np.ones(len(s), dtype=bool), np.zeros(len(s), dtype=bool), ""
    rid = run_ids(s)
    runs, fit_rows, held_rows = [], [], []
    for r in np.unique(rid):
        m = rid == r
        if m.sum() >= 3:
            runs.append(Run(s.t[m], s.x[m], s.xd[m], s.current[m], s.force[m], path.name))
            fit_rows.append(fit_mask[m])
            held_rows.append(held[m])
    return Test(path, runs, fit_rows, held_rows, s.current_unit, excluded, label)


def start_plant(source: str) -> Plant:
    """Where the fit starts: `paper` (Table 3, command in volts) or a plant file."""
    if source == "paper":
        return Plant(BoucWenParams.preset("paper-volt"), 0.0, "V")
    return load_plant(source)


def identify(
    data: Sequence[Path],
    holdout: Sequence[Path] = (),
    start: str = "paper",
    max_evaluations: int = 60,
    progress: Callable[[str], None] = log.info,
    starts: int = STARTS,
    seed: int = 0,
) -> tuple[Plant, dict[str, Any]]:
    """Fit the twin to `data` (from `starts` starts, `seed`), judge it on `holdout` (or, where
    no test is held out, on each file's segments left out of the fit: `left_out_segments`);
    returns the plant and the report."""
    if not data:
        raise ValueError("no data files given")
    tests = [load_test(Path(p), True, segments=not holdout) for p in data]
    others = [load_test(Path(p), False) for p in holdout]
    units = {t.command_unit for t in tests + others}
    if len(units) > 1:
        raise ValueError(f"commands in different units ({', '.join(sorted(units))})")
    unit = units.pop()
    first = start_plant(start)
    if first.command_unit != unit:
        log.warning(
            "%s: the start's command is in %s, the data's in %s: the fit starts from its numbers "
            "taken per %s",
            start,
            first.command_unit,
            unit,
            unit,
        )
    runs = [r for t in tests for r in t.runs]
    rows = [m for t in tests for m in t.fit_rows]
    offset0 = float(np.mean(np.concatenate([r.force[m] for r, m in zip(runs, rows, strict=True)])))
    free = FREE if command_varies(runs) else tuple(n for n in FREE if n != "eta")
    if "eta" not in free:
        progress(f"eta held at the start's {first.params.eta:g} 1/s: the command is held per run")
    for t in tests:
        if t.held_label:
            progress(f"{t.path.name}: left out of the fit, the segments {t.held_label}")
    progress(
        f"fitting {len(free) + 1} parameters to {sum(int(m.sum()) for m in rows)} samples of "
        f"{len(tests)} test(s), from {start} and {starts - 1} start(s) drawn around it"
        f" (seed {seed})"
    )
    result = fit(
        runs,
        rows,
        first.params,
        offset0,
        max_evaluations=max_evaluations,
        progress=progress,
        free=free,
        starts=starts,
        seed=seed,
    )
    per_test, held_sum = [], EtSum()
    for t in tests + others:
        fitted = [run_force(result.params, result.offset_n, r, SUBSTEP_S) for r in t.runs]
        force = np.concatenate(fitted)
        measured = np.concatenate([r.force for r in t.runs])
        warm = np.concatenate([warm_rows(r) for r in t.runs])
        fit_mask = np.concatenate(t.fit_rows) & warm
        held = np.concatenate(t.held_rows) & warm
        entry = {
            "file": str(t.path),
            "samples": t.samples,
            "excluded": t.excluded["excluded_samples"],
            "warmup_samples": int((~warm).sum()),
        }
        if t in tests:
            entry["et_fitted_rows"] = _et(measured, force, fit_mask)
        if held.any():
            held_sum.add(measured[held], force[held])
            key = "et_segments_not_fitted" if t in tests else "et_holdout_test"
            entry[key] = _et(measured, force, held)
            entry["held_out" if t in tests else "held_out_samples"] = (
                t.held_label if t in tests else int(held.sum())
            )
        per_test.append(entry)
    estimate = held_sum.numbers()
    report = {
        "start": start,
        "starts": starts,
        "seed": seed,
        "start_ets_fitted_rows": list(result.start_ets),
        "chosen_start": result.chosen_start + 1,
        "free_parameters": [*free, "offset_n"],
        "bounds": {n: list(BOUNDS[n]) for n in free},
        "at_bounds": list(result.at_bounds),
        "evaluations": result.evaluations,
        "seconds": result.seconds,
        "status": result.status,
        "et_start_fitted_rows": result.start_et,
        "et_fitted_rows_objective": result.cost_et,
        "estimate": {
            "et": estimate["et"],
            "on": "tests held out" if holdout else "segments not fitted",
            "method": _method(bool(holdout)),
        },
        "warmup_s": WARMUP_S,
        "tests": per_test,
    }
    plant = Plant(result.params, result.offset_n, unit, _finite(report))
    return plant, report


def command_varies(runs: Sequence[Run]) -> bool:
    """Whether the command changes within runs rather than being held per run (as
    `training.select.command_varies` tells it of a Series): only then can the fit tell eq.
    36's lag; held, eta would go anywhere (and slow the fit where it goes fast)."""
    span = float(np.ptp(np.concatenate([r.command for r in runs])))
    return span > 0.0 and any(
        float(np.std(r.command)) > COMMAND_VARIES_FRACTION * span for r in runs
    )


def _method(tests: bool) -> str:
    """How the printed estimate was made, for the report."""
    if tests:
        return "the tests given to --holdout, never fitted"
    return (
        f"each test cut into {SEGMENTS} contiguous segments dealt by character (the"
        f" displacement's amplitude, its frequency, the command's level) into {SEGMENT_GROUPS}"
        f" groups; the group most unlike the others left out of the fit, and"
        f" {GUARD_FRACTION:.0%} of a segment each side of its segments (guard bands); still the"
        " same test's sensors and conditions: optimistic next to another test"
    )


def _et(measured: np.ndarray, force: np.ndarray, rows: np.ndarray) -> float:
    """Et (eqs 41-43) of the twin's force on `rows`; NaN where there are none."""
    return error_norm(measured[rows], force[rows]) if rows.any() else math.nan


def _finite(value: Any) -> Any:
    """The report with every undefined number as None (the plant file is strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value
