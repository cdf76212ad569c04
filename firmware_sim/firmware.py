"""The simulated rig firmware as a pure state machine: frames and a clock in, frames out.

`Firmware.on_frame(frame_id, data, t_s)` takes a received frame, `Firmware.tick(t_s)` advances
the rig by one RigSensors period and returns the frames to send; no I/O, no clock of its own,
so the CAN contract's firmware rules (`spec/can-protocol.md`) are tested by calling it.
Times are seconds since boot. The DBC gives the periods, the layouts and the value tables
(State, FaultCode, Mode and Waveform are handled by their labels).

Choices the contract leaves open, made here:
- Before the first valid DamperCommand the watchdog is not armed and State is IDLE (BOOT in
  the very first RigStatus only). Any valid DamperCommand, SAFE or ACTIVE, feeds the watchdog.
- In State FAULT (watchdog, e-stop, stroke limit) the coil command is 0 A. After a watchdog
  trip, 5 consecutive valid ACTIVE commands return it to RUNNING (the contract); 5 consecutive
  valid SAFE commands return it to IDLE, so a daemon that stopped and now sends SAFE can see
  the firmware healthy before it re-arms. A gap of more than 20 ms restarts the count.
- The actuator timeout (500 ms) is armed by the first valid ActuatorCommand, so an autostart
  motion runs until a daemon takes over.
- FaultCode shows the most important active condition: e-stop 5, stroke limit 3, watchdog 1,
  sensor fault 4, actuator timeout 1, setpoint timeout 7, setpoint clamped 3, bad command
  frames 6, setpoint over limit 2.
- A frame the profile cannot encode (a value beyond its signal's range) is not sent: the
  firmware faults as for a sensor fault (coil to 0 A, State FAULT, FaultCode and SensorFault
  set in the next frame it can send) and goes on; 5 consecutive valid SAFE commands clear it
  once its frames encode again.
- corrupt_crc, freeze_counter and drop_frames act on RigSensors; silent stops every frame.
  During an e-stop or stroke-limit injection the actuator ramps to rest (ActuatorEnabled 0)
  and ActuatorCommands are ignored; the next one after the injection ends moves it again.
- Fault windows hold round(duration / period) ticks (at least one): tick times are ideal.
- Late commands (the contract: an ACTIVE command that does not echo the latest RigSensors
  frame sent is not applied): the runner says when a frame left (`sent`). A command that
  comes more than one period after the latest frame left is late too: the next frame is
  overdue because this process was held up, and a firmware on time would have sent it.
  A late command feeds the watchdog and neither adds to nor breaks a recovery count.
- STREAM (contract 1.1): entering it, the piston stays where it is until the first setpoint;
  then it follows the latest valid ActuatorSetpoint (`Actuator.follow`, one place), clamped
  to the STREAM command's envelope and the stroke (FaultCode 3 while the latest is clamped).
  A late setpoint (the same rule as a late command) is dropped, counted (`late_setpoints`),
  its time and echo listed (`late_setpoint_times`, the first `MAX_LATE_LISTED`: what a HIL
  run's tracking error may set aside as a measured stall) and does not feed the setpoint
  watchdog. No valid setpoint for more than 20 ms (from the
  last one, or from entering STREAM): HOLD where it is (FaultCode 7); a valid setpoint within
  500 ms of the last one resumes the stream; else, at 500 ms, it ramps to rest (FaultCode 7
  stays). A repeated STREAM command (the daemon's every 100 ms) does not restart a stream
  that ramped to rest: only one after a command of another waveform does (which also clears
  FaultCode 7). The daemon's ActuatorCommand timeout (500 ms) applies to STREAM as to SINE.

A test instrument, not firmware: `armed_motion` lists the stretches of ACTIVE commands (from
the first valid ACTIVE command after a SAFE one to the next SAFE one: the daemon's ARMED,
through watchdog trips), each with the actuator's amplitude and frequency in force when it
began (the larger of the motion's and the commanded one) and the largest the motion reached
during it (at each tick: a command's ramp needs ticks to show), for `mrrig bench fuzz` to hold
against the limits the daemon was armed with.
"""

