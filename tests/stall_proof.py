"""What a process test may set aside, and only that: the stalls the simulator measured.

The simulator (`python -m firmware_sim --measure-echo --stats FILE`) writes the windows in
which frames were held up: its own (a sensor frame sent late, periods skipped) and the
transport's (its own frame echoed back late by the bridge). `prove` checks a run against them:

1. every sensor frame the simulator sent on time got exactly one command;
2. every fault of the daemon is one a stall causes and lies inside such a window: the
   interval in which the frames it missed should have come (the gap its sensor timeout or a
   stale frame names; the firmware's watchdog trip, reported in the next RigStatus, and its
   gap) lies inside one stall; any other fault (a controller's, the rig's e-stop) fails;
3. tracking (Et, eqs 41-43) over the armed frames outside the windows meets the bound.

A stall of the daemon itself the simulator cannot see: the kernel measures it, and the
daemon's summary keeps it (`kernel_stalls`, mrrig/loop/kernel_stalls.py: the passes of its
loop that waited on a run queue, or whose GIL another of the daemon's Python threads held
while it waited on one, or lost time to the VM's steal). A fault a stall causes is
explained by those too, where the passes next to its silent interval lost that interval's
length (less DETECT_S) or more: the figure is printed. Any other fault still fails.

Both processes read CLOCK_MONOTONIC (`clock_t0_s` in the simulator's stats and in the daemon's
summary), so their times are comparable on one machine.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mrrig.loop.kernel_stalls import format_stalls
from mrrig.loop.samples import RigState
from mrrig.offline.metrics import error_norm

# A late frame marks a window (the simulator's RunStats.LATE_S); the daemon's own timeouts see
# a stall within that much of its end.
DETECT_S = 0.005
# The firmware reports its watchdog in RigStatus, every 0.1 s.
STATUS_PERIOD_S = 0.1
# After a window, the coil's lag and the estimate need this long to be the loop's again.
SETTLE_S = 0.1


@dataclass(frozen=True)
class Window:
    kind: str  # "simulator", "transport" or "kernel" (the daemon's, from its summary)
    start_s: float  # CLOCK_MONOTONIC, s
    end_s: float
    runq_ms: float = 0.0  # kernel: the daemon's loop waited this long on a run queue
    steal_ms: float = 0.0  # kernel: the VM lost this much to the hypervisor
    others_ms: float = 0.0  # kernel: another Python thread of the daemon waited on a run queue

    def __str__(self) -> str:
        return (
            f"{self.kind} stall {1e3 * (self.end_s - self.start_s):.1f} ms "
            f"[{self.start_s:.3f}, {self.end_s:.3f}] s"
        )

    def measured(self, clock_t0_s: float) -> str:
        """A kernel window's figures, its times on the daemon's clock."""
        steal = f" and lost {self.steal_ms:.0f} ms to the VM's steal" if self.steal_ms else ""
        others = (
            f", another of its threads (the GIL's holder?) {self.others_ms:.1f} ms"
            if self.others_ms
            else ""
        )
        return (
            f"daemon waited {self.runq_ms:.1f} ms on the run queue{others}{steal} in "
            f"[{self.start_s - clock_t0_s:.3f}, {self.end_s - clock_t0_s:.3f}] s"
        )


@dataclass
class Proof:
    windows: list[Window]
    explained: list[tuple[dict, Window]]  # each fault and the window that explains it
    et: float | None  # over the armed frames outside the windows
    armed_frames: int  # outside the windows


def demo_files(out: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """The daemon's summary and its simulator's stats of a `mrrig demo` run, from the files its
    log names (`--summary-json`, and `sim-stats.json` beside it in its work folder)."""
    m = re.search(r"--summary-json (\S+)", out)
    assert m, out[-3000:]
    summary = json.loads(Path(m[1]).read_text())
    return summary, json.loads((Path(m[1]).parent / "sim-stats.json").read_text())


def windows(sim_stats: Mapping[str, Any]) -> list[Window]:
    """The simulator's stall windows on CLOCK_MONOTONIC."""
    t0 = sim_stats["clock_t0_s"]
    return [
        Window(w["kind"], t0 + w["start_s"], t0 + w["end_s"]) for w in sim_stats["stall_windows"]
    ]


def kernel_windows(kernel: Mapping[str, Any] | None, clock_t0_s: float) -> list[Window]:
    """The daemon's stalls that the kernel measured (its summary's `kernel_stalls`, times
    on the daemon's clock whose zero is `clock_t0_s`) on CLOCK_MONOTONIC."""
    rows = (kernel or {}).get("windows") or []
    return [Window("kernel", clock_t0_s + w[0], clock_t0_s + w[1], *w[2:5]) for w in rows]


