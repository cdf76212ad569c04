"""The firmware rules of spec/can-protocol.md, one test each, on the pure state machine.

A `Rig` drives `Firmware` with frames from the daemon's packer and a clock of ideal 2 ms ticks;
what the firmware sends is decoded with the codec's parser, as the daemon would.
"""

from __future__ import annotations

import dataclasses
import math

import pytest

from firmware_sim.config import (
    ActuatorConfig,
    CommandConfig,
    ConfigError,
    FaultSpec,
    SensorConfig,
    SimConfig,
    load_config,
)
from firmware_sim.firmware import (
    ACTUATOR_TIMEOUT_S,
    RECOVERY_COMMANDS,
    WATCHDOG_TIMEOUT_S,
    Firmware,
    Frame,
)
from mrrig.rigio.canbus import Codec, Parsed
from mrrig.rigio.canbus.profile import contract_profile

CODEC = Codec()
SENSORS_ID = CODEC.layout("RigSensors").frame_id
STATUS_ID = CODEC.layout("RigStatus").frame_id
DAMPER_ID = CODEC.layout("DamperCommand").frame_id
ACTUATOR_ID = CODEC.layout("ActuatorCommand").frame_id
T = CODEC.layout("RigSensors").period_s
STATUS_EVERY = round(CODEC.layout("RigStatus").period_s / T)
ANSWER_DELAY_S = 0.0005  # the daemon's answer arrives this long after the sensor frame
QUIET = dataclasses.replace(SimConfig(), sensors=SensorConfig(0.0, 0.0, 0.0, 0.02, 5000.0))
# State and FaultCode numbers of the contract
BOOT, IDLE, RUNNING, FAULT = 0, 1, 2, 3
COMMAND_TIMEOUT, OVER_LIMIT, STROKE_LIMIT, SENSOR_FAULT, E_STOP, BAD_FRAMES = 1, 2, 3, 4, 5, 6


class Rig:
    """Firmware plus a daemon-side packer/parser and an ideal clock."""

    def __init__(self, config: SimConfig = QUIET, faults: tuple[FaultSpec, ...] = ()) -> None:
        self.fw = Firmware(config, contract_profile(), faults)
        self.daemon = CODEC.packer("DAEMON")
        self.parser = CODEC.parser()
        self.k = 0
        self.sensors: list[Parsed] = []
        self.status: list[Parsed] = []
        self.frames: list[Frame] = []
        self.last_actuator: tuple[str, float, float] | None = None
        self.keep_actuator = True  # repeat the last ActuatorCommand every 100 ms, as a daemon

    @property
    def t_s(self) -> float:
        """Time of the last tick."""
        return (self.k - 1) * T

    def tick(self) -> list[Frame]:
        if self.keep_actuator and self.last_actuator and self.k % STATUS_EVERY == 0:
            self.actuator(*self.last_actuator)
        frames = self.fw.tick(self.k * T)
        self.k += 1
        self.frames.extend(frames)
        for f in frames:
            self.fw.sent(f, self.t_s)
            parsed = self.parser.parse(f.frame_id, f.data, self.t_s)
            (self.sensors if f.frame_id == SENSORS_ID else self.status).append(parsed)
        return frames

    def damper(
        self,
        mode: str = "ACTIVE",
        current_a: float = 1.0,
        echo: int | None = None,
        counter: int | None = None,
        corrupt: bool = False,
        delay_s: float = ANSWER_DELAY_S,
    ) -> Parsed | None:
        """A DamperCommand `delay_s` after the last tick, echoing `echo` (None: the latest
        sensor frame's counter)."""
        if echo is None:
            echo = next((f.counter for f in reversed(self.frames) if f.frame_id == SENSORS_ID), 0)
        data = self.daemon.encode(
            "DamperCommand",
            {
                "Mode": mode,
                "CurrentSetpoint": current_a,
                "SensorCounterEcho": echo,
                "ControllerId": 1 if mode == "ACTIVE" else 0,
                "DesiredForce": 0.0,
            },
            counter,
        )
        if corrupt:
            data = bytes((data[0] ^ 0x5A,)) + data[1:]
        return self.fw.on_frame(DAMPER_ID, data, self.t_s + delay_s)

    def actuator(self, waveform: str, amplitude_m: float = 0.0, frequency_hz: float = 0.0):
        self.last_actuator = (waveform, amplitude_m, frequency_hz)
        data = self.daemon.encode(
            "ActuatorCommand",
            {"Waveform": waveform, "Amplitude": amplitude_m, "Frequency": frequency_hz},
        )
        return self.fw.on_frame(ACTUATOR_ID, data, self.t_s + ANSWER_DELAY_S)

    def run(self, n: int, answer: str | None = None, current_a: float = 1.0) -> None:
        """n ticks; with `answer` (a Mode label) one command per sensor frame, echoing it."""
        for _ in range(n):
            frames = self.tick()
            if answer is not None:
                sensor = [f for f in frames if f.frame_id == SENSORS_ID]
                self.damper(answer, current_a, sensor[0].counter if sensor else None)

    def run_until_status(
        self, answer: str | None = None, current_a: float = 1.0
    ) -> dict[str, float]:
        """Tick until the next RigStatus and return its values."""
        n = len(self.status)
        while len(self.status) == n:
            self.run(1, answer, current_a)
        assert self.status[-1].ok
        return self.status[-1].values


