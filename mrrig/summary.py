"""The run summary: the same numbers in the daemon's exit summary and in `mrrig review`."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from mrrig.metrics import error_norm, percentiles
from mrrig.samples import RigState


def summarize(
    samples: np.ndarray,
    events: Iterable[Mapping[str, Any]],
    counters: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Metrics of one run from its SAMPLE_DTYPE records and events.

    Et and the tracking error use ARMED frames only (the others have no force to track);
    current and latency use every frame. A fault is an event with `kind == "fault"`; its
    reason is the `reason` field (else the text). `counters` (frames received, invalid
    frames, commands sent, ...) are merged in; a counter never replaces a computed key.
    """
    armed = samples["state"] == RigState.ARMED
    f_des = samples["f_des"][armed]
    f_meas = samples["f_meas"][armed]
    if f_des.size and np.ptp(f_des) > 0:
        et = error_norm(f_des, f_meas)  # eqs 41-43
    else:
        et = math.nan  # no armed frame, or a constant target: Et is not defined
    t = samples["t"]
    i_cmd = samples["i_cmd"]
    latency = samples["latency_us"][np.isfinite(samples["latency_us"])]
    faults = [
        {"t": ev.get("t"), "reason": ev.get("reason", ev.get("text"))}
        for ev in events
        if ev.get("kind") == "fault"
    ]
    out: dict[str, Any] = {
        "duration_s": float(t[-1] - t[0]) if t.size else 0.0,
        "last_frame_t_s": float(t[-1]) if t.size else math.nan,
        "frames": int(samples.size),
        "armed_frames": int(armed.sum()),
        "faults": faults,
        "et": et,
        "tracking_error_n": percentiles(np.abs(f_des - f_meas), qs=(50, 95)),
        "i_cmd_a": {
            "mean": float(i_cmd.mean()) if i_cmd.size else math.nan,
            "max": float(i_cmd.max()) if i_cmd.size else math.nan,
            "std": float(i_cmd.std()) if i_cmd.size else math.nan,
        },
        "latency_us": percentiles(latency, qs=(50, 99, 99.9)),
        "frame_gap_ms": frame_gaps(t),
    }
    for key, value in (counters or {}).items():
        out.setdefault(key, value)
    return out


def frame_gaps(t_s: np.ndarray) -> dict[str, float | int]:
    """The largest gap between consecutive sensor frames (ms), and how many exceed 10 ms: what
    the transport and the machine did to the 2 ms stream."""
    gaps = np.diff(np.asarray(t_s, dtype=float)) * 1e3
    return {
        "max": float(gaps.max()) if gaps.size else math.nan,
        "over_10_ms": int((gaps > 10.0).sum()),
    }


def _fmt(value: Any, unit: str = "", digits: int = 4) -> str:
    if isinstance(value, float):
        return f"{value:.{digits}g}{unit}"
    return f"{value}{unit}"


def _stats_line(d: Mapping[str, float], unit: str) -> str:
    return ", ".join(f"{k} {_fmt(v, unit)}" for k, v in d.items())


def _nested(d: Mapping[str, Any]) -> str:
    """One line of a mapping of percentile dicts (or plain values)."""
    return "; ".join(
        f"{k}: {_stats_line(v, '') if isinstance(v, Mapping) else _fmt(v)}" for k, v in d.items()
    )


def format_summary(d: Mapping[str, Any]) -> str:
    """Multi-line text of a `summarize` dict for a terminal."""
    lines = [
        f"duration      {_fmt(d['duration_s'], ' s', 6)}, {d['frames']} frames"
        f" ({d['armed_frames']} armed)",
        f"Et            {_fmt(d['et'])} (armed frames)",
        f"|f_des-f_meas| {_stats_line(d['tracking_error_n'], ' N')}",
        f"i_cmd         {_stats_line(d['i_cmd_a'], ' A')}",
        f"latency       {_stats_line(d['latency_us'], ' us')}",
        f"frame gaps    max {_fmt(d['frame_gap_ms']['max'], ' ms')},"
        f" {d['frame_gap_ms']['over_10_ms']} over 10 ms",
        f"faults        {len(d['faults'])}",
    ]
    lines += [f"  t={_fmt(f['t'], ' s', 6)}  {f['reason']}" for f in d["faults"]]
    known = {
        "duration_s",
        "last_frame_t_s",
        "frames",
        "armed_frames",
        "et",
        "tracking_error_n",
        "i_cmd_a",
        "latency_us",
        "frame_gap_ms",
        "faults",
    }
    extra = {k: v for k, v in d.items() if k not in known}
    if extra:
        lines.append("counters")
        width = max(len(k) for k in extra)
        lines += [
            f"  {k:<{width}}  " + (_nested(v) if isinstance(v, Mapping) else _fmt(v))
            for k, v in extra.items()
        ]
    return "\n".join(lines)