def kernel_explains(silent: tuple[float, float], ks: Iterable[Window]) -> Window | None:
    """The kernel's windows next to the silent interval (within DETECT_S) merged into one,
    where the daemon lost that long, less DETECT_S, in them; None otherwise, and for lost
    frames (no interval: the daemon's stall delays frames, it does not lose them)."""
    if silent[1] <= silent[0]:
        return None
    near = [w for w in ks if w.start_s <= silent[1] + DETECT_S and silent[0] - DETECT_S <= w.end_s]
    runq = sum(w.runq_ms for w in near)
    steal = sum(w.steal_ms for w in near)
    others = sum(w.others_ms for w in near)
    if not near or (runq + steal + others) * 1e-3 < silent[1] - silent[0] - DETECT_S:
        return None
    a, b = min(w.start_s for w in near), max(w.end_s for w in near)
    return Window("kernel", a, b, runq, steal, others)


def spans(ws: Iterable[Window]) -> list[Window]:
    """The windows of both kinds merged where they overlap or touch: one stall may begin in
    the transport and go on in the simulator."""
    out: list[Window] = []
    for w in sorted(ws, key=lambda w: w.start_s):
        if out and w.start_s <= out[-1].end_s + DETECT_S:
            last = out[-1]
            kind = last.kind if last.kind == w.kind else "simulator+transport"
            out[-1] = Window(kind, last.start_s, max(last.end_s, w.end_s))
        else:
            out.append(w)
    return out


def watchdog_trips(sim_stats: Mapping[str, Any]) -> list[tuple[float, float]]:
    """The firmware's watchdog trips: (time on CLOCK_MONOTONIC, how long no command came)."""
    t0 = sim_stats["clock_t0_s"]
    out = []
    for e in sim_stats["fault_events"]:
        m = re.match(r"watchdog: no valid DamperCommand for ([\d.]+) ms", e["event"])
        if m:
            out.append((t0 + e["t_s"], float(m.group(1)) * 1e-3))
    return out


def silent_interval(
    fault: Mapping[str, Any], t_s: float, trips: list[tuple[float, float]]
) -> tuple[float, float] | None:
    """When the frames the fault missed should have come (CLOCK_MONOTONIC), for the faults a
    stall causes: the daemon's sensor timeout and a stale frame name their gap, lost frames
    show when the next frame came, the firmware's watchdog is the trip it reported before.
    None for any other fault: no stall explains it."""
    reason = str(fault["reason"])
    if reason.startswith("firmware watchdog"):
        late = STATUS_PERIOD_S + DETECT_S
        seen = [(t, gap) for t, gap in trips if t - DETECT_S <= t_s <= t + late]
        if not seen:
            return None
        t_trip, gap = seen[-1]
        return t_trip - gap, t_trip
    m = re.match(
        r"no sensor frame for ([\d.]+) ms|sensor frame ([\d.]+) ms old when answered", reason
    )
    if m:
        return t_s - float(m.group(1) or m.group(2)) * 1e-3, t_s
    if re.match(r"\d+ sensor frames lost", reason):
        return t_s, t_s
    return None


def explaining_window(
    fault: Mapping[str, Any],
    t_s: float,
    ws: Iterable[Window],
    trips: list[tuple[float, float]],
    ks: Iterable[Window] = (),
) -> Window | None:
    """The stall that covers the fault's silent interval (fault at `t_s` on CLOCK_MONOTONIC):
    one the simulator measured (`ws`), else the daemon's own that the kernel measured (`ks`)."""
    silent = silent_interval(fault, t_s, trips)
    if silent is None:
        return None
    for w in spans(ws):
        if w.start_s <= silent[0] + DETECT_S and silent[1] <= w.end_s + DETECT_S:
            return w
    return kernel_explains(silent, ks)


def check_answers(sim_stats: Mapping[str, Any]) -> None:
    """Rule 1: each sensor frame sent on time got exactly one command."""
    on_time = sim_stats["answers_on_time"]
    assert on_time["frames"] > 0, on_time
    assert on_time["answered_once"] == on_time["frames"], on_time
    assert on_time["unanswered"] == 0 and on_time["more_than_once"] == 0, on_time
    assert sim_stats["answers"]["unmatched"] == 0, sim_stats["answers"]