def test_rig_sensors_every_period_and_rig_status_every_100_ms_with_valid_e2e():
    rig = Rig(SimConfig())
    rig.run(5 * STATUS_EVERY)
    assert len(rig.sensors) == 5 * STATUS_EVERY
    assert len(rig.status) == 5
    assert all(p.ok for p in rig.sensors + rig.status)
    counters = [p.counter for p in rig.sensors]
    assert all((b - a) % 16 == 1 for a, b in zip(counters, counters[1:], strict=False))


def test_before_the_first_command_state_is_idle_and_the_watchdog_not_armed():
    rig = Rig()
    assert rig.run_until_status()["State"] == BOOT
    rig.run(10 * STATUS_EVERY)
    status = rig.run_until_status()
    assert (status["State"], status["FaultCode"], status["CommandTimeouts"]) == (IDLE, 0, 0)
    assert rig.fw.watchdog_trips == 0


def test_active_command_drives_the_coil_and_state_running():
    rig = Rig()
    rig.run(STATUS_EVERY, answer="ACTIVE", current_a=1.2)
    status = rig.run_until_status(answer="ACTIVE", current_a=1.2)
    assert rig.fw.coil_command_a == pytest.approx(1.2)
    assert status["State"] == RUNNING and status["FaultCode"] == 0
    # measured coil current: the plant's lagged current (eta = 190 1/s), settled after 0.2 s
    assert status["CoilCurrent"] == pytest.approx(1.2, abs=0.01)


def test_safe_command_sets_coil_current_to_0_a():
    rig = Rig()
    rig.run(10, answer="ACTIVE", current_a=1.5)
    rig.run(1, answer="SAFE", current_a=1.5)
    rig.run(1)
    assert rig.fw.coil_command_a == 0.0
    assert rig.fw.state == "IDLE"


def test_watchdog_trips_after_20_ms_without_damper_command_fault_code_1_and_timeouts_plus_1():
    rig = Rig()
    rig.run(10, answer="ACTIVE")
    last_command_s = rig.t_s + ANSWER_DELAY_S
    while (rig.k * T) - last_command_s <= WATCHDOG_TIMEOUT_S:
        rig.run(1)
        assert rig.fw.state == "RUNNING" and rig.fw.coil_command_a == 1.0
    rig.run(1)  # the first tick more than 20 ms after the last command
    assert rig.fw.coil_command_a == 0.0
    assert (rig.fw.state, rig.fw.fault_code, rig.fw.watchdog_trips) == (
        "FAULT",
        "COMMAND_TIMEOUT",
        1,
    )
    status = rig.run_until_status()
    assert (status["State"], status["FaultCode"], status["CommandTimeouts"]) == (FAULT, 1, 1)
    rig.run(3 * STATUS_EVERY)
    assert rig.run_until_status()["CommandTimeouts"] == 1  # one trip, not one per period


