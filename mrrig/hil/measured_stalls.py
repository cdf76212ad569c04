"""The stalls a simulated HIL run measured, as windows on the run's clock (seconds from its
first streamed frame), for `mrrig.hil.metrics.tracking_apart_from_windows`: the setpoints the
actuator dropped as late (firmware_sim's stats, `late_setpoint_times`), the windows in which
the simulator or the transport held frames up (its `stall_windows`, `--measure-echo`), and the
daemon's own stalls that the kernel measured (its summary's `kernel_stalls`). Pure: the two
processes' JSON in, windows out; both clocks are CLOCK_MONOTONIC (`clock_t0_s` in each)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from typing import Any

from mrrig.hil.metrics import StallWindow

DROPPED = "setpoint dropped"


def measured_windows(
    sim_stats: Mapping[str, Any], daemon_summary: Mapping[str, Any], run_t0_s: float
) -> list[StallWindow]:
    """Every measured stall of the run whose first streamed frame the daemon received at
    `run_t0_s` (its clock); a dropped setpoint is a window of no length at its drop."""
    daemon_t0 = float(daemon_summary["clock_t0_s"])
    sim_shift = float(sim_stats["clock_t0_s"]) - daemon_t0 - run_t0_s
    out = [
        StallWindow(DROPPED, d["t_s"] + sim_shift, d["t_s"] + sim_shift)
        for d in sim_stats.get("late_setpoint_times", ())
    ]
    out += [
        StallWindow(w["kind"], w["start_s"] + sim_shift, w["end_s"] + sim_shift)
        for w in sim_stats.get("stall_windows", ())
    ]
    kernel = daemon_summary.get("kernel_stalls") or {}
    out += [
        StallWindow("kernel", w[0] - run_t0_s, w[1] - run_t0_s) for w in kernel.get("windows", ())
    ]
    return out


def counted(windows: list[StallWindow]) -> str:
    """`3 setpoint dropped, 1 transport`: the windows by kind."""
    return (
        ", ".join(f"{n} {kind}" for kind, n in Counter(w.kind for w in windows).items()) or "none"
    )
