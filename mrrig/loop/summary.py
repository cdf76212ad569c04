"""The run summary: the same numbers in the daemon's exit summary and in `mrrig review`."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from mrrig.loop.coverage import OUTSIDE_BITS
from mrrig.loop.feasibility import F_DEADBAND_N, V_DEADBAND_M_S, opposed
from mrrig.loop.kernel_stalls import format_stalls
from mrrig.loop.samples import RigState


class Histogram:
    """Counts of non-negative values in fixed bins of `bin_width` up to `top` (above: one
    overflow bin), with the exact max: percentiles to half a bin in fixed memory, however long
    the run."""

    def __init__(self, bin_width: float, top: float) -> None:
        self.width = float(bin_width)
        self.counts = np.zeros(int(math.ceil(top / bin_width)) + 1, dtype=np.int64)
        self.n = 0
        self.max = -math.inf

    def add(self, values: np.ndarray) -> None:
        v = np.asarray(values, dtype=float)
        v = v[np.isfinite(v)]
        if not v.size:
            return
        last = self.counts.size - 1
        np.add.at(self.counts, np.minimum((np.maximum(v, 0.0) / self.width).astype(int), last), 1)
        self.n += int(v.size)
        self.max = max(self.max, float(v.max()))

    def percentiles(self, qs: tuple[float, ...]) -> dict[str, float]:
        """Like `metrics.percentiles`: `p50`, ... and `max`; a value is its bin's middle (the
        max where that is smaller, or in the overflow bin); NaN without values."""
        out = {}
        cum = np.cumsum(self.counts) if self.n else None
        for q in qs:
            if cum is None:
                out[f"p{q:g}"] = math.nan
                continue
            k = int(np.searchsorted(cum, q / 100.0 * (self.n - 1), side="right"))
            mid = (k + 0.5) * self.width
            out[f"p{q:g}"] = self.max if k >= self.counts.size - 1 else min(mid, self.max)
        out["max"] = self.max if self.n else math.nan
        return out


class _Moments:
    """Count, mean, sum of squared deviations, min and max, merged batch by batch (Chan et al.)."""

    def __init__(self) -> None:
        self.n, self.mean, self.m2 = 0, 0.0, 0.0
        self.min, self.max = math.inf, -math.inf

    def add(self, x: np.ndarray) -> None:
        if not x.size:
            return
        nb, mb = x.size, float(x.mean())
        m2b = float(((x - mb) ** 2).sum())
        n = self.n + nb
        delta = mb - self.mean
        self.mean += delta * nb / n
        self.m2 += m2b + delta * delta * self.n * nb / n
        self.n = n
        self.min, self.max = min(self.min, float(x.min())), max(self.max, float(x.max()))


# the summary's percentile resolution: 0.5 us of latency, 0.05 N of tracking error, 1 mA of
# command step
LATENCY_BIN_US, LATENCY_TOP_US = 0.5, 100_000.0
# latency_split_us: "waited" from the bus's receive timestamp to the loop's read (the bridge's
# hop, a stall), "work" from that read to the end of send() (the spec's budget), "send_call"
# the send() within the work
LATENCY_PARTS = ("waited", "work", "send_call")
ERROR_BIN_N, ERROR_TOP_N = 0.05, 12_000.0
STEP_BIN_A, STEP_TOP_A = 0.001, 10.0
# a command step counted as a jump: an eighth of a 2 A coil driver's range within one frame
COMMAND_JUMP_A = 0.25


class SummaryAccumulator:
    """The run summary built batch by batch in fixed memory: the daemon adds each batch of
    samples as it completes and keeps none of them; `summarize` adds a whole run at once.
    Both give the same numbers (sums merged in another order differ by rounding only)."""

    def __init__(self) -> None:
        self.frames = 0
        self.first_t = self.last_t = math.nan
        self.f_des = _Moments()  # armed frames
        self.sse = 0.0  # armed: sum of (f_des - f_meas)^2
        # armed frames after an armed frame: their force answers an armed command (the first
        # frame of an armed stretch measures the damper as it was before arming)
        self.f_des_answered = _Moments()
        self.sse_answered = 0.0
        self.opposed = 0  # answered frames whose desired force opposes the motion
        self._last_armed = False  # the previous batch's last frame
        self.error = Histogram(ERROR_BIN_N, ERROR_TOP_N)
        self.i_cmd = _Moments()  # every frame
        # |i_cmd(k) - i_cmd(k-1)| where frames k-1 and k are both armed
        self.step = Histogram(STEP_BIN_A, STEP_TOP_A)
        self.jumps = 0
        self._last_cmd: tuple[float, bool] | None = None  # the previous batch's last frame
        self.latency = Histogram(LATENCY_BIN_US, LATENCY_TOP_US)
        self.max_gap_ms, self.gaps_over_10_ms = math.nan, 0
        # armed frames marked against the model's envelope, those outside, and by input
        self.covered = self.outside = 0
        self.outside_by = np.zeros(len(OUTSIDE_BITS), dtype=np.int64)

    def add(self, samples: np.ndarray) -> None:
        if not samples.size:
            return
        t = samples["t"].astype(float)
        g = frame_gaps(t if math.isnan(self.last_t) else np.concatenate([[self.last_t], t]))
        self.max_gap_ms = float(np.fmax(self.max_gap_ms, g["max"]))
        self.gaps_over_10_ms += g["over_10_ms"]
        if math.isnan(self.first_t):
            self.first_t = float(t[0])
        self.last_t = float(t[-1])
        self.frames += int(samples.size)
        armed = samples["state"] == RigState.ARMED
        f_des, f_meas = samples["f_des"][armed], samples["f_meas"][armed]
        self.f_des.add(f_des)
        self.sse += float(((f_des - f_meas) ** 2).sum())
        answered = armed & np.concatenate([[self._last_armed], armed[:-1]])
        self._last_armed = bool(armed[-1])
        f_des_a = samples["f_des"][answered]
        self.f_des_answered.add(f_des_a)
        self.sse_answered += float(((f_des_a - samples["f_meas"][answered]) ** 2).sum())
        self.opposed += int(opposed(f_des_a, samples["xd"][answered]).sum())
        self.error.add(np.abs(f_des - f_meas))
        self.i_cmd.add(samples["i_cmd"])
        self._add_steps(samples["i_cmd"].astype(float), armed)
        self.latency.add(samples["latency_us"])
        marks = samples["outside"][armed]
        marks = marks[np.isfinite(marks)].astype(np.int64)
        self.covered += int(marks.size)
        self.outside += int((marks != 0).sum())
        for k, bit in enumerate(OUTSIDE_BITS.values()):
            self.outside_by[k] += int(((marks & bit) != 0).sum())

    def _add_steps(self, i_cmd: np.ndarray, armed: np.ndarray) -> None:
        if self._last_cmd is not None:
            i_cmd = np.concatenate([[self._last_cmd[0]], i_cmd])
            armed = np.concatenate([[self._last_cmd[1]], armed])
        self._last_cmd = (float(i_cmd[-1]), bool(armed[-1]))
        steps = np.abs(np.diff(i_cmd))[armed[1:] & armed[:-1]]
        self.step.add(steps)
        self.jumps += int((steps > COMMAND_JUMP_A).sum())

    def result(
        self,
        events: Iterable[Mapping[str, Any]],
        counters: Mapping[str, Any] | None = None,
    ) -> dict[str, Any]:
        """The summary dict (see `summarize`)."""
        fd = self.f_des
        # eqs 41-43; undefined without an armed frame or for a constant target
        et = math.sqrt(self.sse) / math.sqrt(fd.m2) if fd.n and fd.max > fd.min else math.nan
        fa = self.f_des_answered
        et_answered = (
            math.sqrt(self.sse_answered) / math.sqrt(fa.m2)
            if fa.n and fa.max > fa.min
            else math.nan
        )
        i = self.i_cmd
        out: dict[str, Any] = {
            "duration_s": self.last_t - self.first_t if self.frames else 0.0,
            "last_frame_t_s": self.last_t,
            "frames": self.frames,
            "armed_frames": fd.n,
            "faults": [
                # with its kind where the event names one (the safety list's, e.g. sensor_timeout)
                {"t": ev.get("t"), "reason": ev.get("reason", ev.get("text"))}
                | ({"fault": ev["fault"]} if ev.get("fault") else {})
                for ev in events
                if ev.get("kind") == "fault"
            ],
            "et": et,
            "et_answered": et_answered,
            # what no current of a semi-active damper gives (mrrig.loop.feasibility)
            "force_against_motion": {
                "frames": self.opposed,
                "share": self.opposed / fa.n if fa.n else math.nan,
            },
            "tracking_error_n": self.error.percentiles((50, 95)),
            "i_cmd_a": {
                "mean": i.mean if i.n else math.nan,
                "max": i.max if i.n else math.nan,
                "std": math.sqrt(i.m2 / i.n) if i.n else math.nan,
            },
            "i_cmd_step_a": {
                **self.step.percentiles((99,)),
                f"over_{COMMAND_JUMP_A:g}_a": self.jumps,
            },
            "latency_us": self.latency.percentiles((50, 99, 99.9)),
            "frame_gap_ms": {"max": self.max_gap_ms, "over_10_ms": self.gaps_over_10_ms},
        }
        if self.covered:
            out["coverage"] = {
                "armed_frames_marked": self.covered,
                "outside_frames": self.outside,
                "outside_share": self.outside / self.covered,
                "outside_share_by_input": {
                    name: int(n) / self.covered
                    for name, n in zip(OUTSIDE_BITS, self.outside_by, strict=True)
                },
            }
        for key, value in (counters or {}).items():
            out.setdefault(key, value)
        return out


# the spec's budget of the daemon's work per frame, receive -> send (spec/system.md)
LATENCY_BUDGET_US = {"p99": 300.0, "p99.9": 1000.0}


def _over_budget(us: Mapping[str, float]) -> list[str]:
    return [k for k, limit in LATENCY_BUDGET_US.items() if not us.get(k, math.nan) <= limit]


def _budget_line(d: Mapping[str, Any]) -> str:
    """One rule wherever a summary is printed (the daemon's, `mrrig review`'s): the budget is
    for the loop's work per frame (`latency_split_us`, which the daemon measures and a
    recording's summary keeps). Without it, the latency (bus receive -> send) decides only
    where it is within the budget: it holds the wait before the loop reads the frame too."""
    budget = ", ".join(f"{k} <= {v:g} us" for k, v in LATENCY_BUDGET_US.items())
    head = f"the spec's budget of the work per frame {budget}:"
    work = (d.get("latency_split_us") or {}).get("work")
    if work:
        over = _over_budget(work)
        verdict = "within it" if not over else "OVER it at " + ", ".join(over)
        return f"{head} {verdict} (its work)"
    if not _over_budget(d["latency_us"]):
        return f"{head} within it (the latency, which holds the work)"
    return (
        f"{head} not judged (no work per frame here: the latency over it holds the wait"
        " before the loop's read too; the whole run's summary has the work)"
    )


def _latency_lines(d: Mapping[str, Any]) -> list[str]:
    """The latency from the bus's receive timestamp, the loop's own work per frame where the
    summary has it, and the budget's verdict (`_budget_line`)."""
    work = (d.get("latency_split_us") or {}).get("work")
    lines = [f"latency       {_stats_line(d['latency_us'], ' us')} (bus receive -> send)"]
    if work:
        lines.append(f"  of it work  {_stats_line(work, ' us')} (the loop's read -> send)")
    return [*lines, f"              {_budget_line(d)}"]