from __future__ import annotations

import logging
import math
import random
from collections import deque
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from damper.plant import BoucWenDamper, BoucWenParams, params_at_temperature
from damper.plant_file import load_plant
from firmware_sim.actuator import ServoActuator
from firmware_sim.config import FaultSpec, SimConfig
from firmware_sim.motion import Actuator, MotionStretch
from mrrig.rigio.canbus.codec import EncodeError, Packer, Parsed
from mrrig.rigio.canbus.layout import MessageLayout, frame_key
from mrrig.rigio.canbus.profile import RigProfile

logger = logging.getLogger(__name__)

# The CAN contract's firmware numbers (spec/can-protocol.md, "Firmware behaviour").
WATCHDOG_TIMEOUT_S = 0.020
RECOVERY_COMMANDS = 5
ACTUATOR_TIMEOUT_S = 0.5
MAX_LATE_LISTED = 10000  # late setpoints listed with their time (all of them counted)
PLANT_PRESET = "rig-current"
HEATING_STEP_K = 0.01  # the plant's parameters are updated when the temperature moved this much


class Frame(NamedTuple):
    """One frame to send; `expect_answer` marks a clean RigSensors frame (one command due).
    `counter`: its E2E counter; in a layout without E2E, this firmware's own count of its
    sensor frames (never on the bus: the simulator's bookkeeping of answers)."""

    frame_id: int
    data: bytes
    counter: int
    expect_answer: bool
    is_extended: bool = False
    is_fd: bool = False


def _counter(layout: MessageLayout, data: bytes) -> int:
    return (int.from_bytes(data, "little") >> layout.counter_shift) & layout.counter_mask