def test_watchdog_returns_to_running_after_5_consecutive_valid_active_commands():
    rig = Rig()
    rig.run(10, answer="ACTIVE")
    rig.run(20)
    assert rig.fw.state == "FAULT"
    rig.run(RECOVERY_COMMANDS - 1, answer="ACTIVE")
    rig.run(1)
    assert rig.fw.state == "FAULT" and rig.fw.coil_command_a == 0.0
    rig.damper("ACTIVE", 1.0, counter=None)  # the 5th in a row
    rig.run(1)
    assert rig.fw.state == "RUNNING" and rig.fw.coil_command_a == 1.0
    assert rig.fw.fault_code == "NONE"


def test_watchdog_recovery_count_restarts_after_a_safe_command():
    rig = Rig()
    rig.run(10, answer="ACTIVE")
    rig.run(20)
    rig.run(RECOVERY_COMMANDS - 1, answer="ACTIVE")
    rig.run(1, answer="SAFE")
    rig.run(RECOVERY_COMMANDS - 1, answer="ACTIVE")
    assert rig.fw.state == "FAULT"
    rig.run(1, answer="ACTIVE")
    assert rig.fw.state == "RUNNING"


def test_watchdog_returns_to_idle_after_5_consecutive_valid_safe_commands():
    rig = Rig()
    rig.run(10, answer="ACTIVE")
    rig.run(20)
    rig.run(RECOVERY_COMMANDS - 1, answer="SAFE")
    assert rig.fw.state == "FAULT"
    rig.run(1, answer="SAFE")
    assert rig.fw.state == "IDLE" and rig.fw.fault_code == "NONE"


def test_setpoint_above_the_current_limit_is_clamped_and_reported_fault_code_2():
    rig = Rig()
    limit_a = QUIET.damper.current_limit_a
    rig.run(10, answer="ACTIVE", current_a=limit_a + 0.5)
    assert rig.fw.coil_command_a == limit_a
    status = rig.run_until_status(answer="ACTIVE", current_a=limit_a + 0.5)
    assert (status["State"], status["FaultCode"]) == (RUNNING, OVER_LIMIT)
    assert rig.fw.max_commanded_current_a == pytest.approx(limit_a + 0.5)
    rig.run(5, answer="ACTIVE", current_a=limit_a)
    assert rig.fw.fault_code == "NONE" and rig.fw.coil_command_a == limit_a


def test_late_active_command_answering_an_older_frame_is_not_applied_and_is_counted():
    """Its echo is not the latest RigSensors frame's counter: the command came after the next
    frame left; the coil keeps the previous setpoint for that period."""
    rig = Rig()
    rig.run(10, answer="ACTIVE", current_a=1.0)
    previous = rig.sensors[-1].counter
    rig.tick()
    rig.damper("ACTIVE", 1.5, echo=previous)
    rig.tick()
    assert rig.fw.coil_command_a == 1.0 and rig.fw.late_commands == 1
    assert rig.fw.state == "RUNNING"
    rig.run(1, answer="ACTIVE", current_a=1.5)  # the latest frame's answer is applied
    rig.tick()
    assert rig.fw.coil_command_a == 1.5 and rig.fw.late_commands == 1


def test_late_commands_count_as_valid_for_the_watchdog():
    rig = Rig()
    rig.run(10, answer="ACTIVE", current_a=1.0)
    for _ in range(round(2 * WATCHDOG_TIMEOUT_S / T)):  # 40 ms of answers one frame behind
        previous = rig.sensors[-1].counter
        rig.tick()
        rig.damper("ACTIVE", 1.5, echo=previous)
    rig.tick()
    assert rig.fw.watchdog_trips == 0 and rig.fw.state == "RUNNING"
    assert rig.fw.coil_command_a == 1.0
    assert rig.fw.late_commands == round(2 * WATCHDOG_TIMEOUT_S / T)


