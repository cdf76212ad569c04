"""STREAM (contract 1.1) in the simulated firmware, one test per rule of spec/can-protocol.md,
on the pure state machine: the piston follows the latest valid ActuatorSetpoint, clamped to
the envelope and the stroke (FaultCode 3); no valid setpoint for 20 ms holds it where it is,
500 ms ramps it to rest (FaultCode 7); a late setpoint is dropped and counted."""

from __future__ import annotations

import pytest

from firmware_sim.firmware import ACTUATOR_TIMEOUT_S, WATCHDOG_TIMEOUT_S
from mrrig.rigio.canbus import Parsed
from tests.test_firmware import ANSWER_DELAY_S, CODEC, QUIET, SENSORS_ID, Rig, T

SETPOINT_ID = CODEC.layout("ActuatorSetpoint").frame_id
STROKE_LIMIT, SETPOINT_TIMEOUT = 3, 7  # FaultCode numbers of the contract
RAMP_TICKS = round(QUIET.actuator.ramp_s / T)


class StreamRig(Rig):
    """The firmware's rig with a daemon that streams setpoints."""

    def setpoint(
        self,
        position_m: float,
        echo: int | None = None,
        velocity_m_s: float = 0.0,
        delay_s: float = ANSWER_DELAY_S,
    ) -> Parsed | None:
        """An ActuatorSetpoint `delay_s` after the last tick, echoing `echo` (None: the latest
        sensor frame's counter)."""
        if echo is None:
            echo = next(f.counter for f in reversed(self.frames) if f.frame_id == SENSORS_ID)
        data = self.daemon.encode(
            "ActuatorSetpoint",
            {
                "SensorCounterEcho": echo,
                "PositionSetpoint": position_m,
                "VelocityFeedforward": velocity_m_s,
            },
        )
        return self.fw.on_frame(SETPOINT_ID, data, self.t_s + delay_s)

    def stream(self, positions_m: list[float]) -> list[float]:
        """One tick per position, each answered with it; the piston's position after each."""
        xs = []
        for x in positions_m:
            self.run(1)
            assert self.setpoint(x).ok
            xs.append(self.fw.actuator.x_m)
        return xs


def _streaming(envelope_m: float = 0.03) -> StreamRig:
    rig = StreamRig()
    rig.run(1)
    rig.actuator("STREAM", envelope_m)
    return rig


def test_stream_follows_the_latest_valid_setpoint():
    rig = _streaming()
    rig.run(5)  # the stream starts where the piston is, until its first setpoint
    assert rig.fw.actuator.x_m == 0.0 and rig.fw.fault_code == "NONE"
    targets = [0.001 * k for k in range(1, 11)]
    applied = []
    for x in targets:
        rig.stream([x])
        rig.run(1)
        applied.append(rig.fw.actuator.stream_setpoint_m)
        assert rig.setpoint(x).ok  # the frame the extra tick sent, answered
    # each tick applies the setpoint that came in the period before it; the servo-hydraulic
    # actuator (firmware_sim/actuator.py) is behind it on the ramp, and there once it holds
    assert applied == pytest.approx(targets, abs=1e-6)
    measured = [p.values["Displacement"] for p in rig.sensors[-2 * len(targets) :]]
    assert all(m < 0.01 for m in measured) and measured[-1] > measured[0]
    rig.stream([0.01] * 100)
    assert rig.sensors[-1].values["Displacement"] == pytest.approx(0.01, abs=1e-6)
    assert rig.sensors[-1].values["ActuatorEnabled"] == 1
    assert rig.fw.fault_code == "NONE" and rig.fw.late_setpoints == 0
    assert rig.fw.command_counts()["setpoint_valid"] == 2 * len(targets) + 100


def test_setpoints_outside_stream_move_nothing():
    rig = StreamRig()
    rig.run(1)
    rig.actuator("HOLD")
    for _ in range(5):
        rig.run(1)
        assert rig.setpoint(0.01).ok
    rig.run(1)
    assert rig.fw.actuator.x_m == 0.0 and rig.fw.late_setpoints == 0


@pytest.mark.parametrize(
    ("envelope_m", "setpoint_m", "limit_m"),
    [(0.01, 0.02, 0.01), (0.01, -0.015, -0.01), (0.04, 0.05, 0.04)],
    ids=["over the envelope", "under the envelope", "beyond the stroke"],
)
def test_a_setpoint_beyond_the_envelope_or_the_stroke_is_clamped_with_fault_code_3(
    envelope_m, setpoint_m, limit_m
):
    assert QUIET.actuator.stroke_m == 0.04
    rig = _streaming(envelope_m)
    rig.stream([0.5 * limit_m, setpoint_m])
    assert rig.fw.actuator.stream_setpoint_m == pytest.approx(limit_m)
    assert rig.fw.fault_code == "STROKE_LIMIT" and rig.fw.clamped_setpoints == 1
    n = len(rig.status)
    while len(rig.status) == n:
        rig.stream([setpoint_m])
    assert rig.status[-1].values["FaultCode"] == STROKE_LIMIT
    rig.stream([0.5 * limit_m])
    assert rig.fw.actuator.stream_setpoint_m == pytest.approx(0.5 * limit_m)
    assert rig.fw.fault_code == "NONE"