class Firmware:
    """The rig firmware: command handling, watchdog, actuator, damper plant, sensors, faults."""

    def __init__(
        self, config: SimConfig, profile: RigProfile, faults: Sequence[FaultSpec] | None = None
    ) -> None:
        """`profile`: the rig profile (`[can]`, the same table as the daemon's): which
        messages carry which roles, in which units."""
        self._cfg = config
        self._profile = profile
        codec = profile.codec
        sensors = profile.sensor_layout
        status = codec.layout(profile.status_message) if profile.status_message else None
        # the status roles ride in the sensor frame, in a message of their own, or nowhere
        self._status_in_sensors = status is sensors
        sends = (sensors.name,) + ((status.name,) if status and status is not sensors else ())
        self._packer = Packer(codec, None, sends)
        self._parser = codec.parser()
        if sensors.period_s is None:
            raise ValueError(f"{codec.dbc_path}: {sensors.name} needs GenMsgCycleTime")
        self.period_s: float = sensors.period_s
        self._status_every = 0
        if status is not None and not self._status_in_sensors:
            if status.period_s is None:
                raise ValueError(f"{codec.dbc_path}: {status.name} needs GenMsgCycleTime")
            self._status_every = round(status.period_s / sensors.period_s)
        self._sensors = sensors
        self._status = status
        self.sensors_id = sensors.frame_id
        self.sensors_key = sensors.key
        coil = next((f for f in (status.fields if status else ()) if f.name == "CoilCurrent"), None)
        self._coil_current_max_a = (
            math.inf if coil is None else coil.raw_max * coil.scale + coil.offset
        )
        command = codec.layout(profile.command_message)
        self.damper_command_id = command.frame_id
        self.damper_command_key = command.key
        actuator = profile.actuator_message
        self._actuator_key = codec.layout(actuator).key if actuator is not None else None
        setpoint = profile.setpoint_message
        self._setpoint_key = codec.layout(setpoint).key if setpoint is not None else None
        self._mode_labels = self._labels("command_mode")
        self._waveform_labels = self._labels("actuator_waveform")
        self._fault_labels = {v: k for k, v in self._labels("firmware_fault").items()}
        self._sent_sensor_frames = 0
        # without E2E: the latest sensor payloads and this firmware's count of each (the
        # measured echo of a frame is found by its bytes)
        self._recent_payloads: deque[tuple[bytes, int]] = deque(maxlen=64)

        self._faults = tuple(config.faults if faults is None else faults)
        self._fault_on = [False] * len(self._faults)
        self.active_faults: frozenset[str] = frozenset()

        self._gauss = random.Random(config.seed).gauss
        self.actuator = Actuator(config.actuator, self.period_s, np.random.default_rng(config.seed))
        act = config.actuator
        # the piston behind the motion generator (`[actuator.servo] waveforms`) or a STREAM
        servo = act.servo.actual()
        self.servo = ServoActuator(servo, act.stroke_m)
        self._servo_streaming = False  # whether the last tick's STREAM went through the servo
        self._x_prev_m = 0.0  # the piston's position at the last tick
        logger.info(
            "servo actuator: b1 %.1f 1/s, b2 %.4g 1/s^2, transport delay %.2f ms "
            "(spread %g of nominal, seed %d)%s",
            servo.b1_per_s,
            servo.b2_per_s2,
            servo.transport_delay_s * 1e3,
            act.servo.spread,
            act.servo.seed,
            ", the waveforms through it" if act.servo.waveforms else "",
        )
        if act.autostart != "STOP":
            self.actuator.command(
                act.autostart, act.autostart_amplitude_m, act.autostart_frequency_hz
            )
        self._params = BoucWenParams.preset(PLANT_PRESET)  # at ambient temperature
        # a twin (plant file): its parameters, its force offset and its command per A
        self._offset_n, self._command_per_a = 0.0, 1.0
        if config.plant.file is not None:
            twin = load_plant(config.plant.file)
            self._params, self._offset_n = twin.params, twin.offset_n
            self._command_per_a = config.plant.command_per_a if twin.command_unit == "V" else 1.0
        self._plant = BoucWenDamper(self._params, config.damper.substep_s)
        self._params_degc = config.thermal.ambient_degc  # the plant's parameters are for this
        self._limit_a = config.damper.current_limit_a
        self.temperature_degc = config.thermal.ambient_degc

        self.events: list[tuple[float, str]] = []
        self._ticks = 0
        self._t_prev_s = 0.0
        self._boot = True
        # damper command state
        self._armed = False
        self._last_cmd_s = 0.0
        self._active = False
        self._setpoint_a = 0.0
        self._over_limit = False
        self.max_commanded_current_a = 0.0
        self._tripped = False
        self.unsendable: str | None = None  # why the last frame could not be encoded
        self.watchdog_trips = 0
        self._n_active = 0
        self._n_safe = 0
        # actuator command state
        self._act_seen = False
        self._last_act_s = 0.0
        self._act_timed_out = False
        # actuator setpoint state (STREAM, contract 1.1)
        self._last_setpoint_s = 0.0
        self._setpoint_timed_out = False  # FaultCode 7
        self._stream_ended = False  # ramped to rest: a repeated STREAM does not restart it
        self._setpoint_clamped = False  # FaultCode 3
        self.late_setpoints = 0
        self.late_setpoint_times: list[tuple[float, int]] = []  # (t_s, echo), the first ones
        self.clamped_setpoints = 0
        # bad command frames within the budget window
        self._bad_times: deque[float] = deque()
        self._bad_over = False
        # outputs of the last tick
        self.coil_command_a = 0.0
        self.coil_current_a = 0.0
        self.force_n = 0.0
        self._last_sensor_counter = 0
        # the latest RigSensors frame that left (`sent`): its counter and when
        self._sent_counter: int | None = None
        self._sent_s = -math.inf
        self.late_commands = 0
        self.armed_motion: list[MotionStretch] = []
        self._stretch_open = False

    # ---- received frames ------------------------------------------------------------------

    def _labels(self, role: str) -> dict[int, str]:
        m = self._profile.mapped.get(role)
        return {} if m is None else self._profile.codec.choices(m.message, m.signal)

    def sensor_counter(self, data: bytes) -> int | None:
        """The counter of a sensor frame's payload (this firmware's own, echoed back); in a
        layout without E2E the count it was sent with, None for a payload not sent lately."""
        if self._sensors.e2e:
            return _counter(self._sensors, data)
        return next((n for sent, n in reversed(self._recent_payloads) if sent == data), None)

    def command_of(self, v: dict[str, float]) -> tuple[str, float, int]:
        """(mode, setpoint A, echoed sensor counter) of a valid command's values. A layout
        without a mode signal is ACTIVE at any setpoint above 0 A; one without the echo
        answers the latest sensor frame sent (so no command of it is ever seen late by its
        echo, only by its time)."""
        setpoint = v["CurrentSetpoint"]
        if "command_mode" not in self._profile.mapped:
            mode = "ACTIVE" if setpoint > 0.0 else "SAFE"
        elif self._mode_labels:
            mode = self._mode_labels[int(v["Mode"])]
        else:
            mode = "ACTIVE" if v["Mode"] else "SAFE"
        if "counter_echo" in self._profile.mapped:
            echo = int(v["SensorCounterEcho"])
        else:
            echo = self._sent_counter if self._sent_counter is not None else 0
        return mode, setpoint, echo

    def setpoint_of(self, v: dict[str, float]) -> tuple[float, int]:
        """(position setpoint m, echoed sensor counter) of a valid ActuatorSetpoint's values;
        a layout without its echo answers the latest sensor frame sent, as `command_of`."""
        if "setpoint_counter_echo" in self._profile.mapped:
            echo = int(v["SensorCounterEcho"])
        else:
            echo = self._sent_counter if self._sent_counter is not None else 0
        return v["PositionSetpoint"], echo

    def on_frame(
        self, frame_id: int, data: bytes, t_s: float, is_extended: bool = False, is_fd: bool = False
    ) -> Parsed | None:
        """Check and apply one received frame; None for frames that are not commands."""
        key = frame_key(frame_id, is_extended)
        if key not in (self.damper_command_key, self._actuator_key, self._setpoint_key):
            return None
        parsed = self._parser.parse(frame_id, data, t_s, is_extended, is_fd)
        if not parsed.ok:
            self._bad_times.append(t_s)
            logger.debug("dropped command frame: %s", parsed.reason)
            return parsed
        v = parsed.values
        assert v is not None
        if key == self.damper_command_key:
            self.on_damper_command(*self.command_of(v), t_s)
        elif key == self._setpoint_key:
            self.on_actuator_setpoint(*self.setpoint_of(v), t_s)
        else:
            self.on_actuator_command(
                self._waveform_labels[int(v["Waveform"])], v["Amplitude"], v["Frequency"], t_s
            )
        return parsed

    def sent(self, frame: Frame, t_s: float) -> None:
        """`frame` (from `tick`) left at t_s: a RigSensors frame is the one commands answer."""
        if frame.frame_id == self.sensors_id and frame.is_extended == self._sensors.is_extended:
            self._sent_counter = frame.counter
            self._sent_s = t_s

    def is_late(self, echo: int, t_s: float) -> bool:
        """A command echoing `echo` at t_s answers an older frame than the latest sent, or
        comes after the next frame was due (see the module's notes)."""
        return echo != self._sent_counter or t_s - self._sent_s > self.period_s

    def on_damper_command(self, mode: str, setpoint_a: float, echo: int, t_s: float) -> None:
        """A valid DamperCommand answering the frame with counter `echo`: feeds the watchdog;
        ACTIVE sets the (clamped) setpoint unless it is late."""
        self._armed = True
        self._last_cmd_s = t_s
        self._track_stretch(mode == "ACTIVE", t_s)
        if mode == "ACTIVE":
            self.max_commanded_current_a = max(self.max_commanded_current_a, setpoint_a)
            if self.is_late(echo, t_s):
                # the coil keeps its setpoint for this period (spec/can-protocol.md)
                self.late_commands += 1
                logger.debug("late ACTIVE command echoing %d at t=%.4f s: not applied", echo, t_s)
                return
            over = setpoint_a > self._limit_a
            if over and not self._over_limit:
                self._event(
                    t_s,
                    f"setpoint {setpoint_a:.4f} A over the limit {self._limit_a:.4f} A: clamped",
                )
            self._over_limit = over
            self._setpoint_a = min(setpoint_a, self._limit_a)
            self._active = True
            self._n_active += 1
            self._n_safe = 0
        else:
            self._over_limit = False
            self._setpoint_a = 0.0
            self._active = False
            self._n_safe += 1
            self._n_active = 0
        if self.unsendable is not None and self._n_safe >= RECOVERY_COMMANDS:
            self.unsendable = None
            self._event(t_s, f"send fault cleared after {RECOVERY_COMMANDS} valid SAFE commands")
        if self._tripped and max(self._n_active, self._n_safe) >= RECOVERY_COMMANDS:
            self._tripped = False
            self._event(t_s, f"watchdog cleared after {RECOVERY_COMMANDS} valid {mode} commands")

    def _track_stretch(self, active: bool, t_s: float) -> None:
        if active and not self._stretch_open:
            a, f = self.actuator.motion_in_force()
            self.armed_motion.append(MotionStretch(t_s, math.inf, a, f, a, f))
            self._stretch_open = True
        elif not active and self._stretch_open:
            self.armed_motion[-1] = self.armed_motion[-1]._replace(end_s=t_s)
            self._stretch_open = False

    def on_actuator_setpoint(self, position_m: float, echo: int, t_s: float) -> None:
        """A valid ActuatorSetpoint answering the frame with counter `echo`: in STREAM, unless
        late, feeds the setpoint watchdog and sets where the piston goes (clamped to the
        envelope and the stroke); outside STREAM it moves nothing."""
        act = self.actuator
        if act.waveform != "STREAM":
            return
        if self.is_late(echo, t_s):
            self.late_setpoints += 1
            if len(self.late_setpoint_times) < MAX_LATE_LISTED:
                self.late_setpoint_times.append((t_s, echo))
            logger.debug("late setpoint echoing %d at t=%.4f s: dropped", echo, t_s)
            return
        self._last_setpoint_s = t_s
        if self._setpoint_timed_out:
            self._setpoint_timed_out = False
            self._event(t_s, "actuator setpoint stream back")
        limit_m = min(act.envelope_m, self._cfg.actuator.stroke_m)
        clamped = abs(position_m) > limit_m
        if clamped:
            self.clamped_setpoints += 1
            if not self._setpoint_clamped:
                self._event(
                    t_s,
                    f"setpoint {position_m * 1e3:.3f} mm beyond the envelope"
                    f" +-{limit_m * 1e3:g} mm: clamped",
                )
        self._setpoint_clamped = clamped
        act.stream_to(max(-limit_m, min(limit_m, position_m)))

    def on_actuator_command(
        self, waveform: str, amplitude_m: float, frequency_hz: float, t_s: float
    ) -> None:
        """A valid ActuatorCommand: re-arms the actuator timeout and drives the motion."""
        self._act_seen = True
        self._last_act_s = t_s
        if self._act_timed_out:
            self._act_timed_out = False
            self._event(t_s, "actuator command stream back")
        if self._halted_by_injection():
            return
        if waveform == "STREAM":
            if self._stream_ended:
                return  # a repeat of the STREAM that timed out: the ramp to rest goes on
            if self.actuator.waveform != "STREAM":
                self._last_setpoint_s = t_s  # the setpoint watchdog starts with the stream
                self._setpoint_clamped = False
        else:
            self._stream_ended = self._setpoint_timed_out = False
        if amplitude_m > self._cfg.actuator.stroke_m and waveform in ("SINE", "RANDOM"):
            logger.warning(
                "actuator amplitude %.5f m clamped to the stroke %.5f m",
                amplitude_m,
                self._cfg.actuator.stroke_m,
            )
        if waveform != self.actuator.waveform:
            logger.info(
                "actuator %s amplitude %.5f m frequency %.3f Hz",
                waveform,
                amplitude_m,
                frequency_hz,
            )
        self.actuator.command(waveform, amplitude_m, frequency_hz)

    def _watch_motion(self) -> None:
        if self._stretch_open:
            s = self.armed_motion[-1]
            a, f = self.actuator.motion()
            if a > s.amplitude_max_m or f > s.frequency_max_hz:
                self.armed_motion[-1] = s._replace(
                    amplitude_max_m=max(a, s.amplitude_max_m),
                    frequency_max_hz=max(f, s.frequency_max_hz),
                )

    # ---- derived state ----------------------------------------------------------------------

    def _cannot_send(self, t_s: float, exc: EncodeError) -> None:
        """A frame the profile cannot encode: not sent, and the firmware faults (coil off)."""
        if self.unsendable is None:
            self._event(t_s, f"cannot send {exc}: FAULT, coil to 0 A", logging.WARNING)
        self.unsendable = str(exc)
        self._n_active = self._n_safe = 0

    def _halted_by_injection(self) -> bool:
        return "estop" in self.active_faults or "stroke_limit" in self.active_faults

    @property
    def state(self) -> str:
        """RigStatus State label."""
        if self._boot:
            return "BOOT"
        if self._tripped or self.unsendable is not None or self._halted_by_injection():
            return "FAULT"
        return "RUNNING" if self._active else "IDLE"

    @property
    def fault_code(self) -> str:
        """RigStatus FaultCode label: the most important active condition."""
        active = self.active_faults
        if "estop" in active:
            return "E_STOP"
        if "stroke_limit" in active:
            return "STROKE_LIMIT"
        if self._tripped:
            return "COMMAND_TIMEOUT"
        if "sensor_fault" in active or self.unsendable is not None:
            return "SENSOR_FAULT"
        if self._act_timed_out:
            return "COMMAND_TIMEOUT"
        if self._setpoint_timed_out:
            return "ACTUATOR_SETPOINT_TIMEOUT"
        if self._setpoint_clamped and self.actuator.waveform == "STREAM":
            return "STROKE_LIMIT"
        if self._bad_over:
            return "BAD_COMMAND_FRAMES"
        if self._over_limit and self._active:
            return "SETPOINT_OVER_LIMIT"
        return "NONE"

    def command_counts(self) -> dict[str, int]:
        """Received command frames: valid, bad CRC, repeated counter, other rejections."""
        out = {
            "damper_valid": 0,
            "actuator_valid": 0,
            "setpoint_valid": 0,
            "bad_crc": 0,
            "repeated_counter": 0,
            "other_rejected": 0,
        }
        p = self._profile
        for name, key in (
            (p.command_message, "damper_valid"),
            (p.actuator_message, "actuator_valid"),
            (p.setpoint_message, "setpoint_valid"),
        ):
            if name is None:
                continue
            st = self._parser.stats[name]
            out[key] = st.frames_ok
            out["bad_crc"] += st.bad_crc
            out["repeated_counter"] += st.repeated_counter
            out["other_rejected"] += st.wrong_length + st.decode_errors
        return out

    def _event(self, t_s: float, text: str, level: int = logging.INFO) -> None:
        self.events.append((t_s, text))
        logger.log(level, "t=%.3f s: %s", t_s, text)

    # ---- one period -------------------------------------------------------------------------

    def _update_injections(self, t_s: float) -> None:
        active = set()
        half = 0.5 * self.period_s  # windows hold round(duration / period) ticks, float-safe
        for i, spec in enumerate(self._faults):
            end_s = spec.start_s + max(spec.duration_s, self.period_s)
            on = spec.start_s - half <= t_s < end_s - half
            if on != self._fault_on[i]:
                self._fault_on[i] = on
                self._event(t_s, f"fault injection {spec.kind} {'starts' if on else 'ends'}")
            if on:
                active.add(spec.kind)
        self.active_faults = frozenset(active)
        if self._halted_by_injection() and self.actuator.waveform != "STOP":
            self.actuator.command("STOP", 0.0, 0.0)

    def _check_timeouts(self, t_s: float) -> None:
        if self._armed and t_s - self._last_cmd_s > WATCHDOG_TIMEOUT_S:
            if not self._tripped:
                self._tripped = True
                self.watchdog_trips += 1
                # after SAFE commands the coil is at 0 A already: the host has stopped, as
                # at the end of every run; after ACTIVE ones the host went silent mid-control
                after = "ACTIVE" if self._active else "SAFE"
                self._event(
                    t_s,
                    f"watchdog: no valid DamperCommand for "
                    f"{(t_s - self._last_cmd_s) * 1e3:.1f} ms after {after} commands, coil to 0 A"
                    + ("" if self._active else " (the daemon stopped or stalled)"),
                    logging.WARNING if self._active else logging.INFO,
                )
            self._n_active = self._n_safe = 0
        if (
            self._act_seen
            and not self._act_timed_out
            and self.actuator.moving
            and t_s - self._last_act_s > ACTUATOR_TIMEOUT_S
        ):
            self._act_timed_out = True
            self.actuator.command("STOP", 0.0, 0.0)
            self._event(t_s, "no ActuatorCommand for 500 ms while moving: ramping to rest")
        self._watch_setpoints(t_s)
        window = self._cfg.commands.bad_frame_window_s
        bad = self._bad_times
        while bad and t_s - bad[0] > window:
            bad.popleft()
        over = len(bad) > self._cfg.commands.bad_frame_budget
        if over != self._bad_over:
            self._bad_over = over
            self._event(
                t_s,
                f"bad command frames {'over' if over else 'back within'} budget "
                f"({len(bad)} in {window:g} s)",
            )

    def _watch_setpoints(self, t_s: float) -> None:
        """The setpoint watchdog of STREAM: HOLD after 20 ms, the ramp to rest after 500 ms."""
        act = self.actuator
        if act.waveform != "STREAM":
            return
        quiet_s = t_s - self._last_setpoint_s
        if not self._setpoint_timed_out and quiet_s > WATCHDOG_TIMEOUT_S:
            self._setpoint_timed_out = True
            act.stream_to(act.x_m)
            self._event(
                t_s,
                f"no valid ActuatorSetpoint for {quiet_s * 1e3:.1f} ms: HOLD where it is",
                logging.WARNING,
            )
        if self._setpoint_timed_out and quiet_s > ACTUATOR_TIMEOUT_S:
            self._stream_ended = True
            act.command("STOP", 0.0, 0.0)
            self._event(t_s, "no valid ActuatorSetpoint for 500 ms: ramping to rest")

    def tick(self, t_s: float) -> list[Frame]:
        """Advance the rig to t_s (one RigSensors period after the last tick) and return the
        frames due: RigSensors, and RigStatus every status period (both subject to faults)."""
        dt_s = t_s - self._t_prev_s if self._ticks else 0.0
        self._t_prev_s = t_s
        self._update_injections(t_s)
        self._check_timeouts(t_s)
        x, xd = (
            self.actuator.advance(dt_s) if dt_s > 0.0 else (self.actuator.x_m, self.actuator.xd_m_s)
        )
        # the servo-hydraulic actuator follows a STREAM's setpoints always (contract 1.1: the
        # daemon's computed stroke), the motion generator's waveforms where configured
        streaming = self.actuator.waveform == "STREAM"
        if streaming and not self._servo_streaming and not self._cfg.actuator.servo.waveforms:
            self.servo.reset(self._x_prev_m)  # from where the piston was
        self._servo_streaming = streaming
        if streaming or self._cfg.actuator.servo.waveforms:
            x, xd = self.servo.step(x, xd, dt_s)
        self._x_prev_m = x
        self._watch_motion()
        on = self.active_faults
        halted = self._tripped or self.unsendable is not None or self._halted_by_injection()
        self.coil_command_a = self._setpoint_a if self._active and not halted else 0.0
        if dt_s > 0.0:
            force = self._plant.step(x, xd, self.coil_command_a * self._command_per_a, dt_s)
        else:
            force = self._plant.reset(x, xd, 0.0)
        force += self._offset_n
        current_a = self._plant.state[2] / self._command_per_a
        self.force_n = force
        th = self._cfg.thermal
        # the damper dissipates the coil's power and the work the actuator does on it
        power_w = th.coil_resistance_ohm * current_a * current_a + force * xd
        rise = self.temperature_degc - th.ambient_degc
        self.temperature_degc += (
            dt_s * (power_w - rise / th.thermal_resistance_k_per_w) / th.heat_capacity_j_per_k
        )
        if th.heating and abs(self.temperature_degc - self._params_degc) >= HEATING_STEP_K:
            # the force parameters follow the temperature in steps too small to show
            self._params_degc = self.temperature_degc
            self._plant.set_params(
                params_at_temperature(
                    self._params,
                    self.temperature_degc - th.ambient_degc,
                    th.viscous_per_k,
                    th.yield_per_k,
                    th.stiffness_per_k,
                )
            )

        sn = self._cfg.sensors
        gauss = self._gauss
        displacement = x + gauss(0.0, sn.displacement_noise_m)
        force_meas = force + gauss(0.0, sn.force_noise_n)
        if "sensor_spike" in on:
            displacement += sn.spike_displacement_m
            force_meas += sn.spike_force_n
        self.coil_current_a = max(0.0, current_a + gauss(0.0, sn.current_noise_a))

        frames: list[Frame] = []
        if "silent" not in on:
            try:
                if "drop_frames" not in on:
                    frames.append(self._sensor_frame(displacement, force_meas, on))
                if self._status_every and self._ticks % self._status_every == 0:
                    frames.append(self._status_frame())
            except EncodeError as exc:
                self._cannot_send(t_s, exc)
        self._ticks += 1
        self._boot = False
        return frames

    def _sensor_frame(self, displacement_m: float, force_n: float, on: frozenset[str]) -> Frame:
        values = self._status_values() if self._status_in_sensors else {}
        values |= {
            "ActuatorEnabled": int(not self.actuator.at_rest and not self._halted_by_injection()),
            "LimitTripped": int("stroke_limit" in on),
            "EStop": int("estop" in on),
            "SensorFault": int("sensor_fault" in on or self.unsendable is not None),
            "Displacement": displacement_m,  # quantised to the DBC's scale by the packer
            "Force": force_n,
        }
        frozen = "freeze_counter" in on
        lay = self._sensors
        data = self._packer.encode(
            lay.name, values, counter=self._last_sensor_counter if frozen else None
        )
        corrupt = "corrupt_crc" in on
        if corrupt:
            data = bytes((data[0] ^ 0xFF,)) + data[1:]
        if lay.e2e:
            counter = _counter(lay, data)
        else:
            counter = self._sent_sensor_frames & 0xF
            self._recent_payloads.append((data, counter))
        self._sent_sensor_frames += 1
        self._last_sensor_counter = counter
        return Frame(lay.frame_id, data, counter, not (frozen or corrupt), *self._format(lay))

    @staticmethod
    def _format(lay: MessageLayout) -> tuple[bool, bool]:
        return lay.is_extended, lay.is_fd

    def _status_values(self) -> dict[str, float | str]:
        fault = self.fault_code
        if not self._fault_labels:  # a fault flag, not the contract's code
            fault = 0 if fault == "NONE" else 1
        return {
            "State": self.state,
            "CoilCurrent": min(self.coil_current_a, self._coil_current_max_a),
            "DamperTemperature": self.temperature_degc,
            "FaultCode": fault,
            "CommandTimeouts": self.watchdog_trips % 256,
        }

    def _status_frame(self) -> Frame:
        lay = self._status
        data = self._packer.encode(lay.name, self._status_values())
        return Frame(lay.frame_id, data, _counter(lay, data), False, *self._format(lay))
