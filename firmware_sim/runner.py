"""The simulator's I/O loop: an absolute-deadline 2 ms clock around `Firmware` and a CAN bus.

One thread, no Notifier: the loop waits for command frames in `bus.recv(timeout)` (a select
on the socket for the remote bridge) until `lead_s` before the next deadline, computes the
frame (plant step and encoding, 0.1-0.2 ms here), waits in `recv` again until `spin_s`
before the deadline, then busy-waits, still polling the bus, and sends. Deadlines are
t0 + k * period, so the rate never drifts; the busy tail is short, so the CPU stays low.
Received frames are applied on arrival; the plant uses the latest command received before it
computes a frame (a zero-order hold, as the firmware's coil driver would).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import math
import os
import time
from array import array
from collections.abc import Callable
from typing import Any

import can
import numpy as np

from firmware_sim.firmware import Firmware, Frame

logger = logging.getLogger(__name__)

# Below this much time to the deadline the loop spins without polling the bus.
_POLL_MARGIN_S = 50e-6
# Late by more than this many periods (a stalled VM): skip the missed deadlines.
_RESYNC_PERIODS = 10
_PR_SET_TIMERSLACK = 29


class RunStats:
    """What the loop measured: frames, answers per sensor frame, latency, jitter, CPU."""

    def __init__(self) -> None:
        self.sensor_frames_sent = 0
        self.sensor_frames_faulted = 0  # sent with a fault injected: no answer expected
        self.status_frames_sent = 0
        self.answered_once = 0
        self.unanswered = 0
        self.answered_more_than_once = 0
        self.unmatched_answers = 0  # valid commands echoing no frame awaiting an answer
        self.resyncs = 0
        self.latency_us = array("d")
        self.jitter_us = array("d")
        self._pending_counter = -1
        self._pending_send_s = 0.0
        self._pending_answers = 0

    def _close_pending(self) -> None:
        if self._pending_counter < 0:
            return
        n = self._pending_answers
        if n == 0:
            self.unanswered += 1
        elif n == 1:
            self.answered_once += 1
        else:
            self.answered_more_than_once += 1

    def on_sensor_sent(self, frame: Frame, ideal_s: float, sent_s: float) -> None:
        """A RigSensors frame left at sent_s for the deadline ideal_s (same clock)."""
        self._close_pending()
        self.sensor_frames_sent += 1
        self.jitter_us.append((sent_s - ideal_s) * 1e6)
        if frame.expect_answer:
            self._pending_counter = frame.counter
            self._pending_send_s = sent_s
            self._pending_answers = 0
        else:
            self.sensor_frames_faulted += 1
            self._pending_counter = -1

    def on_command(self, echo: int, received_s: float) -> None:
        """A valid DamperCommand echoing sensor counter `echo` arrived at received_s."""
        if echo != self._pending_counter:
            self.unmatched_answers += 1
            return
        if self._pending_answers == 0:
            self.latency_us.append((received_s - self._pending_send_s) * 1e6)
        self._pending_answers += 1

    def summary(self, firmware: Firmware, wall_s: float, cpu_s: float) -> dict[str, Any]:
        """The stats file's content (the last frame, still awaiting its answer, is left out)."""
        return {
            "wall_s": wall_s,
            "sensor_frames_sent": self.sensor_frames_sent,
            "sensor_frames_faulted": self.sensor_frames_faulted,
            "status_frames_sent": self.status_frames_sent,
            "commands": firmware.command_counts(),
            "answers": {
                "answered_once": self.answered_once,
                "unanswered": self.unanswered,
                "answered_more_than_once": self.answered_more_than_once,
                "unmatched": self.unmatched_answers,
            },
            "answer_latency_us": _percentiles(self.latency_us),
            "period_jitter_us": _percentiles(self.jitter_us),
            "cpu_fraction": cpu_s / wall_s if wall_s > 0.0 else 0.0,
            "resyncs": self.resyncs,
            "watchdog_trips": firmware.watchdog_trips,
            "max_commanded_current_a": firmware.max_commanded_current_a,
            "fault_events": [{"t_s": round(t, 6), "event": e} for t, e in firmware.events],
        }


