"""The simulator's I/O loop: an absolute-deadline 2 ms clock around `Firmware` and a CAN bus.

One thread, no Notifier: the loop waits for command frames in `bus.recv(timeout)` (a select
on the socket for the remote bridge) until `lead_s` before the next deadline, computes the
frame (plant step and encoding), waits in `recv` again until `spin_s`
before the deadline, then busy-waits, still polling the bus, and sends. Deadlines are
t0 + k * period, so the rate never drifts; the busy tail is short, so the CPU stays low.
Received frames are applied on arrival; the plant uses the latest command received before it
computes a frame (a zero-order hold, as the firmware's coil driver would).
"""

from __future__ import annotations

import collections
import gc
import logging
import math
import time
from array import array
from collections.abc import Callable
from typing import Any

import numpy as np

from firmware_sim.firmware import Firmware, Frame
from mrrig.loop.realtime import make_realtime
from mrrig.pycan import can
from mrrig.rigio.canbus.layout import frame_key

logger = logging.getLogger(__name__)

# Below this much time to the deadline the loop spins without polling the bus.
_POLL_MARGIN_S = 50e-6
# Late by more than this many periods (a stalled VM): skip the missed deadlines.
_RESYNC_PERIODS = 10


class RunStats:
    """What the loop measured: frames, answers per sensor frame, latency, jitter, CPU."""

    # Answers come in frame order (one per frame as soon as computed, over a FIFO bus): an
    # answer is for the first frame after the last answered one that has its counter (counters
    # wrap at 16), so a transport stall of up to WINDOW periods delays answers without mixing
    # them up. After RESYNC_S without any answer (the first answer; a daemon restarted) the
    # frames before went unanswered, and the answer is for the newest frame with its counter.
    WINDOW = 64  # frames awaiting an answer, at most (128 ms)
    RESYNC_S = 0.1
    # a repeated answer is looked for among the last REPEATS answered frames
    REPEATS = 16
    STALE_KEPT = 100  # stale ACTIVE answers listed in the stats, at most
    # Held up by more than this, a frame marks a stall window. The simulator's own: a sensor
    # frame sent this late after its deadline (its process did not run), from the frame sent
    # before to this one, and the periods skipped after a long stall. The transport's
    # (`measure_echo`: the bus echoes this process's own frames, through the bridge and back):
    # an echo this late, from the send to the echo. A frame sent late is not "on time".
    LATE_S = 0.005

    def __init__(self, measure_echo: bool = False, stale_answer_age_s: float = math.inf) -> None:
        self.stale_answer_age_s = stale_answer_age_s
        # ACTIVE answers that reached the bus more than stale_answer_age_s after the frame they
        # answer did (its bus timestamp from the echo, with measure_echo; else its send)
        self.active_answers_stale = 0
        # each of those: [counter, frame_s, answer_s], when the bus took the frame in and the
        # answer, on this process's clock (the first STALE_KEPT of them)
        self.stale_answers: list[list[float]] = []
        # ACTIVE commands the firmware applied (not late): the age of the frame each answers
        # when it came, on this process's clock from the frame's send; over
        # stale_answer_age_s, or answering no frame that awaits an answer, each is counted
        self.applied_active_age_us = array("d")
        self.active_applied_stale = 0
        self.active_applied_invalid = 0
        self._wall_minus_clock_s = math.nan  # time.time() - this process's clock
        self.sensor_frames_sent = 0
        self.sensor_frames_faulted = 0  # sent with a fault injected: no answer expected
        self.status_frames_sent = 0
        self.answered_once = 0
        self.answered_late = 0  # of answered_once: arrived after the next sensor frame
        self.unanswered = 0
        self.answered_more_than_once = 0
        self.unmatched_answers = 0  # valid commands echoing no frame sent lately
        # SAFE commands repeating the counter of the last answered frame: the daemon's own SAFE
        # after a sensor timeout (spec/system.md), not a second answer
        self.safe_repeats = 0
        self._last_echo: int | None = None
        self._last_command_s: float | None = None
        self.resyncs = 0
        self.latency_us = array("d")
        self.jitter_us = array("d")
        # [counter, send time, answers, answered late]: frames after the last answered one,
        # and the last answered frames
        self._awaiting: collections.deque[list] = collections.deque()
        self._answered: collections.deque[list] = collections.deque()
        # frames sent on time (no stall of this process): each must get exactly one answer
        self.on_time = {"frames": 0, "answered_once": 0, "unanswered": 0, "more_than_once": 0}
        self.clock_t0_s = math.nan  # the run's time zero on the clock `run` was given
        self._last_sent_s = math.inf
        self.stall_windows: list[list] = []  # [kind, start_s, end_s]
        self.measure_echo = measure_echo
        self.echo_us = array("d")
        self._echo_awaiting: collections.deque[tuple[int, float]] = collections.deque()

    def _close(self, entry: list) -> None:
        n = entry[2]
        if n == 0:
            self.unanswered += 1
        elif n == 1:
            self.answered_once += 1
            self.answered_late += entry[3]
        else:
            self.answered_more_than_once += 1
        if entry[4]:
            key = ("unanswered", "answered_once", "more_than_once")[min(n, 2)]
            self.on_time[key] += 1

    def stall(self, kind: str, start_s: float, end_s: float) -> None:
        """A window in which `kind` ("simulator", "transport") held frames up; windows of one
        kind that overlap or touch are merged."""
        for w in reversed(self.stall_windows):
            if w[0] == kind:
                if start_s <= w[2] + self.LATE_S:
                    w[1], w[2] = min(w[1], start_s), max(w[2], end_s)
                    return
                break
        self.stall_windows.append([kind, start_s, end_s])

    def on_sensor_sent(
        self, frame: Frame, ideal_s: float, sent_s: float, sent_wall_s: float | None = None
    ) -> None:
        """A RigSensors frame left at sent_s for the deadline ideal_s (same clock); at
        sent_wall_s on time.time(), the bus timestamps' clock."""
        self.sensor_frames_sent += 1
        if sent_wall_s is not None:
            self._wall_minus_clock_s = sent_wall_s - sent_s
        self.jitter_us.append((sent_s - ideal_s) * 1e6)
        on_time = sent_s - ideal_s <= self.LATE_S
        if not on_time:  # the process last ran when it sent the frame before
            self.stall("simulator", min(ideal_s, self._last_sent_s), sent_s)
        self._last_sent_s = sent_s
        if self.measure_echo:
            self._echo_awaiting.append((frame.counter, sent_s))
            if len(self._echo_awaiting) > self.WINDOW:
                start_s = self._echo_awaiting.popleft()[1]
                self.stall("transport", start_s, sent_s)  # its echo never came
        if frame.expect_answer:
            self.on_time["frames"] += on_time
            self._awaiting.append([frame.counter, sent_s, 0, False, on_time, sent_wall_s])
            if len(self._awaiting) > self.WINDOW:
                self._close(self._awaiting.popleft())
        else:
            self.sensor_frames_faulted += 1

    def _applied(self, entry: list | None, received_s: float) -> None:
        """An ACTIVE command the firmware applied, answering `entry` (None: no frame sent
        lately that awaits an answer)."""
        if entry is None:
            self.active_applied_invalid += 1
            return
        age_s = received_s - entry[1]
        self.applied_active_age_us.append(age_s * 1e6)
        self.active_applied_stale += age_s > self.stale_answer_age_s

    def on_command(
        self,
        echo: int,
        received_s: float,
        safe: bool = False,
        bus_ts_s: float | None = None,
        applied: bool = False,
    ) -> None:
        """A valid DamperCommand echoing sensor counter `echo` arrived at received_s; the bus
        stamped it bus_ts_s (time.time(): the kernel's on SocketCAN, the bridge's on the
        Python bridge), which is when it was sent as far as the bus can tell. `applied`: an
        ACTIVE command the firmware applied (not late)."""
        if safe and echo == self._last_echo:
            self.safe_repeats += 1
            return
        self._last_echo = echo
        in_turn = (
            self._last_command_s is not None and received_s - self._last_command_s <= self.RESYNC_S
        )
        self._last_command_s = received_s
        awaiting = self._awaiting
        ks = [k for k, entry in enumerate(awaiting) if entry[0] == echo]
        if ks:
            k = ks[0] if in_turn else ks[-1]
            for _ in range(k):  # frames the answers passed by
                self._close(awaiting.popleft())
            entry = awaiting.popleft()
            entry[2], entry[3] = 1, bool(awaiting)
            self.latency_us.append((received_s - entry[1]) * 1e6)
            # the frame's age when the answer reached the bus (this process's own reading
            # delay is no part of the daemon's answer), else when it reached this process
            if bus_ts_s is not None and entry[5] is not None:
                age_s = bus_ts_s - entry[5]
                frame_s, answer_s = (t - self._wall_minus_clock_s for t in (entry[5], bus_ts_s))
            else:
                age_s = received_s - entry[1]
                frame_s, answer_s = entry[1], received_s
            if not safe and age_s > self.stale_answer_age_s:
                self.active_answers_stale += 1
                if len(self.stale_answers) < self.STALE_KEPT:
                    self.stale_answers.append([echo, frame_s, answer_s])
            self._answered.append(entry)
            if len(self._answered) > self.REPEATS:
                self._close(self._answered.popleft())
            if applied:
                self._applied(entry, received_s)
            return
        for entry in reversed(self._answered):
            if entry[0] == echo:
                entry[2] += 1
                if applied:
                    self._applied(entry, received_s)
                return
        self.unmatched_answers += 1
        if applied:
            self._applied(None, received_s)

    def on_echo(self, counter: int, received_s: float, bus_ts_s: float | None = None) -> None:
        """This process's own RigSensors frame with `counter`, echoed back by the bus, which
        stamped it bus_ts_s (time.time()): the receive timestamp that the daemon measures the
        frame's age from (spec/system.md), and so the stale-answer count too."""
        awaiting = self._echo_awaiting
        while awaiting:
            sent_counter, sent_s = awaiting.popleft()
            if sent_counter == counter:
                self.echo_us.append((received_s - sent_s) * 1e6)
                if received_s - sent_s > self.LATE_S:
                    self.stall("transport", sent_s, received_s)
                if bus_ts_s is not None:
                    for entry in reversed(self._awaiting):
                        if entry[0] == counter:
                            entry[5] = bus_ts_s
                            break
                return

    def finish(self) -> None:
        """Count every frame, once the answers have had the time they have while the run goes
        on (`run` listens WINDOW periods after the last frame)."""
        for queue in (self._answered, self._awaiting):
            while queue:
                self._close(queue.popleft())

    def summary(self, firmware: Firmware, wall_s: float, cpu_s: float) -> dict[str, Any]:
        """The stats file's content (call `finish()` first)."""
        return {
            "wall_s": wall_s,
            "sensor_frames_sent": self.sensor_frames_sent,
            "sensor_frames_faulted": self.sensor_frames_faulted,
            "status_frames_sent": self.status_frames_sent,
            "commands": firmware.command_counts(),
            "answers": {
                "answered_once": self.answered_once,
                "answered_late": self.answered_late,
                "unanswered": self.unanswered,
                "answered_more_than_once": self.answered_more_than_once,
                "unmatched": self.unmatched_answers,
                "safe_repeats": self.safe_repeats,
                "active_to_stale": self.active_answers_stale,
                "active_applied_to_stale": self.active_applied_stale,
                "active_applied_to_invalid": self.active_applied_invalid,
            },
            # ACTIVE commands not applied: they answered an older frame than the latest sent
            "late_commands": firmware.late_commands,
            # ActuatorSetpoints dropped as late, and those clamped to the envelope (STREAM)
            "late_setpoints": firmware.late_setpoints,
            "clamped_setpoints": firmware.clamped_setpoints,
            # the dropped ones' times (the run's clock, as stall_windows) and echoes
            "late_setpoint_times": [
                {"t_s": round(t, 6), "echo": e} for t, e in firmware.late_setpoint_times
            ],
            "applied_active_age_us": _percentiles(self.applied_active_age_us),
            "armed_motion": [
                {k: round(v, 6) if math.isfinite(v) else None for k, v in m._asdict().items()}
                for m in firmware.armed_motion
            ],
            "stale_answers": [
                {"counter": c, "frame_s": round(a, 6), "answer_s": round(b, 6)}
                for c, a, b in self.stale_answers
            ],
            "answers_on_time": dict(self.on_time),
            "clock_t0_s": self.clock_t0_s,
            "stall_windows": [
                {"kind": k, "start_s": round(a, 6), "end_s": round(b, 6)}
                for k, a, b in self.stall_windows
            ],
            "echo_us": _percentiles(self.echo_us),
            "stale_answer_age_s": self.stale_answer_age_s,
            "answer_latency_us": _percentiles(self.latency_us),
            "period_jitter_us": _percentiles(self.jitter_us),
            "cpu_fraction": cpu_s / wall_s if wall_s > 0.0 else 0.0,
            "resyncs": self.resyncs,
            "watchdog_trips": firmware.watchdog_trips,
            "max_commanded_current_a": firmware.max_commanded_current_a,
            "damper_temperature_degc": firmware.temperature_degc,
            "fault_events": [{"t_s": round(t, 6), "event": e} for t, e in firmware.events],
        }


