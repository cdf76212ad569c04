"""Training stage 1, the data: files to one `Series` in SI units with a run id per sample,
velocity and acceleration by the daemon's Kalman filter where a file lacks them, and the bad
stretches of a real recording (a saturated load cell, idle rig, a test's start or end)
found and excluded.

Tidy characterization CSVs, daemon recordings (.rrd) and any CSV with a column map and units
(or headers that name field and unit, `x_cm`, `force_n`, `command_v`) are read. The command
is a coil current (A) or a current driver's voltage (V); the Series says which.
"""

from __future__ import annotations

import csv
import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mrrig.export import RECORDING_SUFFIXES
from mrrig.loop.estimation import kalman_lanes
from mrrig.offline.datasets import (
    TIDY_HEADER,
    DataError,
    Series,
    columns_from_header,
    csv_header,
    load_csv,
)

log = logging.getLogger(__name__)

KALMAN_WARMUP_S = 0.1  # dropped at the start of each run whose xd/xdd we estimate
# Long runs are filtered in blocks side by side; each block starts this many samples early
# (its filter settles there: the filter's transient is ~0.1 s, 50-300 samples)
KALMAN_BLOCK = 8192
KALMAN_OVERLAP = 1024

# Bad stretches (`find_bad_stretches`)
WINDOW_S = 0.25  # the motion's statistics are taken over windows this long
SATURATION_MIN_SAMPLES = 3  # equal samples at the force's extreme: a flat top
SATURATION_PAD_S = 0.02  # excluded either side of a flat top (the approach to the limit)
IDLE_FRACTION = 0.02  # window velocity spread below this fraction of the run's typical: idle
TRANSIENT_Z = 6.0  # window mean displacement this many robust sigmas off the run's: drift
TRANSIENT_SPREAD = 4.0  # window velocity spread this many times the run's median: transient
TRANSIENT_MIN_WINDOWS = 8  # runs with fewer windows are not judged for transients
STRETCH_PAD_S = 0.1  # excluded either side of an idle or transient window
MERGE_WINDOWS = 2  # gaps of at most so many windows between bad ones (or the run's end) go too


def _is_tidy(path: Path) -> bool:
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            header = next(csv.reader(fh), [])
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DataError(f"{path}: cannot read: {exc}".replace("\n", " ")) from exc
    return tuple(h.strip() for h in header) == TIDY_HEADER


def load_tidy(path: str | Path) -> Series:
    """Read a tidy characterization CSV. xd/xdd are None when the file has any nan in them
    (the caller estimates them). current_meas_a is not used for training."""
    path = Path(path)
    if not _is_tidy(path):
        header = ",".join(TIDY_HEADER)
        raise DataError(f"{path}: not a tidy characterization file (header {header})")
    try:
        a = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, encoding="utf-8")
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: {exc}".replace("\n", " ")) from exc
    if a.shape[0] == 0:
        raise DataError(f"{path}: no data rows")
    if a.shape[1] != len(TIDY_HEADER):
        raise DataError(f"{path}: {a.shape[1]} columns, want {len(TIDY_HEADER)}")
    for j in (0, 1, 2, 5, 6):
        if not np.all(np.isfinite(a[:, j])):
            row = int(np.flatnonzero(~np.isfinite(a[:, j]))[0]) + 1
            raise DataError(f"{path}: column {TIDY_HEADER[j]!r}, data row {row}: not finite")
    if np.any(a[:, 0] != np.round(a[:, 0])):
        raise DataError(f"{path}: column 'run_id' must hold integers")
    has_est = bool(np.all(np.isfinite(a[:, 3:5])))
    return Series(
        t=a[:, 1],
        x=a[:, 2],
        xd=a[:, 3] if has_est else None,
        xdd=a[:, 4] if has_est else None,
        current=a[:, 6],
        force=a[:, 5],
        name=path.stem,
        run_id=a[:, 0].astype(int),
    )


RUN_GAP_PERIODS = 5.0  # a time step this many median periods long starts a new run


def runs_from_time(t: np.ndarray) -> np.ndarray:
    """Run ids for a file without a run column: a new run wherever time does not increase or
    jumps by more than `RUN_GAP_PERIODS` median sample periods (a recording paused)."""
    dt = np.diff(t)
    pos = dt[dt > 0.0]
    gap = RUN_GAP_PERIODS * float(np.median(pos)) if pos.size else np.inf
    return np.concatenate([[0], np.cumsum((dt <= 0.0) | (dt > gap))]).astype(int)