def test_no_setpoint_for_20_ms_holds_where_it_is_then_500_ms_ramps_to_rest_fault_code_7():
    rig = _streaming()
    rig.stream([0.002, 0.004, 0.006])
    last_setpoint_s = rig.t_s + ANSWER_DELAY_S
    held, x_at_trip = [], None
    while rig.k * T - last_setpoint_s <= ACTUATOR_TIMEOUT_S:
        x_before = rig.fw.actuator.x_m
        rig.run(1)
        quiet_s = rig.t_s - last_setpoint_s
        want = "NONE" if quiet_s <= WATCHDOG_TIMEOUT_S else "ACTUATOR_SETPOINT_TIMEOUT"
        assert rig.fw.fault_code == want, quiet_s
        if want != "NONE":
            x_at_trip = x_before if x_at_trip is None else x_at_trip
            held.append(rig.fw.actuator.stream_setpoint_m)
    assert set(held) == {x_at_trip}  # HOLD where it was when the watchdog tripped
    assert rig.fw.actuator.x_m == pytest.approx(0.006)  # the last setpoint
    assert rig.status[-1].values["FaultCode"] == SETPOINT_TIMEOUT
    xs = []
    for _ in range(RAMP_TICKS + 1):
        rig.run(1)
        xs.append(rig.fw.actuator.x_m)
    assert xs[0] < 0.006 and xs[-1] == 0.0  # ramped to rest at stroke centre, no jump
    assert max(abs(b - a) for a, b in zip(xs, xs[1:], strict=False)) <= 0.006 / RAMP_TICKS + 1e-12
    assert rig.fw.actuator.at_rest and rig.fw.fault_code == "ACTUATOR_SETPOINT_TIMEOUT"
    assert rig.run_until_status()["FaultCode"] == SETPOINT_TIMEOUT
    # the daemon's STREAM repeated every 100 ms (`keep_actuator`) does not restart it
    assert rig.setpoint(0.01).ok
    rig.run(1)
    assert rig.fw.actuator.x_m == 0.0
    # a command of another waveform ends the fault; STREAM then streams again
    rig.actuator("STOP")
    rig.actuator("STREAM", 0.03)
    assert rig.fw.fault_code == "NONE"
    rig.stream([0.003])
    assert rig.fw.actuator.stream_setpoint_m == pytest.approx(0.003)


def test_a_setpoint_within_500_ms_resumes_the_held_stream():
    rig = _streaming()
    rig.stream([0.005])
    rig.run(round(0.1 / T))
    assert rig.fw.fault_code == "ACTUATOR_SETPOINT_TIMEOUT"
    rig.stream([0.006])
    assert rig.fw.actuator.stream_setpoint_m == pytest.approx(0.006)
    assert rig.fw.fault_code == "NONE"


def test_the_setpoint_watchdog_starts_with_the_stream():
    rig = _streaming()
    rig.run(round(WATCHDOG_TIMEOUT_S / T))
    assert rig.fw.fault_code == "NONE"
    rig.run(1)
    assert rig.fw.fault_code == "ACTUATOR_SETPOINT_TIMEOUT"


def test_a_late_setpoint_is_dropped_and_counted():
    rig = _streaming()
    rig.stream([0.002])
    rig.run(1)
    older = rig.sensors[-2].counter
    first_s = rig.t_s + ANSWER_DELAY_S
    assert rig.setpoint(0.009, echo=older).ok  # valid frame, answering the frame before
    assert rig.fw.actuator.stream_setpoint_m == pytest.approx(0.002)
    assert rig.fw.late_setpoints == 1
    # on time by its echo but after the next frame was due: late too
    rig.run(1)
    latest, second_s = rig.sensors[-1].counter, rig.t_s + 1.5 * T
    assert rig.setpoint(0.009, delay_s=1.5 * T).ok
    assert rig.fw.actuator.stream_setpoint_m == pytest.approx(0.002)
    assert rig.fw.late_setpoints == 2
    # each dropped one listed with its time and echo: a HIL run's measured stalls
    assert rig.fw.late_setpoint_times == [(first_s, older), (second_s, latest)]


def test_late_setpoints_alone_do_not_feed_the_setpoint_watchdog():
    rig = _streaming()
    rig.stream([0.002])
    for _ in range(round(WATCHDOG_TIMEOUT_S / T) + 1):
        rig.run(1)
        assert rig.setpoint(0.009, echo=rig.sensors[-2].counter).ok
    rig.run(1)
    assert rig.fw.fault_code == "ACTUATOR_SETPOINT_TIMEOUT"
    assert rig.fw.late_setpoints == round(WATCHDOG_TIMEOUT_S / T) + 1


def test_stop_ramps_a_stream_to_rest_from_where_it_is():
    rig = _streaming()
    rig.stream([0.004, 0.008])
    rig.run(1)
    x0 = rig.fw.actuator.x_m
    assert x0 > 0.004
    rig.actuator("STOP")
    xs = []
    for _ in range(RAMP_TICKS + 1):
        rig.run(1)
        xs.append(rig.fw.actuator.x_m)
    assert xs[0] == pytest.approx(x0 - x0 / RAMP_TICKS) and xs[-1] == 0.0
    assert rig.fw.actuator.at_rest and rig.fw.fault_code == "NONE"
