"""A stretch of a recording: one run's (a plan step's, found in the catalog by its run id) or a
time window on the recording's own clock. The daemon writes one recording per start, and a
plan's steps are runs of their own inside it: exporting a step gives that step's rows only.

The slice keeps the recording's identity (its UTC start stays the time zero of `t_s`, so the
UTC column of the export is that of the whole recording) and adds what was cut: the window in
seconds and, for a run, its catalog record."""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from mrrig.export import ExportError, utc_start

if TYPE_CHECKING:
    from mrrig.catalog import RunRecord
    from mrrig.offline.review import Recording


def window(
    rec: Recording,
    from_s: float | None,
    until_s: float | None,
    run: dict[str, Any] | None = None,
) -> Recording:
    """The samples and events of `rec` with `from_s <= t <= until_s` (an open end where None);
    ExportError, naming the recording, where the window is empty or inverted."""
    lo = -math.inf if from_s is None else from_s
    hi = math.inf if until_s is None else until_s
    if not lo < hi:
        raise ExportError(f"{rec.path}: empty time window: from {lo:g} s until {hi:g} s")
    t = rec.samples["t"]
    kept = (t >= lo) & (t <= hi)
    if not kept.any():
        have = f"{t[0]:.3f}-{t[-1]:.3f} s" if t.size else "no samples"
        raise ExportError(
            f"{rec.path}: no sample between {lo:g} s and {hi:g} s (the recording has {have})"
        )
    events = [ev for ev in rec.events if lo <= float(ev.get("t", math.nan)) <= hi]
    cut: dict[str, Any] = {"from_s": from_s, "until_s": until_s}
    if run is not None:
        cut["run"] = run
    identity = {**(rec.identity or {}), "window": cut}
    return replace(rec, samples=rec.samples[kept], events=events, identity=identity)


def run_window(rec: Recording, run: RunRecord) -> tuple[float, float | None]:
    """The run's stretch on the recording's clock: its `started_utc` and `ended_utc` less the
    recording's UTC start (`mrrig.export.utc_start`). ExportError where the recording has no
    UTC start or the run is not inside it."""
    t0, source = utc_start(rec)
    if t0 is None:
        raise ExportError(f"{rec.path}: no UTC start to place run {run.run_id} in ({source})")
    start = _seconds(run.started_utc, t0)
    end = _seconds(run.ended_utc, t0) if run.ended_utc is not None else None
    t = rec.samples["t"]
    if t.size and (start > t[-1] or (end is not None and end < t[0])):
        raise ExportError(
            f"{rec.path}: run {run.run_id} ({run.started_utc.isoformat()}) is not inside the"
            f" recording (its samples span {t0.isoformat()} + {t[0]:.3f}-{t[-1]:.3f} s)"
        )
    return start, end


def _seconds(at: dt.datetime, t0: dt.datetime) -> float:
    aware = at if at.tzinfo is not None else at.replace(tzinfo=dt.UTC)
    return (aware - t0).total_seconds()