def test_late_commands_neither_add_to_nor_break_a_watchdog_recovery():
    rig = Rig()
    rig.run(10, answer="ACTIVE")
    rig.run(20)
    assert rig.fw.state == "FAULT"
    rig.run(RECOVERY_COMMANDS - 1, answer="ACTIVE")
    previous = rig.sensors[-1].counter
    rig.tick()
    rig.damper("ACTIVE", 1.0, echo=previous)  # late: not the 5th
    rig.tick()
    assert rig.fw.state == "FAULT" and rig.fw.coil_command_a == 0.0
    rig.damper("ACTIVE", 1.0)  # the 5th valid ACTIVE command in time
    rig.tick()
    assert rig.fw.state == "RUNNING" and rig.fw.coil_command_a == 1.0


def test_a_command_after_the_next_frame_was_due_is_late_though_that_frame_did_not_leave():
    """The simulator's own choice: its process held up past the next deadline, a command
    echoing the latest frame sent comes more than a period after it left: a firmware on time
    had sent the next frame, so it is late."""
    rig = Rig()
    rig.run(10, answer="ACTIVE", current_a=1.0)
    rig.tick()
    rig.damper("ACTIVE", 1.5, delay_s=T + 0.0001)
    rig.tick()
    assert rig.fw.coil_command_a == 1.0 and rig.fw.late_commands == 1
    rig.damper("ACTIVE", 1.5, delay_s=T - 0.0001)  # within the period: applied
    rig.tick()
    assert rig.fw.coil_command_a == 1.5 and rig.fw.late_commands == 1


def test_a_late_safe_command_is_applied():
    """Only ACTIVE commands can be late: SAFE (0 A) is always safe to apply."""
    rig = Rig()
    rig.run(10, answer="ACTIVE", current_a=1.0)
    previous = rig.sensors[-1].counter
    rig.tick()
    rig.damper("SAFE", 0.0, echo=previous)
    rig.tick()
    assert rig.fw.coil_command_a == 0.0 and rig.fw.state == "IDLE"
    assert rig.fw.late_commands == 0


def test_armed_motion_lists_each_active_stretch_with_the_motion_at_its_start_and_its_peak():
    rig = Rig()
    rig.actuator("SINE", 0.015, 2.0)
    rig.run(50, answer="SAFE")
    rig.run(10, answer="ACTIVE")
    for k in range(1, 7):  # six steps of 4 mm while ACTIVE: 15 mm to 39 mm
        rig.actuator("SINE", 0.015 + 0.004 * k, 2.0)
        rig.run(2, answer="ACTIVE")
    ramp_ticks = round(QUIET.actuator.ramp_s / T) + 1
    rig.run(ramp_ticks, answer="ACTIVE")
    rig.actuator("SINE", 0.039, 3.0)
    rig.run(ramp_ticks, answer="ACTIVE")
    rig.run(1, answer="SAFE")
    rig.actuator("SINE", 0.040, 5.0)  # between stretches
    rig.run(5, answer="SAFE")
    rig.run(5, answer="ACTIVE")
    first, second = rig.fw.armed_motion
    assert first.amplitude_at_start_m == pytest.approx(0.015)
    assert first.amplitude_max_m == pytest.approx(0.039)
    assert (first.frequency_at_start_hz, first.frequency_max_hz) == pytest.approx((2.0, 3.0))
    assert first.end_s < second.start_s and math.isinf(second.end_s)
    assert second.amplitude_at_start_m == pytest.approx(0.040)  # the one heading for
    assert second.frequency_at_start_hz == pytest.approx(5.0)
    assert rig.fw.actuator.motion()[0] < 0.040  # still on its way there