def run_ids(series: Series) -> np.ndarray:
    return series.run_id if series.run_id is not None else runs_from_time(series.t)


def stretches(run_id: np.ndarray) -> np.ndarray:
    """Ids 0, 1, ... of the contiguous stretches of equal run id (a run split by excluded
    samples counts as one stretch per piece)."""
    if run_id.size == 0:
        return run_id.astype(int)
    return np.cumsum(np.concatenate([[False], run_id[1:] != run_id[:-1]])).astype(int)


def stretch_bounds(stretch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first row, length) of each stretch of a `stretches` array."""
    n = stretch.size
    first = np.flatnonzero(np.concatenate([[True], stretch[1:] != stretch[:-1]])) if n else stretch
    return first, np.diff(np.append(first, n))


def sample_period(t: np.ndarray) -> float:
    """A run's sample period: its span over its sample count (robust to times printed with few
    digits, where the median difference is off by the rounding)."""
    return float((t[-1] - t[0]) / (t.size - 1)) if t.size > 1 else float("nan")


def load_recording(path: str | Path) -> Series:
    """A daemon recording (.rrd, or its .parquet/.mf4 export) as a Series: x_est, xd, xdd (the
    daemon's own Kalman estimates, the inputs its controller saw), f_meas, i_cmd.

    Samples in FAULT are dropped: there the command path is not trusted. In IDLE the daemon
    sends SAFE 0 A and records i_cmd = 0, which is what the firmware applies, so those samples
    stay (they are the 0 A part of the data). The first `KALMAN_WARMUP_S` of the file are
    dropped too (the daemon's filter starts with it). A new run id starts after every dropped
    stretch or time gap over 5 sample periods, so lag filters restart there.
    """
    # rerun and pyarrow are slow to import: only .rrd inputs pay for them
    from mrrig.export import read_any
    from mrrig.loop.samples import RigState

    path = Path(path)
    s = read_any(path).samples  # the .rrd, or its Parquet or MDF4 export
    fields = ("t", "x_est", "xd", "xdd", "f_meas", "i_cmd")
    keep = s["state"] != RigState.FAULT
    for f in fields:
        keep &= np.isfinite(s[f])
    if s.size:
        period = float(np.median(np.diff(s["t"]))) if s.size > 1 else 0.0
        keep &= s["t"] - s["t"][0] > KALMAN_WARMUP_S - 0.5 * period
    if keep.sum() < 2:
        raise DataError(f"{path}: fewer than 2 usable samples (not FAULT, all fields finite)")
    idx = np.flatnonzero(keep)
    t = s["t"][idx]
    dt = np.diff(t)
    period = float(np.median(dt))
    new_run = (np.diff(idx) > 1) | (dt > 5.0 * period) | (dt <= 0.0)
    return Series(
        t=t,
        x=s["x_est"][idx],
        xd=s["xd"][idx],
        xdd=s["xdd"][idx],
        current=s["i_cmd"][idx],
        force=s["f_meas"][idx],
        name=path.stem,
        run_id=np.concatenate([[0], np.cumsum(new_run)]).astype(int),
    )


def _kalman_by_blocks(
    x: np.ndarray, first: np.ndarray, length: np.ndarray, dt_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Kalman filter over the runs (first row, length) of x, all side by side: a run
    longer than `KALMAN_BLOCK` is cut into blocks, each started `KALMAN_OVERLAP` samples
    early in its run so that its filter has settled where its own rows begin."""
    lanes = []  # (filter start, own start, end)
    for f, n in zip(first.tolist(), length.tolist(), strict=True):
        for s in range(f, f + n, KALMAN_BLOCK):
            lanes.append(
                (f if s == f else max(f, s - KALMAN_OVERLAP), s, min(s + KALMAN_BLOCK, f + n))
            )
    width = max(e - a for a, _, e in lanes)
    X = np.full((len(lanes), width), np.nan)
    for j, (a, _, e) in enumerate(lanes):
        X[j, : e - a] = x[a:e]
    est = kalman_lanes(X, dt_s)
    out = tuple(np.empty(x.size) for _ in range(3))
    for j, (a, s, e) in enumerate(lanes):
        for k in range(3):
            out[k][s:e] = est[k][j, s - a : e - a]
    return out


def estimate_derivatives(series: Series, warmup_s: float = KALMAN_WARMUP_S) -> Series:
    """Fill xd/xdd with the Kalman filter (the daemon's, paper eqs 17-29) run over each run at
    its sample period (`sample_period`), and drop the first `warmup_s` of each run (the
    filter's start-up transient). x becomes the filtered displacement, as the daemon's
    controller sees it. The runs are filtered side by side (`estimation.kalman_lanes`)."""
    run_id = run_ids(series)
    x, xd, xdd = (np.empty(len(series)) for _ in range(3))
    keep = np.zeros(len(series), dtype=bool)
    order = np.argsort(run_id, kind="stable")
    uniq, first_sorted, counts = np.unique(run_id[order], return_index=True, return_counts=True)
    periods = {}
    for r, f0, n in zip(uniq.tolist(), first_sorted.tolist(), counts.tolist(), strict=True):
        rows = order[f0 : f0 + n]
        t = series.t[rows]
        if rows.size < 2 or np.any(np.diff(t) <= 0.0):
            raise DataError(f"{series.name}: run {r}: time must increase (and >= 2 samples)")
        periods.setdefault(round(sample_period(t), 12), []).append(rows)
    for dt_s, runs in periods.items():
        rows = np.concatenate(runs)
        length = np.array([r.size for r in runs])
        first = np.concatenate([[0], np.cumsum(length)[:-1]])
        est = _kalman_by_blocks(series.x[rows], first, length, dt_s)
        for k, dest in enumerate((x, xd, xdd)):
            dest[rows] = est[k]
        for r in runs:
            t = series.t[r]
            keep[r] = t - t[0] > warmup_s - 0.5 * dt_s  # round(warmup_s / dt_s) samples dropped
    out = replace(series, x=x, xd=xd, xdd=xdd, run_id=run_id, x_meas=None, force_meas=None)
    return select(out, keep)


def select(s: Series, rows: np.ndarray) -> Series:
    """The Series restricted to rows (a boolean mask or indices)."""
    pick = {
        f: (None if getattr(s, f) is None else getattr(s, f)[rows])
        for f in ("t", "x", "xd", "xdd", "current", "force", "run_id", "x_meas", "force_meas")
    }
    return Series(name=s.name, current_unit=s.current_unit, **pick)


def concatenate(parts: Sequence[Series], name: str = "") -> Series:
    """One Series from several, run ids renumbered so that every part's runs stay distinct.
    A DataError if the parts' commands are in different units (A and V)."""
    units = {p.current_unit for p in parts}
    if len(units) > 1:
        raise DataError(f"{name}: commands in different units ({', '.join(sorted(units))})")
    runs, offset = [], 0
    for p in parts:
        _, dense = np.unique(run_ids(p), return_inverse=True)
        runs.append(dense + offset)
        offset += int(dense.max()) + 1
    cat = lambda f: np.concatenate([getattr(p, f) for p in parts])  # noqa: E731
    return Series(
        t=cat("t"),
        x=cat("x"),
        xd=cat("xd"),
        xdd=cat("xdd"),
        current=cat("current"),
        force=cat("force"),
        name=name,
        run_id=np.concatenate(runs),
        current_unit=units.pop() if units else "A",
    )


def load_file(
    path: Path, columns: dict[str, str] | None = None, units: dict[str, str] | None = None
) -> Series:
    """One file as a Series (run ids, SI units), xd/xdd not yet estimated: `.rrd` ->
    `load_recording`; a CSV with the tidy header -> `load_tidy`; any other CSV ->
    `datasets.load_csv` with `columns`/`units`, or with the fields its headers name
    (`datasets.columns_from_header`); a new run wherever time does not increase."""
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    if path.suffix.lower() in RECORDING_SUFFIXES:
        return load_recording(path)
    if _is_tidy(path):
        return load_tidy(path)
    if columns is None:
        found = columns_from_header(csv_header(path))
        if found is None:
            raise DataError(
                f"{path}: not a tidy characterization CSV and its headers do not name t, x, "
                "force and the command with units (e.g. t_s, x_cm, force_n, command_v): "
                "give a column map (--columns)"
            )
        columns, units = found
        log.info("%s: columns from the header: %s", path, columns)
    s = load_csv(path, columns, units)
    return replace(s, run_id=runs_from_time(s.t))


def load_training_data(
    paths: Sequence[str | Path],
    columns: dict[str, str] | None = None,
    units: dict[str, str] | None = None,
) -> Series:
    """Load and concatenate training files into one Series with xd/xdd present (`load_file`;
    files without velocity or acceleration get both from `estimate_derivatives`). Errors are
    one-line `DataError`s naming the file."""
    if not paths:
        raise DataError("no training data files given")
    parts = []
    for p in map(Path, paths):
        s = load_file(p, columns, units)
        if s.xd is None or s.xdd is None:
            s = estimate_derivatives(s)
            if len(s) == 0:
                raise DataError(f"{p}: no samples left after the Kalman warm-up")
        log.info("%s: %d samples, %d runs", p, len(s), np.unique(s.run_id).size)
        parts.append(s)
    return concatenate(parts, name="+".join(s.name for s in parts))


# ---------------------------------------------------------------------------- bad stretches
@dataclass(frozen=True)
class Stretch:
    """An excluded stretch of one run."""

    kind: str  # saturation | idle | transient
    run: int
    t_start_s: float
    t_end_s: float
    samples: int


def _windows(n: int, w: int) -> np.ndarray:
    """Window index of each of n samples (windows of w; the last may be longer)."""
    k = max(1, n // w)
    return np.minimum(np.arange(n) // w, k - 1)


def _mark_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of each stretch of True in a boolean array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(), strict=True))


def _saturated(force: np.ndarray) -> np.ndarray:
    """Samples of a flat top at the force's extreme: `SATURATION_MIN_SAMPLES` or more equal
    samples in a row at the largest or smallest force of the data (a load cell at its limit
    reads one value; a real peak is not flat)."""
    out = np.zeros(force.size, dtype=bool)
    if force.size == 0:
        return out
    for limit in (force.max(), force.min()):
        for a, b in _mark_runs(force == limit):
            if b - a >= SATURATION_MIN_SAMPLES:
                out[a:b] = True
    return out


def _close(flags: np.ndarray, gap: int) -> np.ndarray:
    """Window flags with short gaps closed: a gap of at most `gap` windows between flagged
    windows, or between a flagged window and the run's start or end, is flagged too (a
    test's unsteady end is one stretch, not islands of kept samples)."""
    out = flags.copy()
    idx = np.flatnonzero(flags)
    if idx.size == 0:
        return out
    for a, b in itertools.pairwise(idx.tolist()):
        if 1 < b - a <= gap + 1:
            out[a:b] = True
    if idx[0] <= gap:
        out[: idx[0]] = True
    if flags.size - 1 - idx[-1] <= gap:
        out[idx[-1] :] = True
    return out


def _pad(mask: np.ndarray, samples: int) -> np.ndarray:
    if samples <= 0 or not mask.any():
        return mask
    # a flagged sample within `samples` of a position: a running count over the window
    c = np.concatenate([[0], np.cumsum(mask, dtype=np.int64)])
    idx = np.arange(mask.size)
    lo = np.maximum(idx - samples, 0)
    hi = np.minimum(idx + samples + 1, mask.size)
    return c[hi] - c[lo] > 0


def find_bad_stretches(series: Series) -> tuple[np.ndarray, list[Stretch]]:
    """(bad mask, the stretches) of a Series: saturation (`_saturated`, padded by
    `SATURATION_PAD_S`), idle windows (velocity spread under `IDLE_FRACTION` of the run's
    90th percentile window) and transient windows (mean displacement over `TRANSIENT_Z`
    robust sigmas from the run's, or velocity spread over `TRANSIENT_SPREAD` times the run's
    median: a test's start or end, a drift), in windows of `WINDOW_S`, padded by
    `STRETCH_PAD_S`. Needs xd."""
    run_id = run_ids(series)
    first, length = stretch_bounds(stretches(run_id))
    kinds = {k: np.zeros(len(series), dtype=bool) for k in ("saturation", "idle", "transient")}
    kinds["saturation"] = _saturated(series.force)
    for f, n in zip(first.tolist(), length.tolist(), strict=True):
        rows = slice(f, f + n)
        dt = sample_period(series.t[rows])
        if not dt > 0.0:
            continue
        pad_sat = int(round(SATURATION_PAD_S / dt))
        kinds["saturation"][rows] = _pad(kinds["saturation"][rows], pad_sat)
        w = max(2, int(round(WINDOW_S / dt)))
        win = _windows(n, w)
        nw = int(win.max()) + 1
        cnt = np.bincount(win, minlength=nw)
        xd = series.xd[rows]
        mean_xd = np.bincount(win, xd, nw) / cnt
        spread = np.sqrt(np.maximum(np.bincount(win, xd * xd, nw) / cnt - mean_xd**2, 0.0))
        idle = spread < IDLE_FRACTION * np.percentile(spread, 90)
        transient = np.zeros(nw, dtype=bool)
        if nw >= TRANSIENT_MIN_WINDOWS:
            mean_x = np.bincount(win, series.x[rows], nw) / cnt
            med = np.median(mean_x)
            mad = 1.4826 * np.median(np.abs(mean_x - med))
            transient = spread > TRANSIENT_SPREAD * np.median(spread)
            if mad > 0.0:
                transient |= np.abs(mean_x - med) > TRANSIENT_Z * mad
        pad = int(round(STRETCH_PAD_S / dt))
        kinds["idle"][rows] = _pad(_close(idle, MERGE_WINDOWS)[win], pad)
        kinds["transient"][rows] = _pad(_close(transient, MERGE_WINDOWS)[win], pad)
    bad = kinds["saturation"] | kinds["idle"] | kinds["transient"]
    found = []
    for kind in ("saturation", "idle", "transient"):
        mask = kinds[kind]
        for other in ("saturation", "idle", "transient"):  # each sample counted once
            if other == kind:
                break
            mask = mask & ~kinds[other]
        for a, b in _mark_runs(mask):
            cuts = [a, *(a + 1 + np.flatnonzero(run_id[a + 1 : b] != run_id[a : b - 1])), b]
            for ra, rb in itertools.pairwise(cuts):  # one stretch per run it touches
                t0, t1 = float(series.t[ra]), float(series.t[rb - 1])
                found.append(Stretch(kind, int(run_id[ra]), t0, t1, int(rb - ra)))
    return bad, found


def exclude_bad_stretches(series: Series, keep_all: bool = False) -> tuple[Series, dict[str, Any]]:
    """The Series without its bad stretches (`find_bad_stretches`), and what was excluded:
    counts by kind and each stretch's run and time range. A run with a stretch cut out of
    its middle becomes two stretches (history and lag filters restart after the gap: the
    `stretches` of the run ids). keep_all: nothing excluded (the report says so)."""
    if keep_all:
        return series, {"keep_all": True, "excluded_samples": 0, "by_kind": {}, "stretches": []}
    bad, found = find_bad_stretches(series)
    by_kind = {}
    for st in found:
        by_kind[st.kind] = by_kind.get(st.kind, 0) + st.samples
    report = {
        "keep_all": False,
        "excluded_samples": int(bad.sum()),
        "of_samples": len(series),
        "by_kind": by_kind,
        "stretches": [st.__dict__ for st in found],
    }
    for st in found:
        log.info(
            "excluded %s: run %d, %.4f-%.4f s (%d samples)",
            st.kind,
            st.run,
            st.t_start_s,
            st.t_end_s,
            st.samples,
        )
    if not bad.any():
        return series, report
    kept = select(series, ~bad)
    # a run with a hole becomes two runs: nothing (history, lag) carries across the gap
    idx = np.flatnonzero(~bad)
    gap = np.concatenate([[False], np.diff(idx) > 1])
    rid = run_ids(kept)
    new = np.cumsum(np.concatenate([[True], (rid[1:] != rid[:-1]) | gap[1:]])[: idx.size]) - 1
    return replace(kept, run_id=new.astype(int)), report


def measured_series(b: Series) -> Series:
    """What the rig records of data set B: noisy displacement and force, the command; xd/xdd
    by the daemon's Kalman filter (first 0.1 s of each run dropped)."""
    raw = Series(
        t=b.t,
        x=b.x_meas,
        xd=None,
        xdd=None,
        current=b.current,
        force=b.force_meas,
        name="B-measured",
        run_id=b.run_id,
    )
    return estimate_derivatives(raw)
