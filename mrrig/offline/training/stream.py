"""Training stage 1 for data of any size: files read in segments of at most `SEGMENT_ROWS`
samples, each prepared alone (implausible values, Kalman estimates, bad stretches), so that
memory is bounded by a segment, not by the files.

A CSV is streamed (`datasets.iter_csv`, `CSV_CHUNK_ROWS` at a time); a segment ends at a
run's start where it can, and a run longer than a segment is cut into segments (each its own
run: the Kalman warm-up and history restart there). Tidy characterization CSVs and daemon
recordings (.rrd) are read whole, then cut the same way. `mrrig evaluate` goes through every
segment (`segments`); `mrrig train` keeps at most `TRAIN_MAX_SAMPLES` of them
(`training_subset`: all where the data has fewer, else a seeded random choice of whole
segments), each file one test (`sample_tests`: the tests that cross-validation leaves out).

Implausible values are samples outside the sensors' ranges of the CAN contract
(`configs/mrrig.dbc`: RigSensors Displacement and Force, RigStatus CoilCurrent for a command
in A): a load cell cannot have read them, so they are a broken file or a unit error. They are
bad stretches (`implausible`, padded by `IMPLAUSIBLE_PAD_S`), excluded before the Kalman filter
(a run is cut there) and even with --keep-all, and reported with the others.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import replace
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from mrrig.export import RECORDING_SUFFIXES
from mrrig.offline.datasets import (
    COMMAND_UNITS,
    DataError,
    Series,
    columns_from_header,
    csv_header,
    iter_csv,
)
from mrrig.offline.training.data import (
    RUN_GAP_PERIODS,
    Stretch,
    _is_tidy,
    _mark_runs,
    _pad,
    concatenate,
    estimate_derivatives,
    exclude_bad_stretches,
    load_file,
    run_ids,
    select,
)
from mrrig.rigio.canbus.codec import DEFAULT_DBC_PATH

log = logging.getLogger(__name__)

SEGMENT_ROWS = 250_000  # samples prepared at a time (`segments`)
TRAIN_MAX_SAMPLES = 500_000  # samples `mrrig train` keeps at most (`training_subset`)
IMPLAUSIBLE_PAD_S = 0.02  # excluded either side of an implausible sample
MAX_LISTED_STRETCHES = 200  # stretches a report lists (the rest are counted)
# field -> (message, signal) of the CAN contract whose range bounds it
SENSOR_SIGNALS = {
    "x": ("RigSensors", "Displacement"),
    "force": ("RigSensors", "Force"),
    "current": ("RigStatus", "CoilCurrent"),
}


@cache
def sensor_ranges(dbc_path: Path = DEFAULT_DBC_PATH) -> dict[str, tuple[float, float]]:
    """(min, max) in SI units of each field the CAN contract bounds (`SENSOR_SIGNALS`)."""
    import cantools  # noqa: PLC0415 - only the offline tools that check ranges pay for it

    db = cantools.database.load_file(str(dbc_path), strict=True)
    out = {}
    for field, (message, signal) in SENSOR_SIGNALS.items():
        sig = db.get_message_by_name(message).get_signal_by_name(signal)
        out[field] = (float(sig.minimum), float(sig.maximum))
    return out


def _csv_segments(
    path: Path, columns: dict[str, str] | None, units: dict[str, str] | None, max_rows: int
) -> Iterator[Series]:
    """A CSV streamed into Series of at most `max_rows` samples, run ids from time as
    `data.runs_from_time` gives them (its gap from the file's first chunk)."""
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
    unit = COMMAND_UNITS[(units or {}).get("current", "A")]
    fields = list(columns)
    buf: dict[str, np.ndarray] = {f: np.empty(0) for f in fields}
    starts = np.empty(0, dtype=bool)  # a run starts at this buffered row
    gap, last_t = None, None
    for chunk in iter_csv(path, columns, units):
        t = chunk["t"]
        if gap is None:
            dt = np.diff(t)
            pos = dt[dt > 0.0]
            gap = RUN_GAP_PERIODS * float(np.median(pos)) if pos.size else np.inf
        dt = np.diff(np.concatenate([[np.nan if last_t is None else last_t], t]))
        new = (dt <= 0.0) | (dt > gap) | np.isnan(dt)
        last_t = float(t[-1])
        buf = {f: np.concatenate([buf[f], chunk[f]]) for f in fields}
        starts = np.concatenate([starts, new])
        while starts.size >= max_rows:
            inner = np.flatnonzero(starts[1 : max_rows + 1]) + 1
            cut = int(inner[-1]) if inner.size else max_rows
            yield _series(path, {f: v[:cut] for f, v in buf.items()}, starts[:cut], unit)
            buf = {f: v[cut:] for f, v in buf.items()}
            starts = starts[cut:].copy()
            starts[:1] = True  # the rest of a run cut here is a run of the next segment
    if starts.size:
        yield _series(path, buf, starts, unit)


def _series(path: Path, data: dict[str, np.ndarray], starts: np.ndarray, unit: str) -> Series:
    return Series(
        t=data["t"],
        x=data["x"],
        xd=data.get("xd"),
        xdd=data.get("xdd"),
        current=data["current"],
        force=data["force"],
        name=path.stem,
        run_id=np.cumsum(starts) - 1,
        current_unit=unit,
    )


def _cut(s: Series, max_rows: int) -> Iterator[Series]:
    """A Series in pieces of at most `max_rows`, at run starts where there is one."""
    rid = run_ids(s)
    s = replace(s, run_id=rid)
    while len(s) > max_rows:
        inner = np.flatnonzero(s.run_id[1 : max_rows + 1] != s.run_id[:max_rows]) + 1
        cut = int(inner[-1]) if inner.size else max_rows
        yield select(s, slice(0, cut))
        s = select(s, slice(cut, None))
    yield s


def segments(
    paths: Sequence[str | Path],
    columns: dict[str, str] | None = None,
    units: dict[str, str] | None = None,
    max_rows: int = SEGMENT_ROWS,
) -> Iterator[tuple[Path, Series]]:
    """(file, raw Series of at most `max_rows` samples) of every file in turn, run ids set,
    xd/xdd as the file has them (None: to be estimated)."""
    if not paths:
        raise DataError("no data files given")
    for path in map(Path, paths):
        if not path.is_file():
            raise DataError(f"{path}: no such file")
        if path.suffix.lower() in RECORDING_SUFFIXES or _is_tidy(path):
            for s in _cut(load_file(path, columns, units), max_rows):
                yield path, s
        else:
            for s in _csv_segments(path, columns, units, max_rows):
                yield path, s


def _implausible(s: Series) -> tuple[np.ndarray, str]:
    """Samples outside the sensors' ranges, and the first one's reason (field, value)."""
    ranges = sensor_ranges()
    bad = np.zeros(len(s), dtype=bool)
    first = ""
    for field, (lo, hi) in ranges.items():
        if field == "current" and s.current_unit != "A":
            continue  # a driver voltage: the contract bounds the coil's current only
        v = getattr(s, field)
        out = (v < lo) | (v > hi)
        if out.any() and not first:
            k = int(np.flatnonzero(out)[0])
            first = f"{field} {v[k]:.6g} at t {s.t[k]:.6g} s outside [{lo:g}, {hi:g}]"
        bad |= out
    return bad, first


def drop_implausible(path: Path, s: Series) -> tuple[Series, list[Stretch]]:
    """The Series without its implausible samples (`_implausible`, padded by
    `IMPLAUSIBLE_PAD_S`; a run is cut there, and pieces of one sample go too), and the
    stretches dropped."""
    bad, first = _implausible(s)
    if not bad.any():
        return s, []
    rid = run_ids(s)
    dt = np.diff(s.t)
    pos = dt[dt > 0.0]
    pad = int(round(IMPLAUSIBLE_PAD_S / float(np.median(pos)))) if pos.size else 0
    bad = _pad(bad, pad)
    lone = _piece_starts(np.flatnonzero(~bad), rid, sizes=True) < 2
    bad[np.flatnonzero(~bad)[lone]] = True  # a piece of one sample has no motion to estimate
    found = [
        Stretch("implausible", int(rid[a]), float(s.t[a]), float(s.t[b - 1]), b - a)
        for a, b in _mark_runs(bad)
    ]
    log.warning("%s: %d implausible samples excluded (first: %s)", path, int(bad.sum()), first)
    keep_idx = np.flatnonzero(~bad)
    new = _piece_starts(keep_idx, rid)
    return replace(select(s, keep_idx), run_id=np.cumsum(new) - 1), found


def _piece_starts(keep_idx: np.ndarray, rid: np.ndarray, sizes: bool = False) -> np.ndarray:
    """Over the kept rows: where a piece starts (a run with a hole becomes two, so that the
    Kalman filter and the history restart after it), or with `sizes` each row's piece size."""
    starts = np.concatenate(
        [[True], (np.diff(keep_idx) > 1) | (rid[keep_idx][1:] != rid[keep_idx][:-1])]
    )[: keep_idx.size]
    if not sizes:
        return starts
    piece = np.cumsum(starts) - 1
    return np.bincount(piece)[piece] if piece.size else piece


def prepare(path: Path, raw: Series, keep_all: bool = False) -> tuple[Series, dict[str, Any]]:
    """A raw segment made ready to train on or evaluate: implausible samples out
    (`drop_implausible`, whatever `keep_all`), xd/xdd by the Kalman filter where the file
    lacks them, bad stretches out (`data.exclude_bad_stretches`). Returns the Series and
    what was excluded (the implausible stretches among the others)."""
    n_raw = len(raw)
    s, implausible = drop_implausible(path, raw)
    if len(s) == 0:
        raise DataError(
            f"{path}: every sample is outside the sensors' ranges of {DEFAULT_DBC_PATH.name}"
        )
    if s.xd is None or s.xdd is None:
        s = estimate_derivatives(s)
        if len(s) == 0:
            raise DataError(f"{path}: no samples left after the Kalman warm-up")
    s, report = exclude_bad_stretches(s, keep_all)
    if len(s) == 0:
        kinds = ", ".join(f"{k} {n}" for k, n in report["by_kind"].items())
        raise DataError(
            f"{path}: every sample is a bad stretch ({kinds}): nothing left to learn or score"
        )
    dropped = sum(st.samples for st in implausible)
    listed = [st.__dict__ for st in implausible] + report["stretches"]
    report["stretches"] = [{"file": str(path), **st} for st in listed]
    report["excluded_samples"] += dropped
    report["of_samples"] = n_raw
    if dropped:
        report["by_kind"] = {"implausible": dropped, **report["by_kind"]}
    return s, report


def merge_reports(reports: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One exclusion report from the segments' (`prepare`)."""
    out: dict[str, Any] = {
        "keep_all": all(r["keep_all"] for r in reports),
        "excluded_samples": 0,
        "of_samples": 0,
        "by_kind": {},
        "stretches": [],
        "stretches_not_listed": 0,
    }
    for r in reports:
        out["excluded_samples"] += r["excluded_samples"]
        out["of_samples"] += r["of_samples"]
        for kind, n in r["by_kind"].items():
            out["by_kind"][kind] = out["by_kind"].get(kind, 0) + n
        room = MAX_LISTED_STRETCHES - len(out["stretches"])
        out["stretches"] += r["stretches"][: max(room, 0)]
        out["stretches_not_listed"] += max(len(r["stretches"]) - max(room, 0), 0)
    return out


def sample_tests(report: dict[str, Any]) -> np.ndarray:
    """The test (file) index of each sample of `training_subset`'s Series, from its report."""
    return np.repeat(
        np.arange(len(report["tests"])), [t["samples"] for t in report["tests"]]
    ).astype(int)


def training_subset(
    paths: Sequence[str | Path],
    columns: dict[str, str] | None = None,
    units: dict[str, str] | None = None,
    keep_all: bool = False,
    max_samples: int = TRAIN_MAX_SAMPLES,
    seed: int = 0,
    segment_rows: int = SEGMENT_ROWS,
) -> tuple[Series, dict[str, Any]]:
    """The data `mrrig train` trains on, prepared (`prepare`), with its exclusion report
    (`subset`: how many samples of how many were kept). All of it where the files hold at
    most `max_samples`; else whole segments chosen at random (reservoir sampling, `seed`)
    up to `max_samples`, in file order: memory bounded by `max_samples` plus a segment
    (of at most `segment_rows`, and never more than `max_samples`)."""
    rng = np.random.default_rng(seed)
    kept: list[tuple[int, Path, Series]] = []
    total = seen = 0
    sampling = False
    rows = min(segment_rows, max_samples)
    for k, (path, raw) in enumerate(segments(paths, columns, units, rows)):
        seen += len(raw)
        if not sampling and total + len(raw) <= max_samples:
            kept.append((k, path, raw))
            total += len(raw)
            continue
        sampling = True
        j = int(rng.integers(0, k + 1))
        if j < len(kept) and total - len(kept[j][2]) + len(raw) <= max_samples:
            total += len(raw) - len(kept[j][2])
            kept[j] = (k, path, raw)
    if sampling:
        log.warning(
            "training on %d of the %d samples: whole segments of up to %d chosen at random"
            " (at most %d samples are trained on)",
            total,
            seen,
            rows,
            max_samples,
        )
    parts, reports = [], []
    for _, path, raw in sorted(kept, key=lambda e: e[0]):
        s, report = prepare(path, raw, keep_all)
        parts.append(s)
        reports.append(report)
    report = merge_reports(reports)
    report["subset"] = {"samples": total, "of_samples": seen, "max_samples": max_samples}
    # the tests trained on (a file is a test), in the Series' order: `sample_tests`
    tests: dict[str, int] = {}
    for (_, path, _), s in zip(sorted(kept, key=lambda e: e[0]), parts, strict=True):
        tests[str(path)] = tests.get(str(path), 0) + len(s)
    report["tests"] = [{"file": f, "samples": n} for f, n in tests.items()]
    names = dict.fromkeys(s.name for s in parts)
    return concatenate(parts, name="+".join(names)), report