def _percentiles(values: array) -> dict[str, float | int | None]:
    if not values:
        return {"n": 0, "p50": None, "p99": None, "max": None}
    # a copy taken without exporting the array's buffer: the loop may append to it meanwhile,
    # and an append to an array whose buffer is exported raises BufferError
    a = np.array(values.tolist(), dtype=float)
    p50, p99 = np.percentile(a, [50, 99])
    return {"n": int(a.size), "p50": float(p50), "p99": float(p99), "max": float(a.max())}


def tune_process(realtime_priority: int, poll_idle: bool = True) -> None:
    """Timer slack 1 ns (select wakes on time), locked memory and, if asked, SCHED_FIFO and
    idle CPUs that poll rather than halt."""
    make_realtime(
        realtime_priority,
        who="firmware_sim",
        wakeup_latency_us=0 if realtime_priority > 0 and poll_idle else None,
    )


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
    time_scale: float = 1.0,
) -> None:
    """Run the firmware on `bus` until `should_stop()` or `duration_s`, filling `stats`.

    `time_scale` > 1 slows the whole firmware down by that factor against the wall clock
    (every period, the watchdog and every timeout alike) for machines that cannot hold the
    real rate, such as a software-emulated VM; the plant still integrates its own 2 ms steps.

    Bus errors (`can.CanError`, the remote bridge gone) propagate; `stats` keeps what was
    measured until then.
    """
    period_s = firmware.period_s
    sensors_key = firmware.sensors_key
    if time_scale != 1.0:
        wall_clock = clock

        def clock() -> float:
            return wall_clock() / time_scale

    damper_key = firmware.damper_command_key

    def receive_until(until: float) -> None:
        while (now := clock()) < until:
            msg = bus.recv((until - now) * time_scale)
            if msg is not None:
                _receive(firmware, stats, msg, clock() - t0, damper_key)

    gc.collect()
    gc.freeze()
    t0 = clock()
    stats.clock_t0_s = t0
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
                        _receive(firmware, stats, msg, clock() - t0, damper_key)
            for frame in frames:
                sent_s, sent_wall_s = clock() - t0, time.time()
                bus.send(
                    can.Message(
                        arbitration_id=frame.frame_id,
                        is_extended_id=frame.is_extended,
                        is_fd=frame.is_fd,
                        dlc=len(frame.data),
                        data=frame.data,
                    ),
                    timeout=send_timeout_s,
                )
                firmware.sent(frame, sent_s)
                if frame_key(frame.frame_id, frame.is_extended) == sensors_key:
                    stats.on_sensor_sent(frame, ideal_s, sent_s, sent_wall_s)
                else:
                    stats.status_frames_sent += 1
            k += 1
            late_s = clock() - (t0 + k * period_s)
            if late_s > _RESYNC_PERIODS * period_s:
                skipped = math.ceil(late_s / period_s)
                logger.warning("loop %.1f ms late: skipping %d periods", late_s * 1e3, skipped)
                stats.resyncs += 1
                stats.stall("simulator", (k - 1) * period_s, clock() - t0)
                k += skipped
        # answers still in flight when the last frame left: listen as long as an answer to an
        # earlier frame is waited for, then `stats.finish()` counts every frame
        receive_until(clock() + RunStats.WINDOW * period_s)
    finally:
        gc.unfreeze()


def _receive(
    firmware: Firmware, stats: RunStats, msg: can.Message, t_s: float, damper_key: int
) -> None:
    if msg.is_remote_frame or msg.is_error_frame:
        return
    key = frame_key(msg.arbitration_id, msg.is_extended_id)
    if key == firmware.sensors_key:  # our own, echoed back
        counter = firmware.sensor_counter(bytes(msg.data))
        if stats.measure_echo and counter is not None:
            stats.on_echo(counter, t_s, msg.timestamp or None)
        return
    late_before = firmware.late_commands
    parsed = firmware.on_frame(
        msg.arbitration_id, bytes(msg.data), t_s, msg.is_extended_id, msg.is_fd
    )
    if parsed is not None and parsed.ok and key == damper_key:
        assert parsed.values is not None
        mode, _, echo = firmware.command_of(parsed.values)
        safe = mode == "SAFE"
        applied = not safe and firmware.late_commands == late_before
        stats.on_command(echo, t_s, safe, msg.timestamp or None, applied)