def check_faults(
    faults: Iterable[Mapping[str, Any]],
    clock_t0_s: float,
    ws: list[Window],
    trips: list[tuple[float, float]],
    ks: Sequence[Window] = (),
) -> list[tuple[dict, Window]]:
    """Rule 2: every fault (daemon time `t`) inside a stall; AssertionError names the others
    (with the kernel's windows within 0.1 s of them)."""
    explained, unexplained = [], []
    for f in faults:
        w = explaining_window(f, clock_t0_s + f["t"], ws, trips, ks)
        if w is None:
            unexplained.append(dict(f))
        else:
            explained.append((dict(f), w))
    near = [
        k.measured(clock_t0_s)
        for k in ks
        if any(k.start_s - 0.1 <= clock_t0_s + f["t"] <= k.end_s + 0.1 for f in unexplained)
    ]
    assert not unexplained, (
        f"faults that no measured stall explains: {unexplained}; windows: "
        + ("; ".join(str(w) for w in ws) or "none")
        + "; the kernel's near them: "
        + ("; ".join(near) or "none")
    )
    return explained


def set_aside(
    t_s: np.ndarray,
    ws: Iterable[Window],
    explained: Iterable[tuple[dict, Window]],
    clock_t0_s: float,
) -> np.ndarray:
    """Frames (daemon times `t_s`) inside a window, its settling, or before the fault it caused."""
    out = np.zeros(t_s.shape, dtype=bool)
    t_abs = clock_t0_s + t_s
    ends = {w: w.end_s for w in spans(ws)}
    for f, w in explained:  # a kernel window is set aside where it explains a fault
        ends[w] = max(ends.get(w, w.end_s), clock_t0_s + f["t"])
    for w, end_s in ends.items():
        out |= (t_abs >= w.start_s) & (t_abs <= end_s + SETTLE_S)
    return out


def explain(
    sim_stats: Mapping[str, Any],
    faults: Iterable[Mapping[str, Any]],
    clock_t0_s: float,
    kernel: Mapping[str, Any] | None = None,
) -> list[tuple[dict, Window]]:
    """Rule 2 alone, the windows printed: `faults` with `t` on the daemon's clock, whose time
    zero on CLOCK_MONOTONIC is `clock_t0_s` (0 for faults timed on CLOCK_MONOTONIC itself);
    `kernel`: the daemon summary's `kernel_stalls`, its own stalls."""
    ws = windows(sim_stats)
    ks = kernel_windows(kernel, clock_t0_s)
    print(
        f"simulator: {len(ws)} stall windows"
        + "".join(f"\n  {w}" for w in ws)
        + f"\n  echo through the transport: {sim_stats['echo_us']} us"
    )
    if kernel is not None:
        print(f"daemon (the kernel): {format_stalls(kernel)}")
    explained = check_faults(faults, clock_t0_s, ws, watchdog_trips(sim_stats), ks)
    for f, w in explained:
        if w.kind == "kernel":
            what = f.get("fault") or f["reason"]
            print(f"  {what} at t={f['t']:.3f} s: {w.measured(clock_t0_s)} ({f['reason']})")
        else:
            print(f"  fault at t={f['t']:.3f} s ({f['reason']}): inside the {w}")
    return explained


def prove(
    sim_stats: Mapping[str, Any],
    faults: Iterable[Mapping[str, Any]],
    clock_t0_s: float,
    samples: np.ndarray | None = None,
    et_bound: float | None = None,
    kernel: Mapping[str, Any] | None = None,
) -> Proof:
    """Rules 1-3 on one run; prints the windows. `faults`: the daemon's, with `t` on its clock
    (`clock_t0_s`); `samples`: its SAMPLE_DTYPE records (the recording) for rule 3; `kernel`:
    its summary's `kernel_stalls`."""
    check_answers(sim_stats)
    explained = explain(sim_stats, faults, clock_t0_s, kernel)
    ws = windows(sim_stats)
    et, n = None, 0
    if samples is not None:
        et, n = tracking(samples, ws, explained, clock_t0_s, et_bound)
    return Proof(ws, explained, et, n)


def tracking(
    samples: np.ndarray,
    ws: Sequence[Window],
    explained: Iterable[tuple[dict, Window]],
    clock_t0_s: float,
    et_bound: float | None = None,
) -> tuple[float | None, int]:
    """Rule 3: Et (eqs 41-43) over the armed frames outside the windows, `et_bound` asserted;
    returns it (None without such a frame) and the number of frames it is over."""
    armed = samples["state"] == RigState.ARMED
    kept = armed & ~set_aside(samples["t"], ws, explained, clock_t0_s)
    n = int(kept.sum())
    et = error_norm(samples["f_des"][kept], samples["f_meas"][kept]) if n else None
    print(
        f"  tracking: Et {et} over {n} armed frames outside the windows "
        f"({int(armed.sum()) - n} set aside)"
    )
    if et_bound is not None:
        assert et is not None and et <= et_bound, (et, et_bound)
    return et, n
