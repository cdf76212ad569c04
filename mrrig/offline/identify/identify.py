"""The files around the fit: measured data in (the training stage's readers, its bad-stretch
exclusion), the fit (`fit`), Et per test, and the plant file out (`damper.plant_file`).

The data is used as measured: the displacement and velocity of the file (velocity by the
Kalman filter only where the file has none), the command in its own unit. Where tests are
held out (`holdout`), Et on each is the figure to judge the twin by; without them, the last
`holdout_fraction` of each test is held out instead, a figure that looks better than another
test would (neighbouring samples of one test are alike), and labelled so.
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
from mrrig.offline.identify.fit import FREE, Run, fit, run_force
from mrrig.offline.metrics import error_norm
from mrrig.offline.training.data import (
    estimate_derivatives,
    exclude_bad_stretches,
    load_file,
    run_ids,
)

log = logging.getLogger(__name__)

HOLDOUT_FRACTION = 0.15
SUBSTEP_S = 1e-4  # the simulator's sub-step (configs/sim.toml damper.substep_s)


@dataclass
class Test:
    """One data file: its runs (bad stretches cut out) and which rows the fit may use."""

    path: Path
    runs: list[Run]
    fit_rows: list[np.ndarray]
    command_unit: str
    excluded: dict[str, Any]

    @property
    def samples(self) -> int:
        return sum(r.t.size for r in self.runs)


def load_test(path: Path, holdout_fraction: float, fit: bool) -> Test:
    """A file as runs in SI units; with `fit`, all but its last `holdout_fraction` of samples
    are the fit's rows, else none."""
    s = load_file(path)
    if s.xd is None:
        s = estimate_derivatives(s)
    s, excluded = exclude_bad_stretches(s)
    if len(s) < 3:
        raise ValueError(f"{path}: fewer than 3 samples left after the bad stretches")
    rid = run_ids(s)
    runs = []
    for r in np.unique(rid):
        m = rid == r
        if m.sum() >= 3:
            runs.append(Run(s.t[m], s.x[m], s.xd[m], s.current[m], s.force[m], path.name))
    n = sum(r.t.size for r in runs)
    cut = n - round(holdout_fraction * n) if fit else 0
    rows, first = [], 0
    for r in runs:
        rows.append(first + np.arange(r.t.size) < cut)
        first += r.t.size
    return Test(path, runs, rows, s.current_unit, excluded)


def start_plant(source: str) -> Plant:
    """Where the fit starts: `paper` (Table 3, command in volts) or a plant file."""
    if source == "paper":
        return Plant(BoucWenParams.preset("paper-volt"), 0.0, "V")
    return load_plant(source)


def identify(
    data: Sequence[Path],
    holdout: Sequence[Path] = (),
    start: str = "paper",
    holdout_fraction: float = HOLDOUT_FRACTION,
    max_evaluations: int = 60,
    progress: Callable[[str], None] = log.info,
) -> tuple[Plant, dict[str, Any]]:
    """Fit the twin to `data`, judge it on `holdout` (or on each file's last
    `holdout_fraction` where no test is held out); returns the plant and the report."""
    if not data:
        raise ValueError("no data files given")
    block = holdout_fraction if not holdout else 0.0
    tests = [load_test(Path(p), block, True) for p in data]
    others = [load_test(Path(p), 0.0, False) for p in holdout]
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
    progress(
        f"fitting {len(FREE) + 1} parameters to {sum(int(m.sum()) for m in rows)} samples of "
        f"{len(tests)} test(s), from {start}"
    )
    result = fit(
        runs, rows, first.params, offset0, max_evaluations=max_evaluations, progress=progress
    )
    per_test = []
    for t in tests + others:
        fitted = [run_force(result.params, result.offset_n, r, SUBSTEP_S) for r in t.runs]
        force = np.concatenate(fitted)
        measured = np.concatenate([r.force for r in t.runs])
        mask = np.concatenate(t.fit_rows)
        entry = {
            "file": str(t.path),
            "samples": t.samples,
            "excluded": t.excluded["excluded_samples"],
        }
        if t in tests:
            entry["et_fitted_rows"] = _et(measured, force, mask)
            if block > 0.0:
                entry["et_block_holdout"] = _et(measured, force, ~mask)
        else:
            entry["et_holdout_test"] = _et(measured, force, ~mask)
        per_test.append(entry)
    report = {
        "start": start,
        "free_parameters": [*FREE, "offset_n"],
        "evaluations": result.evaluations,
        "seconds": result.seconds,
        "status": result.status,
        "et_start_fitted_rows": result.start_et,
        "et_fitted_rows_objective": result.cost_et,
        "holdout_fraction": block,
        "tests": per_test,
    }
    plant = Plant(result.params, result.offset_n, unit, _finite(report))
    return plant, report


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