def _percentiles(values: array) -> dict[str, float | int | None]:
    if not values:
        return {"n": 0, "p50": None, "p99": None, "max": None}
    a = np.frombuffer(values, dtype=float)
    p50, p99 = np.percentile(a, [50, 99])
    return {"n": int(a.size), "p50": float(p50), "p99": float(p99), "max": float(a.max())}


def tune_process(realtime_priority: int) -> None:
    """Timer slack 1 ns (select wakes on time) and, if asked, SCHED_FIFO; warn where denied."""
    libc_name = ctypes.util.find_library("c")
    if libc_name is not None:
        libc = ctypes.CDLL(libc_name, use_errno=True)
        if libc.prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0) != 0:
            logger.warning("cannot set timer slack: errno %d", ctypes.get_errno())
    if realtime_priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(realtime_priority))
            logger.info("SCHED_FIFO priority %d", realtime_priority)
        except (PermissionError, AttributeError, OSError) as exc:
            logger.warning("SCHED_FIFO priority %d not permitted (%s): normal scheduling",
                           realtime_priority, exc)


def run(
    firmware: Firmware,
    bus: can.BusABC,
    stats: RunStats,
    *,
    lead_s: float,
    spin_s: float,
    send_timeout_s: float,
    duration_s: float | None = None,
    should_stop: Callable[[], bool] = lambda: False,
    clock: Callable[[], float] = time.monotonic,
) -> None:
    """Run the firmware on `bus` until `should_stop()` or `duration_s`, filling `stats`.

    Bus errors (`can.CanError`, the remote bridge gone) propagate; `stats` keeps what was
    measured until then.
    """
    period_s = firmware.period_s
    sensors_id = firmware.sensors_id
    damper_id = firmware.damper_command_id

    def receive_until(until: float) -> None:
        while (now := clock()) < until:
            msg = bus.recv(until - now)
            if msg is not None:
                _receive(firmware, stats, msg, clock() - t0, damper_id)

    gc.collect()
    gc.freeze()
    t0 = clock()
    k = 0
    try:
        while not should_stop():
            ideal_s = k * period_s
            if duration_s is not None and ideal_s > duration_s:
                break
            deadline = t0 + ideal_s
            receive_until(deadline - lead_s)
            frames = firmware.tick(ideal_s)
            receive_until(deadline - spin_s)
            while (now := clock()) < deadline:
                if deadline - now > _POLL_MARGIN_S:
                    msg = bus.recv(0.0)
                    if msg is not None:
                        _receive(firmware, stats, msg, clock() - t0, damper_id)
            for frame in frames:
                sent_s = clock() - t0
                bus.send(
                    can.Message(arbitration_id=frame.frame_id, is_extended_id=False,
                                dlc=len(frame.data), data=frame.data),
                    timeout=send_timeout_s,
                )
                if frame.frame_id == sensors_id:
                    stats.on_sensor_sent(frame, ideal_s, sent_s)
                else:
                    stats.status_frames_sent += 1
            k += 1
            late_s = clock() - (t0 + k * period_s)
            if late_s > _RESYNC_PERIODS * period_s:
                skipped = math.ceil(late_s / period_s)
                logger.warning("loop %.1f ms late: skipping %d periods", late_s * 1e3, skipped)
                stats.resyncs += 1
                k += skipped
    finally:
        gc.unfreeze()


def _receive(
    firmware: Firmware, stats: RunStats, msg: can.Message, t_s: float, damper_id: int
) -> None:
    if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
        return
    parsed = firmware.on_frame(msg.arbitration_id, bytes(msg.data), t_s)
    if parsed is not None and parsed.ok and msg.arbitration_id == damper_id:
        assert parsed.values is not None
        stats.on_command(int(parsed.values["SensorCounterEcho"]), t_s)
