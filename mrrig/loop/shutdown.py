"""The end of a daemon's run, in this order: the control thread stopped, a SAFE command, the
actuator to rest, the bus closed, the loop's real-time priority left; then the summary (its
counters, latency split and kernel stalls), handed to the telemetry process, which is waited
for. Runs in the loop's thread, whether the loop ended, was stopped or raised."""

from __future__ import annotations

import gc
import time
from dataclasses import replace
from typing import TYPE_CHECKING

from mrrig.loop.exit_codes import Exit
from mrrig.loop.realtime import leave_realtime
from mrrig.loop.samples import RigState

if TYPE_CHECKING:
    from mrrig.loop.daemon import Daemon


def shut_down(d: Daemon) -> None:
    """SAFE first, then the actuator to rest, the summary, the sidecar, the bus."""
    d.kernel_stalls.stop(d.now())  # the loop's last pass
    d.control.stop()
    while (taken := d.control.take()) is not None:
        if taken[0].cmd == "sidecar" and taken[0].sidecar is not None:
            d.sidecar.back(*taken[0].sidecar)  # a restart that finished as it ended
    if d.bus is not None and d.started.is_set():
        if d._last_sensor_t is not None and not d._safe_sent_at_stop:
            d._send_command(False, 0.0, 0.0, d._last_counter)
        d.actuator = replace(d.actuator, waveform="stop")
        try:
            d._send_actuator()
        finally:
            d.bus.shutdown()
    elif d.bus is not None:  # never listened: this daemon did not own the rig
        d.bus.shutdown()
    # the loop is over: what follows (and the exit) must not starve another rig's loop;
    # a full collection of the unfrozen heap is one such thing
    leave_realtime("daemon")
    gc.unfreeze()
    d.notifier.stopping()  # after the SAFE command
    d.summary = _summary(d)
    d.sidecar.close(d.summary)


def _summary(d: Daemon) -> dict:
    """The run's summary (`mrrig.loop.summary`), with the exit code it ends with."""
    d.counters["cpu_loop_s"] = time.process_time() - d._cpu0
    adaptation = d.controller.adaptation_state()
    ahead, missed = d.controller.solved_ahead()
    d.counters["commands_solved_ahead"] = ahead
    d.counters["commands_ahead_missed"] = missed
    d.counters["loop_wall_s"] = d.now()
    never = d.started.is_set() and d.counters["sensor_frames_valid"] == 0
    if never and d.cfg.loop.arm_on_start and d.supervisor.state is not RigState.FAULT:
        # asked to run armed (--arm) on a bus that never carried a frame of any kind
        when = f"in the whole run ({d.now():.1f} s)"
        d._emit(d.sensors.no_sensor_frames(time.perf_counter() - d.t0, when))
    if d.batches.n:
        d._flush_samples()
    d._flush_frames(force=True)
    link = d.sidecar.link
    d.counters["telemetry_dropped"] += link.dropped if link else 0
    summary = d.batches.summary.result(d.events, dict(d.counters))
    summary["stop_reason"] = d.stop_reason
    # the loop's time zero on CLOCK_MONOTONIC: its times set beside another process's
    summary["clock_t0_s"] = d.t0
    summary["run_id"] = d.identity["run_id"]
    summary["controller"] = d.controller.name
    summary["reference"] = d.reference.kind
    if adaptation is not None:
        summary["adaptation"] = adaptation
    if d.exit_code == Exit.OK and d.supervisor.state is RigState.FAULT:
        d.exit_code = Exit.FAULT
    summary["exit_code"] = d.exit_code
    if d.crashed:
        summary["crashed"] = d.crashed
    qs = (50, 99, 99.9)
    summary["latency_split_us"] = {k: h.percentiles(qs) for k, h in d.batches.split_us.items()}
    summary["kernel_stalls"] = d.kernel_stalls.result()
    return summary
