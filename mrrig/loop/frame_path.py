"""The frame's path through the daemon: one DamperCommand per valid RigSensors frame.

`on_frame` (parse, check, count) -> `cycle` (Kalman -> force reference -> controller -> clamp
-> send, then the work off the latency path: the next frame's prediction and solve, the
sample row) -> `_send_command`. `check_timeout` answers SAFE on its own when the frames stop.
`FramePath` is the daemon's base: its state (the controller, the estimate, the supervisor, the
counters, the sample buffer) is built by `mrrig.loop.daemon.Daemon`, which also runs the loop
that calls it."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from typing import Any

from mrrig.loop import hil_loop
from mrrig.loop import reference as ref
from mrrig.loop.safety import Fault
from mrrig.loop.samples import RigState
from mrrig.loop.slew import loop_command

log = logging.getLogger(__name__)

# the faults of the error detectors' disarm and stop actions
# a sample row's fields in the order `cycle` writes them (SAMPLE_DTYPE's: a test checks)
ROW_FIELDS = (
    "t", "counter", "x", "x_est", "xd", "xdd", "f_meas", "f_des", "f_model", "i_cmd", "i_meas",
    "latency_us", "adapt_gain", "adapt_offset_n", "temp_degc", "state", "outside",
    *hil_loop.SAMPLE_FIELDS,
)  # fmt: skip
NO_HIL = (math.nan,) * len(hil_loop.SAMPLE_FIELDS)  # a daemon without [hil]

DETECTOR_FAULTS = {
    "tracking_error": Fault.TRACKING_ERROR,
    "velocity": Fault.OVER_VELOCITY,
    "temperature": Fault.OVER_TEMPERATURE,
}


class FramePath:
    """The daemon's answer to each frame (see the module's docstring for the order)."""

    # ---- frames ------------------------------------------------------------------------
    def on_frame(self, msg, t_rx: float, queued_s: float = 0.0) -> None:
        """One received frame; `queued_s` as in `cycle`."""
        self.counters["frames_received"] += 1
        if self.tap is not None:
            self.tap.rx(msg)
        if self._last_sensor_t is None:
            self.sensors.note_id(msg, t_rx)
        # 29-bit, remote and error frames are none of the DBC's 11-bit messages
        p = self.parser.parse_message(msg, t_rx)
        if p.name == self._sensor_msg:
            if not p.ok:
                self.counters["sensor_frames_invalid"] += 1
                self._emit(self.supervisor.bad_frame(t_rx - self.t0, p.reason))
                return
            self.counters["sensor_frames_valid"] += 1
            gap_s = self.sensors.gap_s(msg.timestamp)
            self._emit(self.sensors.counter_timing(msg.timestamp, p.lost_frames, t_rx - self.t0))
            if p.lost_frames:
                self.counters["lost_frames"] += p.lost_frames
                self._emit(self.supervisor.lost_frames(t_rx - self.t0, p.lost_frames))
            restart, self._restart_next = self._restart_next, False
            if gap_s > self.cfg.loop.timeout_periods * self.period_s:
                self._restart_next = True  # this frame may hold a sample from before the gap
                self._gap_s = gap_s
            if restart:
                self._restart_estimate(t_rx, p.values["Displacement"], self._gap_s)
            elif p.lost_frames:
                del self._targets[: p.lost_frames]  # those computed for the missing frames
                for _ in range(p.lost_frames):  # the estimate goes on through the missing periods
                    self.kf.predict_only()
            if self._last_sensor_t is None:
                self._first_sensor_t = t_rx
            if self._arm_pending and t_rx - self._first_sensor_t >= self.cfg.loop.arm_settle_s:
                self._arm_at_start(t_rx)
            counter = p.counter or 0  # None: a layout without E2E has no counter to echo
            self.cycle(p.values, counter, t_rx, queued_s)
            self._last_sensor_t = t_rx
            self._last_counter = counter
            if self._status_in_sensors:
                self._on_status(p.values, t_rx)
        elif p.name == self._status_msg and p.ok:
            self._on_status(p.values, t_rx)
        elif p.name in self._own_messages:
            self.counters["foreign_commands"] += 1
            self._emit(self.supervisor.foreign_command(t_rx - self.t0, p.name))
        elif not p.ok and p.name is None:
            self.counters["frames_ignored"] += 1
            log.debug("ignored frame: %s", p.reason)

    def _on_status(self, v: dict[str, float], t_rx: float) -> None:
        """The firmware's status (RigStatus, or the roles a profile has in another frame)."""
        self.counters["status_frames"] += 1
        self._i_meas = v["CoilCurrent"]
        self._temp_degc = v["DamperTemperature"]
        status = self.profile.firmware_status(v)
        if status is not None:
            t = t_rx - self.t0
            self._emit(self.supervisor.firmware_status(t, *status))
            if self.hil is not None:  # a stream fault of the firmware ends the run
                self._emit(self.hil.firmware_status(t, status[1], status[2], self.supervisor))

    def _restart_estimate(self, t_rx: float, x_meas: float, gap_s: float) -> None:
        """After a gap longer than the sensor timeout the 4-bit counter no longer tells how
        many periods passed (a 100 ms stall moved it on 2, not 50): predicting through the
        counter's periods would read the travel of the whole gap as a few periods' and the
        velocity would spike. The estimate and the force reference start again, as at the
        first frame, from the second frame after the gap: the first may carry a sample taken
        before it (the firmware sampled, then stalled before sending), and a filter started
        on it read the next frame's jump as a velocity of 1.8 m/s."""
        self.kf.reset(x_meas)
        self.reset_reference(t_rx - self.t0, x_meas)
        self.controller.reset(1)
        self.counters["estimate_restarts"] += 1
        log.info("estimate restarted after %.1f ms without sensor frames", gap_s * 1e3)

    def _arm_at_start(self, t_rx: float) -> None:
        """arm_on_start: once the sensor frames have streamed for arm_settle_s."""
        self._arm_pending = False
        if self.supervisor.state is not RigState.IDLE:
            log.warning("not armed at start: the daemon is in %s", self.supervisor.state.name)
            return
        ok, msg, events = self.supervisor.arm(t_rx - self.t0)
        if not ok:
            log.warning("arm at start refused: %s", msg)
        self.actuator_at_arm = self.actuator
        self.controller.reset(1)
        self.detectors.reset()
        self._emit(events)

    def check_timeout(self, now_abs: float) -> None:
        """No sensor frame for timeout_periods: FAULT, and a SAFE command on its own."""
        if self.hil is not None:  # a run's end and HOLD, STOP, with no frame to wait for
            self.hil.tick(now_abs - self.t0, self.supervisor)
        limit = self.cfg.loop.timeout_periods * self.period_s
        if self._last_sensor_t is None:
            self._emit(self.sensors.first_frame(now_abs, limit, now_abs - self.t0))
            return
        if now_abs - self._last_sensor_t <= limit:
            return
        if self.supervisor.state is not RigState.FAULT:
            self._emit(
                self.supervisor.trip(
                    now_abs - self.t0,
                    Fault.SENSOR_TIMEOUT,
                    f"no sensor frame for {(now_abs - self._last_sensor_t) * 1e3:.1f} ms",
                )
            )
        self._send_command(False, 0.0, 0.0, self._last_counter)
        self.counters["safe_commands_unprompted"] += 1
        self._last_sensor_t = now_abs  # again after another timeout period

    # ---- the cycle ---------------------------------------------------------------------
    def cycle(
        self, values: dict[str, float], counter: int, t_rx: float, queued_s: float = 0.0
    ) -> None:
        """One valid RigSensors frame -> exactly one DamperCommand.

        `queued_s`: how long the frame waited between its receive timestamp at the bus and
        `t_rx` (the loop reading it); its age when answered is that plus the cycle's time.
        A frame older than `loop.max_frame_age_s` is answered SAFE, and while armed the stall
        is a fault. An unexpected error in the computation does not unwind the loop: it is a
        fault, and the frame is still answered, SAFE.
        """
        sup = self.supervisor
        t = t_rx - self.t0
        x_meas, f_meas = values["Displacement"], values["Force"]
        events = sup.sensors(t, values)
        x = xd = xdd = f_des = math.nan
        i_cmd = 0.0
        try:
            x, xd, xdd = self.kf.update(x_meas)
            if self._last_sensor_t is None:
                self.reset_reference(t, x)
            events += sup.finite(t, "the Kalman estimate", x, xd, xdd)
            if self.hil is not None:  # the model steps on the measured force and stroke
                events += self.hil.on_frame(t, f_meas, x_meas, sup)
            f_next = None
            try:
                if self._pipelined():
                    f_des, f_next = self._targets_now(t, x, xd, xdd)
                else:
                    f_des = float(self.reference.forecast(t, x, xd))
            except ref.StaleReference as exc:
                f_des = 0.0
                if sup.active:
                    events += sup.trip(t, Fault.STALE_REFERENCE, f"stale force reference: {exc}")
            if f_next is None and self.controller.wants_next_target:
                f_next = f_des  # a reference not known ahead holds its present value
            # the clamp below passes NaN, and a controller may map it to a finite current
            what = f"the {self.reference.kind} force reference"
            targets = (f_des, f_des if f_next is None else f_next)
            events += sup.finite(t, what, *targets)
            if not all(math.isfinite(f) for f in targets):
                # a reference damper driven off its range keeps a NaN state: it starts again
                # here, or it would fault the rig again as soon as it left FAULT
                self.reset_reference(t, x_meas)
            f_des = self._clamp_force(f_des)
            if f_next is not None:
                f_next = self._clamp_force(f_next)
            if sup.active:
                events += self._detect(t, f_meas, f_des, xd)
            if sup.active:
                if self.controller.follows_reference:  # the ideal controller: the reference's
                    self.controller.follow(self.reference.current_at(t + self.period_s))
                i = self.controller.command_one(x, xd, xdd, f_meas, f_des, f_next)
                events += sup.finite(t, f"the {self.controller.name} controller's command", i)
                if sup.active:
                    i_cmd = self._slew_limit(i)
                if self.hil is not None:  # a law's current; the scenario's current range
                    i_cmd = self.hil.command(i_cmd, self.cfg.loop.i_max_a)
            else:  # disarmed: a model that carries the damper's state follows the motion
                self.controller.follow_motion(x, xd)
        except Exception as exc:  # noqa: BLE001 - a bug must not leave a frame unanswered
            log.exception("cycle failed")
            events += sup.trip(t, Fault.INTERNAL_ERROR, f"{type(exc).__name__}: {exc}")
            i_cmd = 0.0
        if self._stop and sup.active:
            # the stop answers this frame SAFE: the rig is disarmed from this frame on, and the
            # frame is recorded so (not as an armed frame whose command fell to 0 A)
            events += sup.disarm(t, f"stopping: {self.stop_reason}")
        age_s = queued_s + (time.perf_counter() - t_rx)
        if age_s > self._frame_age_limit_s:
            self.counters["stale_frames"] += 1
            if sup.active:
                events += sup.trip(
                    t,
                    Fault.STALE_FRAME,
                    f"sensor frame {age_s * 1e3:.1f} ms old when answered (limit "
                    f"{self._frame_age_limit_s * 1e3:g} ms): the daemon or the bus stalled",
                )
        active = sup.active
        safe_f = f_des if math.isfinite(f_des) else 0.0
        self._send_command(active, i_cmd if active else 0.0, safe_f, counter)
        active = active and sup.active  # a send that failed faulted it: answered SAFE
        if self.hil is not None:  # the frame's ActuatorSetpoint, after its command
            events += self.hil.after_command(self._send_frame, counter, t, sup)
        f_record = f_des
        if self._stop:
            self._safe_sent_at_stop = True
        work_us = (time.perf_counter() - t_rx) * 1e6
        latency_us = work_us + queued_s * 1e6
        b = self.batches
        b.split[b.n] = (queued_s * 1e6, work_us, self._send_call_s * 1e6)
        self._send_call_s = math.nan
        self.last_x = x
        f_model = math.nan
        try:
            if active:
                self.controller.after_send()  # on-line adaptation: armed, no fault this frame
            if self.reference.follows_motion:
                # this instant's desired force: the reference moved on along the motion as
                # estimated now that the frame has come (the targets were its forecasts)
                f_record = self._clamp_force(float(self.reference.force(t, x, xd)))
            # off the latency path: the next frame's Kalman step, reference and controller
            # work, from the predicted state
            self._prepare_next(t + self.period_s, active)
            if active:
                f_model = self.controller.model_force_one(x, xd, xdd, f_meas, f_des, i_cmd)
        except Exception as exc:  # noqa: BLE001
            log.exception("after-send work failed")
            events += sup.trip(t, Fault.INTERNAL_ERROR, f"{type(exc).__name__}: {exc}")
        env = self.envelope  # off the latency path: the command is sent
        adapt = getattr(self.controller, "adapt", None)
        # the row in one assignment, in SAMPLE_DTYPE's order (ROW_FIELDS): a field at a time
        # cost 18 us a frame
        b.buf[b.n] = (
            t, counter, x_meas, x, xd, xdd, f_meas, f_record, f_model,
            i_cmd if active else 0.0, self._i_meas, latency_us,
            math.nan if adapt is None else adapt.theta[0, 0],
            math.nan if adapt is None else adapt.offset_n[0],
            self._temp_degc, sup.state,
            math.nan if env is None else env.outside(x, xd, xdd, i_cmd),
            *NO_HIL,
        )  # fmt: skip
        if self.hil is not None:
            self.hil.record(b.buf[b.n])
        b.n += 1
        if b.n == len(b.buf):
            self._flush_samples()
        if events:
            self._emit(events)

    def _detect(self, t: float, f_meas: float, f_des: float, xd: float) -> list[dict]:
        """The error detectors on an armed frame, and their actions: `warn` an event,
        `disarm` a fault (this frame is answered SAFE), `stop` that and the actuator stopped
        (its command sent at the end of this pass of the loop, off the latency path)."""
        events: list[dict] = []
        for d in self.detectors.check(t, f_meas, f_des, xd, self._temp_degc):
            if d.action == "warn":
                events += self.supervisor.notice(t, "detector", d.text)
                continue
            if self.supervisor.active:
                events += self.supervisor.trip(t, DETECTOR_FAULTS[d.name], d.text)
            if d.action == "stop":
                self.actuator = replace(self.actuator, waveform="stop")
                self._last_actuator_sent = -math.inf
        return events

    def _pipelined(self) -> bool:
        """Whether the desired forces are computed a frame ahead (`_targets`): for a controller
        that solves for the instant its command acts on, with a reference known ahead."""
        return self.controller.wants_next_target and self.reference.known_ahead

    def reset_reference(self, t: float, x: float, reference: ref.ForceReference | None = None):
        """(Re)start the force reference (a new one if given) at time t; forget its forces
        computed ahead."""
        if reference is not None:
            self.reference = reference
        self.reference.reset(t, x)
        self._targets = []

    def restart_reference(self, t: float, x: float, reference: ref.ForceReference | None = None):
        """`reset_reference` for an arm or a new reference while the motion goes on: a
        reference damper keeps the state the estimated motion has put it in (that of the one
        it replaces, where that is the same damper), as the damper under test does."""
        state = self.reference.motion_state()
        self.reset_reference(t, x, reference)
        self.reference.resume(state)

    def _targets_now(self, t: float, x: float, xd: float, xdd: float) -> tuple[float, float]:
        """This frame's desired force and the next frame's: computed after the previous
        frames' commands (`_prepare_next`) where they were, else now, the next one at the
        state one period on (eq. 21): the reference's forecasts, each instant's once, on
        the frame sequence rather than on receive times, which jitter. A reference damper
        moves on after the command, on the estimate of the instant (`cycle`)."""
        T = self.period_s
        q = self._targets
        f_des = q[0] if q else float(self.reference.forecast(t, x, xd))
        if len(q) > 1:
            f_next = q[1]
        else:
            xn, xdn = x + xd * T + 0.5 * xdd * T * T, xd + xdd * T
            f_next = float(self.reference.forecast(t + T, xn, xdn))
        self._targets = [f_next]
        return f_des, f_next

    def _slew_limit(self, i_a: float) -> float:
        """The controller's command within [0, loop.i_max_a] and (a model's) within
        loop.max_current_slew_a_per_s of the last one sent (`slew.loop_command`, the HIL
        reference's too); a command the slew limit moved is counted."""
        sent, moved = loop_command(self.slew, self.controller, i_a, self.cfg.loop.i_max_a)
        self.counters["commands_slew_limited"] += moved
        return sent

    def _clamp_force(self, f_n: float) -> float:
        """A desired force inside `loop.f_range_n`, whatever its source (NaN passes, for the
        finiteness check to name)."""
        lo, hi = self.cfg.loop.f_range_n
        return min(max(f_n, lo), hi)

    def _prepare_next(self, t_next: float, active: bool) -> None:
        """What the next frame's cycle can know before the frame: the Kalman filter's
        prediction, gain and covariance, the reference for the predicted state (one instant
        further for a controller that solves one step ahead: `_targets_now`), and the
        controller's solve on it (`Controller.prepare_one`)."""
        kf = self.kf
        kf.prepare()
        xp, xdp, xddp = kf.prior
        if self._pipelined():
            if len(self._targets) != 1:
                return  # not after a frame's targets: the next frame computes its own
            T = self.period_s
            xn, xdn = xp + xdp * T + 0.5 * xddp * T * T, xdp + xddp * T
            self._targets.append(float(self.reference.forecast(t_next + T, xn, xdn)))
            if active:
                f_now, f_after = (self._clamp_force(f) for f in self._targets)
                self.controller.prepare_one(xp, xdp, xddp, f_now, f_after)
            return
        try:  # the frame's own desired force, forecast off its latency path
            f_next = float(self.reference.forecast(t_next, xp, xdp))
        except ref.StaleReference:
            return  # the frame itself will say so
        if not active:
            return
        f_next = self._clamp_force(f_next)
        wants = self.controller.wants_next_target
        self.controller.prepare_one(xp, xdp, xddp, f_next, f_next if wants else None)

    # ---- CAN ---------------------------------------------------------------------------
    def _send(self, name: str, values: dict[str, Any]) -> bool:
        """Encode and send; a failure of either (a value the profile cannot carry, the bus) is
        a BUS_ERROR fault, never the end of the loop."""
        try:
            msg = self.packer.message(name, values)
            t = time.perf_counter()
            self.bus.send(msg, timeout=self.cfg.bus.send_timeout_s)
            self._send_call_s = time.perf_counter() - t
            if self.tap is not None:
                self.tap.tx(msg)
            return True
        except Exception as exc:  # noqa: BLE001 - any bus failure is a BUS_ERROR fault
            self.counters["send_failures"] += 1
            self._emit(self.supervisor.trip(self.now(), Fault.BUS_ERROR, f"send {name}: {exc}"))
            return False

    def _send_command(self, active: bool, current_a: float, f_des: float, echo: int) -> None:
        self.slew.sent(current_a if active else None)
        ok = self._send(
            self.profile.command_message,
            {
                "Mode": 1 if active else 0,
                "CurrentSetpoint": current_a if active else 0.0,
                "SensorCounterEcho": echo,
                "ControllerId": self.controller.controller_id if active else 0,
                "DesiredForce": f_des if active else 0.0,
            },
        )
        if ok:
            self.counters["commands_sent"] += 1
            self.counters["commands_active"] += active
        elif active:  # in FAULT now: the frame is answered SAFE, if that can be sent
            self._send_command(False, 0.0, 0.0, echo)

    def _send_frame(self, msg) -> bool:
        """Send a frame already encoded (the HIL's ActuatorSetpoint); a failure is a
        BUS_ERROR fault, as in `_send`."""
        try:
            self.bus.send(msg, timeout=self.cfg.bus.send_timeout_s)
            if self.tap is not None:
                self.tap.tx(msg)
            return True
        except Exception as exc:  # noqa: BLE001 - any bus failure is a BUS_ERROR fault
            self.counters["send_failures"] += 1
            self._emit(self.supervisor.trip(self.now(), Fault.BUS_ERROR, f"send setpoint: {exc}"))
            return False