def test_armed_motion_at_start_holds_a_frequency_ramp_still_under_way_while_stopping():
    """Armed while the actuator stops (amplitude ramping to 0) and its frequency still ramps
    up from an earlier command: that frequency's target is in force at arming (the ten-minute
    bench fuzz counted such a stretch, 1.44 Hz at its start rising to 2.0 Hz, as motion
    beyond the limits)."""
    rig = Rig()
    rig.actuator("SINE", 0.015, 2.0)
    ramp_ticks = round(QUIET.actuator.ramp_s / T) + 1
    rig.run(ramp_ticks, answer="SAFE")
    rig.actuator("HOLD", 0.015, 2.0)  # the frequency ramps to 0
    rig.run(ramp_ticks, answer="SAFE")
    rig.actuator("SINE", 0.015, 2.0)  # and back up to 2 Hz
    rig.run(ramp_ticks // 2, answer="SAFE")
    rig.actuator("STOP", 0.0, 0.0)
    rig.run(ramp_ticks // 4, answer="SAFE")
    amplitude_m, frequency_hz = rig.fw.actuator.motion()
    assert amplitude_m > 0.0 and frequency_hz < 1.9  # mid-ramp when armed
    rig.run(ramp_ticks, answer="ACTIVE")
    (stretch,) = rig.fw.armed_motion
    assert stretch.frequency_max_hz == pytest.approx(2.0, abs=0.05)  # the ramp went on
    assert stretch.frequency_at_start_hz == pytest.approx(2.0)


def test_armed_motion_goes_on_through_a_watchdog_trip():
    """A stretch is the daemon's ARMED: a watchdog trip sends no SAFE command."""
    rig = Rig()
    rig.run(10, answer="ACTIVE")
    rig.run(20)
    rig.run(RECOVERY_COMMANDS + 1, answer="ACTIVE")
    assert rig.fw.watchdog_trips == 1 and len(rig.fw.armed_motion) == 1


def test_bad_crc_and_repeated_counter_command_frames_are_dropped_and_counted():
    rig = Rig()
    rig.run(1)
    assert rig.damper("ACTIVE", 0.5, counter=3).ok
    rig.run(1)
    assert rig.fw.coil_command_a == 0.5
    bad_crc = rig.damper("ACTIVE", 1.5, counter=4, corrupt=True)
    repeated = rig.damper("ACTIVE", 1.5, counter=3)
    rig.run(1)
    assert not bad_crc.ok and not repeated.ok
    assert rig.fw.coil_command_a == 0.5
    counts = rig.fw.command_counts()
    assert (counts["damper_valid"], counts["bad_crc"], counts["repeated_counter"]) == (1, 1, 1)
    assert rig.fw.fault_code == "NONE"  # within the budget


def test_bad_command_frames_beyond_the_budget_report_fault_code_6():
    config = dataclasses.replace(
        QUIET, commands=CommandConfig(bad_frame_budget=3, bad_frame_window_s=0.5)
    )
    rig = Rig(config)
    rig.run(1)
    for _ in range(3):
        rig.damper(corrupt=True)
    rig.run(1)
    assert rig.fw.fault_code == "NONE"
    rig.damper(corrupt=True)
    rig.run(1)
    assert rig.fw.fault_code == "BAD_COMMAND_FRAMES"
    assert rig.run_until_status()["FaultCode"] == BAD_FRAMES
    rig.run(round(0.5 / T) + 1)
    assert rig.fw.fault_code == "NONE"  # the window has moved past them


def test_stop_ramps_the_actuator_to_rest_at_stroke_centre():
    rig = Rig()
    rig.actuator("SINE", 0.015, 2.0)
    rig.run(round(1.0 / T))
    assert max(abs(p.values["Displacement"]) for p in rig.sensors[-250:]) > 0.014
    rig.actuator("STOP")
    xs = []
    for _ in range(round(QUIET.actuator.ramp_s / T) + 1):
        rig.run(1)
        xs.append(rig.fw.actuator.x_m)
    assert xs[-1] == 0.0 and rig.fw.actuator.xd_m_s == 0.0
    assert max(abs(b - a) for a, b in zip(xs, xs[1:], strict=False)) < 0.2 * T  # no jump
    rig.run(1)
    assert rig.sensors[-1].values["ActuatorEnabled"] == 0


def test_sine_changes_of_amplitude_and_frequency_are_phase_continuous_and_ramped():
    rig = Rig()
    rig.actuator("SINE", 0.01, 2.0)
    rig.run(round(1.0 / T))
    rig.actuator("SINE", 0.02, 5.0)
    xs, vs = [], []
    for _ in range(round(1.0 / T)):
        rig.run(1)
        xs.append(rig.fw.actuator.x_m)
        vs.append(rig.fw.actuator.xd_m_s)
    v_max = 0.02 * 2 * math.pi * 5.0 + 0.02 / QUIET.actuator.ramp_s
    steps = [abs(b - a) for a, b in zip(xs, xs[1:], strict=False)]
    assert max(steps) <= v_max * T * 1.01
    # velocity is the derivative of the displacement (trapezoid check over each step)
    assert all(
        abs(xs[i + 1] - xs[i] - 0.5 * (vs[i] + vs[i + 1]) * T) < 2e-5 for i in range(len(xs) - 1)
    )
    assert max(abs(x) for x in xs[-250:]) == pytest.approx(0.02, rel=0.01)


def test_hold_brings_the_actuator_to_a_standstill_where_it_is():
    rig = Rig()
    rig.actuator("SINE", 0.015, 1.0)
    rig.run(round(1.1 / T))
    rig.actuator("HOLD")
    rig.run(round(QUIET.actuator.ramp_s / T) + 1)
    x_held = rig.fw.actuator.x_m
    rig.run(100)
    assert rig.fw.actuator.x_m == x_held and rig.fw.actuator.xd_m_s == 0.0
    assert x_held != 0.0


def test_random_is_seeded_band_limited_noise_within_its_peak():
    runs = []
    for _ in range(2):
        rig = Rig()
        rig.actuator("RANDOM", 0.01, 10.0)
        rig.run(round(2.0 / T))
        runs.append([p.values["Displacement"] for p in rig.sensors])
    assert runs[0] == runs[1]
    assert max(abs(x) for x in runs[0]) <= 0.01 + 1e-6
    assert max(abs(x) for x in runs[0]) > 0.003


def test_actuator_ramps_to_rest_after_500_ms_without_actuator_command_fault_code_1():
    rig = Rig()
    rig.keep_actuator = False
    rig.actuator("SINE", 0.01, 2.0)
    last_command_s = rig.t_s + ANSWER_DELAY_S
    while rig.k * T - last_command_s <= ACTUATOR_TIMEOUT_S:
        rig.run(1)
    assert rig.fw.fault_code == "NONE"
    rig.run(1)
    assert rig.fw.fault_code == "COMMAND_TIMEOUT" and rig.fw.state == "IDLE"
    assert rig.run_until_status()["FaultCode"] == COMMAND_TIMEOUT
    rig.run(round(QUIET.actuator.ramp_s / T) + 1)
    assert rig.fw.actuator.at_rest and rig.fw.actuator.x_m == 0.0
    rig.actuator("SINE", 0.01, 2.0)
    rig.run(1)
    assert rig.fw.fault_code == "NONE"


def test_autostart_moves_without_command_and_without_actuator_timeout():
    config = dataclasses.replace(QUIET, actuator=ActuatorConfig(autostart="SINE"))
    rig = Rig(config)
    rig.run(round(2.0 / T))
    assert rig.fw.fault_code == "NONE"
    assert max(abs(p.values["Displacement"]) for p in rig.sensors[-500:]) > 0.009


# ---- fault injections ------------------------------------------------------------------------

START_S, DURATION_S = 0.2, 0.1


def in_window(i: int) -> bool:
    return round(START_S / T) <= i < round((START_S + DURATION_S) / T)


def run_fault(kind: str, answer: str | None = None) -> Rig:
    rig = Rig(faults=(FaultSpec(kind, START_S, DURATION_S),))  # type: ignore[arg-type]
    rig.run(round(0.5 / T), answer=answer)
    return rig


def test_fault_drop_frames_skips_rig_sensors_only():
    rig = run_fault("drop_frames")
    assert len(rig.sensors) == round(0.5 / T) - round(DURATION_S / T)
    assert len(rig.status) == round(0.5 / T) // STATUS_EVERY


def test_fault_corrupt_crc_sends_rig_sensors_with_a_wrong_crc():
    rig = run_fault("corrupt_crc")
    bad = [i for i, p in enumerate(rig.sensors) if not p.ok]
    assert bad == [i for i in range(len(rig.sensors)) if in_window(i)]
    assert all("CRC" in rig.sensors[i].reason for i in bad)
    assert rig.parser.stats["RigSensors"].bad_crc == round(DURATION_S / T)


def test_fault_freeze_counter_repeats_the_rig_sensors_counter():
    rig = run_fault("freeze_counter")
    assert rig.parser.stats["RigSensors"].repeated_counter == round(DURATION_S / T)
    counters = [f.counter for f in rig.frames if f.frame_id == SENSORS_ID]
    first = round(START_S / T)
    assert set(counters[first - 1 : first + round(DURATION_S / T)]) == {counters[first - 1]}
    assert counters[first + round(DURATION_S / T)] == (counters[first - 1] + 1) % 16


def test_fault_sensor_spike_adds_a_displacement_and_force_spike():
    clean, spiked = Rig(), run_fault("sensor_spike")
    clean.run(round(0.5 / T))
    for i, (a, b) in enumerate(zip(clean.sensors, spiked.sensors, strict=True)):
        dx = b.values["Displacement"] - a.values["Displacement"]
        df = b.values["Force"] - a.values["Force"]
        if in_window(i):
            assert dx == pytest.approx(0.02, abs=2e-6) and df == pytest.approx(5000.0, abs=0.02)
        else:
            assert dx == 0.0 and df == 0.0


def test_fault_sensor_spike_of_duration_0_is_one_frame():
    rig = Rig(faults=(FaultSpec("sensor_spike", 0.1),))
    rig.run(100)
    assert sum(p.values["Displacement"] > 0.01 for p in rig.sensors) == 1


def test_fault_estop_sets_flag_zero_current_and_fault_5():
    rig = Rig(faults=(FaultSpec("estop", START_S, DURATION_S),))
    coil_a = []
    for _ in range(round(0.5 / T)):
        rig.run(1, answer="ACTIVE")
        coil_a.append(rig.fw.coil_command_a)
    flagged = [i for i, p in enumerate(rig.sensors) if p.values["EStop"]]
    window = [i for i in range(len(rig.sensors)) if in_window(i)]
    assert flagged == window
    assert [i for i, a in enumerate(coil_a) if a == 0.0] == [0, *window]  # 0: no command yet
    assert rig.sensors[window[-1]].values["ActuatorEnabled"] == 0
    statuses = {round(p.timestamp_s, 3): p.values for p in rig.status}
    assert (statuses[0.2]["State"], statuses[0.2]["FaultCode"]) == (FAULT, E_STOP)
    assert statuses[0.4]["State"] == RUNNING and statuses[0.4]["FaultCode"] == 0
    assert rig.fw.coil_current_a == pytest.approx(1.0, abs=0.01)


def test_fault_stroke_limit_sets_limit_tripped_and_fault_3():
    rig = run_fault("stroke_limit", answer="ACTIVE")
    flagged = [i for i, p in enumerate(rig.sensors) if p.values["LimitTripped"]]
    assert flagged == [i for i in range(len(rig.sensors)) if in_window(i)]
    status = {round(p.timestamp_s, 3): p.values for p in rig.status}[0.2]
    assert (status["State"], status["FaultCode"]) == (FAULT, STROKE_LIMIT)


def test_fault_sensor_fault_sets_the_flag_and_fault_code_4():
    rig = run_fault("sensor_fault", answer="ACTIVE")
    flagged = [i for i, p in enumerate(rig.sensors) if p.values["SensorFault"]]
    assert flagged == [i for i in range(len(rig.sensors)) if in_window(i)]
    status = {round(p.timestamp_s, 3): p.values for p in rig.status}[0.2]
    assert (status["State"], status["FaultCode"]) == (RUNNING, SENSOR_FAULT)


def test_fault_silent_sends_nothing_at_all():
    rig = run_fault("silent")
    assert len(rig.sensors) == round(0.5 / T) - round(DURATION_S / T)
    assert [round(p.timestamp_s, 3) for p in rig.status] == [0.0, 0.1, 0.3, 0.4]


def test_fault_injections_are_logged_when_they_start_and_end(caplog):
    caplog.set_level("INFO", logger="firmware_sim.firmware")
    rig = run_fault("estop")
    events = [e for _, e in rig.fw.events]
    assert events == ["fault injection estop starts", "fault injection estop ends"]
    assert sum("fault injection estop" in r.getMessage() for r in caplog.records) == 2


# ---- config ------------------------------------------------------------------------------------


def test_fault_spec_from_command_line_kind_at_start_colon_duration():
    assert FaultSpec.from_cli("estop@5:2") == FaultSpec("estop", 5.0, 2.0)
    assert FaultSpec.from_cli("sensor_spike@1.5") == FaultSpec("sensor_spike", 1.5, 0.0)
    for bad in ("estop", "melt@1", "estop@x", "estop@-1"):
        with pytest.raises(ValueError):
            FaultSpec.from_cli(bad)


def test_shipped_config_loads_and_a_bad_field_is_named(tmp_path):
    config = load_config("configs/sim.toml")
    assert config.damper.current_limit_a == 2.0
    bad = tmp_path / "sim.toml"
    bad.write_text("[damper]\ncurrent_limit_a = 9.0\n")
    with pytest.raises(ConfigError, match=r"sim.toml: damper.current_limit_a"):
        load_config(bad)
    bad.write_text('[[faults]]\nkind = "melt"\nstart_s = 1.0\n')
    with pytest.raises(ConfigError, match=r"faults\[0\].kind"):
        load_config(bad)
    bad.write_text("[thermal]\ncoil_resistance_ohm = nan\n")
    with pytest.raises(ConfigError, match=r"thermal.coil_resistance_ohm: expected a finite number"):
        load_config(bad)


# ------------------------------------------------------------------------------- heating
def _heating(heating: bool, **thermal) -> SimConfig:
    from firmware_sim.config import ThermalConfig

    th = ThermalConfig(heating=heating, heat_capacity_j_per_k=100.0, **thermal)  # warms fast
    return dataclasses.replace(QUIET, thermal=th)


def _forces_while_moving(config: SimConfig, seconds: float) -> tuple[list[float], list[float]]:
    rig = Rig(config)
    rig.actuator("SINE", 0.02, 5.0)
    rig.run(round(seconds / T), answer="ACTIVE", current_a=1.5)
    force = [p.values["Force"] for p in rig.sensors]
    temps = [p.values["DamperTemperature"] for p in rig.status]
    return force, temps


def test_the_damper_warms_from_its_dissipated_power_and_rig_status_reports_it():
    force, temps = _forces_while_moving(_heating(False), 6.0)
    assert temps[0] == pytest.approx(25.0, abs=0.01)
    assert temps[-1] > temps[0] + 5.0  # the actuator's work and the coil's power
    assert all(b >= a - 0.01 for a, b in zip(temps, temps[1:], strict=False))


def test_with_heating_on_the_force_falls_as_the_damper_warms_and_off_it_does_not():
    cold, temps = _forces_while_moving(_heating(False), 6.0)
    warm, temps_on = _forces_while_moving(_heating(True), 6.0)
    assert temps_on[-1] > 40.0
    n = round(0.2 / T)  # the last cycle of the same motion and current
    ratio = max(map(abs, warm[-n:])) / max(map(abs, cold[-n:]))
    rise = temps_on[-2] - 25.0  # RigStatus every 100 ms: the one inside that cycle
    # -0.003 per K for every force parameter: the force scaled by 1 - 0.003 * rise
    assert ratio == pytest.approx(1.0 - 0.003 * rise, abs=0.02)
    assert warm[: n // 5] == cold[: n // 5]  # the same damper while still cold


def test_heating_coefficients_out_of_range_are_refused(tmp_path):
    path = tmp_path / "sim.toml"
    path.write_text("[thermal]\nheating = true\nviscous_per_k = -0.5\n")
    with pytest.raises(ConfigError, match="thermal.viscous_per_k"):
        load_config(path)