def _coverage_lines(c: Mapping[str, Any] | None) -> list[str]:
    """The share of armed frames outside the model's training envelope; none for a run
    without an envelope (no model, or a model trained before models kept one)."""
    if not c:
        return []
    by = ", ".join(f"{k} {v:.1%}" for k, v in c["outside_share_by_input"].items())
    return [
        f"coverage      {c['outside_share']:.1%} of {c['armed_frames_marked']} armed frames"
        f" outside the model's training envelope ({c['outside_frames']} frames; by input: {by})"
    ]


def frame_gaps(t_s: np.ndarray) -> dict[str, float | int]:
    """The largest gap between consecutive sensor frames (ms), and how many exceed 10 ms: what
    the transport and the machine did to the 2 ms stream."""
    gaps = np.diff(np.asarray(t_s, dtype=float)) * 1e3
    return {
        "max": float(gaps.max()) if gaps.size else math.nan,
        "over_10_ms": int((gaps > 10.0).sum()),
    }


def summarize(
    samples: np.ndarray,
    events: Iterable[Mapping[str, Any]],
    counters: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Metrics of one run from its SAMPLE_DTYPE records and events.

    Et and the tracking error use ARMED frames only (the others have no force to track);
    current and latency use every frame; the command steps |i_cmd(k) - i_cmd(k-1)| those
    pairs of frames that are both armed (arming and disarming are not steps of the controller),
    with how many exceed `COMMAND_JUMP_A`. Percentiles are to half a bin (0.05 N, 0.5 us:
    `SummaryAccumulator`). A fault is an event with `kind == "fault"`; its reason is the
    `reason` field (else the text). `counters` (frames received, invalid frames, commands
    sent, ...) are merged in; a counter never replaces a computed key.
    """
    acc = SummaryAccumulator()
    acc.add(samples)
    return acc.result(events, counters)


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


def _step_line(d: Mapping[str, Any]) -> str:
    jumps = f"over_{COMMAND_JUMP_A:g}_a"
    return (
        f"p99 {_fmt(d['p99'], ' A')}, max {_fmt(d['max'], ' A')},"
        f" {d[jumps]} over {COMMAND_JUMP_A:g} A"
    )


def _against_line(d: Mapping[str, Any]) -> list[str]:
    """None for a summary from before the count, or of a run never armed."""
    a = d.get("force_against_motion")
    if not a or not a["share"] >= 0:  # NaN: no frame answers an armed command
        return []
    return [
        f"against motion {_fmt(a['share'] * 100.0, ' %', 3)} of those frames ({a['frames']}) ask"
        f" force against the motion (beyond {F_DEADBAND_N:g} N, {V_DEADBAND_M_S * 1e3:g} mm/s):"
        " no current of a semi-active damper gives it"
    ]


def format_summary(d: Mapping[str, Any]) -> str:
    """Multi-line text of a `summarize` dict for a terminal."""
    lines = [
        f"duration      {_fmt(d['duration_s'], ' s', 6)}, {d['frames']} frames"
        f" ({d['armed_frames']} armed)",
        f"Et            {_fmt(d['et'])} (armed frames); {_fmt(d['et_answered'])} where the"
        " force answers an armed command (all but each armed stretch's first frame)",
        *_against_line(d),
        f"|f_des-f_meas| {_stats_line(d['tracking_error_n'], ' N')}",
        f"i_cmd         {_stats_line(d['i_cmd_a'], ' A')}",
        f"i_cmd steps   {_step_line(d['i_cmd_step_a'])} (between armed frames)",
        *_latency_lines(d),
        f"frame gaps    max {_fmt(d['frame_gap_ms']['max'], ' ms')},"
        f" {d['frame_gap_ms']['over_10_ms']} over 10 ms",
        *_coverage_lines(d.get("coverage")),
        *([f"kernel stalls {format_stalls(d['kernel_stalls'])}"] if "kernel_stalls" in d else []),
        f"faults        {len(d['faults'])}",
    ]
    lines += [f"  t={_fmt(f['t'], ' s', 6)}  {f['reason']}" for f in d["faults"]]
    known = {
        "duration_s",
        "last_frame_t_s",
        "frames",
        "armed_frames",
        "et",
        "et_answered",
        "force_against_motion",
        "tracking_error_n",
        "i_cmd_a",
        "i_cmd_step_a",
        "latency_us",
        "frame_gap_ms",
        "faults",
        "clock_t0_s",  # for tools that set the run beside another process's clock
        "coverage",
        "kernel_stalls",  # the loop's own stalls (mrrig.loop.kernel_stalls)
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
