"""The daemon's safety rules (spec/system.md, Safety), one test per fault.

Each test drives the real daemon loop through a scripted rig on a virtual bus: the daemon must
go to FAULT within one frame, send SAFE 0 A next, and record the fault as an event with a reason.
"""

from __future__ import annotations

import math
import time

import can
import numpy as np
import pytest

from mrrig.loop import reference as ref
from mrrig.loop.controllers import Controller
from mrrig.loop.safety import FOREIGN_HOLD_S, Fault, Limits, Supervisor
from mrrig.loop.samples import RigState
from mrrig.rigio.canbus.codec import Codec
from tests.rig_harness import ScriptedRig

SAFE = 0
ACTIVE = 1


def assert_safe(cmd: dict) -> None:
    assert cmd["Mode"] == SAFE
    assert cmd["CurrentSetpoint"] == 0.0
    assert cmd["ControllerId"] == 0


def assert_fault(rig: ScriptedRig, fault: Fault) -> dict:
    assert rig.daemon.supervisor.state is RigState.FAULT
    # the loop thread records the event just after it sets the state: give it that moment
    deadline = time.monotonic() + 1.0
    events = [e for e in rig.daemon.events if e["kind"] == "fault"]
    while not events and time.monotonic() < deadline:
        time.sleep(0.001)
        events = [e for e in rig.daemon.events if e["kind"] == "fault"]
    assert events, "no fault event"
    assert events[-1]["fault"] == fault.value
    assert events[-1]["reason"]
    return events[-1]


def test_every_valid_frame_gets_one_active_command_echoing_its_counter(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        for _ in range(40):
            cmd = rig.exchange()
            assert cmd["Mode"] == ACTIVE
            assert cmd["CurrentSetpoint"] == pytest.approx(1.25, abs=1e-4)
            assert cmd["ControllerId"] == 6
            assert cmd["DesiredForce"] == pytest.approx(300.0, abs=0.01)
        assert rig.command(timeout=0.05) is None  # no extra command


def test_frames_failing_crc_get_no_command_and_beyond_budget_fault(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        rig.exchange()
        budget = rig.cfg.loop.bad_frame_budget
        for k in range(budget + 1):
            rig.sensors(crc_ok=False)
            assert rig.command(timeout=0.01) is None, "a command answered a bad frame"
            if k < budget:
                assert rig.daemon.supervisor.state is RigState.ARMED
        ev = assert_fault(rig, Fault.BAD_FRAMES)
        assert "CRC" in ev["reason"]
        assert_safe(rig.exchange())


def test_repeated_counter_beyond_budget_faults(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        c = rig.sensors()
        rig.command()
        for _ in range(rig.cfg.loop.bad_frame_budget + 1):
            rig.sensors(counter=c)
            assert rig.command(timeout=0.01) is None
        ev = assert_fault(rig, Fault.BAD_FRAMES)
        assert "repeated counter" in ev["reason"]
        assert_safe(rig.exchange())


def test_lost_frames_beyond_budget_fault(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        rig.exchange()
        rig.counter = (rig.counter + rig.cfg.loop.lost_frame_budget + 1) & 0xF  # a jump
        cmd = rig.exchange()
        assert_fault(rig, Fault.LOST_FRAMES)
        assert_safe(cmd)


def test_no_sensor_frame_for_three_periods_faults_and_sends_safe_on_its_own(tmp_path):
    with ScriptedRig(tmp_path, timeout_periods=3) as rig:
        c = rig.sensors()
        assert rig.command()["Mode"] == ACTIVE
        t0 = time.monotonic()
        cmd = rig.command(timeout=0.5)  # nothing sent: the daemon must speak by itself
        waited = time.monotonic() - t0
        assert cmd is not None, "no SAFE command after the sensor timeout"
        assert_safe(cmd)
        assert cmd["SensorCounterEcho"] == c
        assert waited < 0.1
        assert_fault(rig, Fault.SENSOR_TIMEOUT)


@pytest.mark.parametrize(
    ("kw", "fault"),
    [
        ({"x": 0.050}, Fault.DISPLACEMENT_RANGE),
        ({"x": -0.050}, Fault.DISPLACEMENT_RANGE),
        ({"force": 7000.0}, Fault.FORCE_RANGE),
        ({"force": -7000.0}, Fault.FORCE_RANGE),
        ({"EStop": 1}, Fault.ESTOP),
        ({"LimitTripped": 1}, Fault.LIMIT_TRIPPED),
        ({"SensorFault": 1}, Fault.SENSOR_FAULT),
    ],
)
def test_sensor_frame_out_of_range_or_flagged_faults_within_the_frame(tmp_path, kw, fault):
    with ScriptedRig(tmp_path) as rig:
        assert rig.exchange()["Mode"] == ACTIVE
        assert_safe(rig.exchange(**kw))  # the offending frame itself is answered SAFE
        assert_fault(rig, fault)
        assert_safe(rig.exchange())  # and it stays SAFE until re-armed


def test_range_boundaries_are_inside(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        lo, hi = rig.cfg.loop.x_range_m
        for x in (lo, hi):
            assert rig.exchange(x=x)["Mode"] == ACTIVE
        flo, fhi = rig.cfg.loop.f_range_n
        for f in (flo, fhi):
            assert rig.exchange(force=f)["Mode"] == ACTIVE


def test_firmware_fault_status_faults_and_blocks_arming(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        rig.status()
        assert rig.exchange()["Mode"] == ACTIVE
        rig.status(state="FAULT", fault_code=3)
        time.sleep(0.05)
        assert_safe(rig.exchange())
        ev = assert_fault(rig, Fault.FIRMWARE_FAULT)
        assert "STROKE_LIMIT" in ev["reason"]
        ok, msg, _ = rig.daemon.supervisor.arm(0.0)
        assert not ok and "firmware" in msg


def test_firmware_watchdog_trip_faults_an_armed_daemon(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        rig.status(timeouts=0)
        rig.exchange()
        rig.status(state="FAULT", fault_code=1, timeouts=1)
        time.sleep(0.05)
        assert_safe(rig.exchange())
        assert "watchdog" in assert_fault(rig, Fault.FIRMWARE_WATCHDOG)["reason"]


class _NaNController(Controller):
    """A controller that fails numerically (stands for a broken model)."""

    name = "nan"
    controller_id = 1

    def command(self, s):
        return np.array([math.nan])

    def model_force(self, s, current):
        return np.array([math.nan])


def test_non_finite_controller_output_faults_within_the_frame(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        assert rig.exchange()["Mode"] == ACTIVE
        rig.daemon.controller = _NaNController(2.0)
        assert_safe(rig.exchange())
        assert_fault(rig, Fault.NON_FINITE)


class _NaNReference(ref.ForceReference):
    kind = "broken"

    def force(self, t_s, x_m, xd_m_s):
        return math.nan


def test_non_finite_force_reference_faults_within_the_frame(tmp_path):
    # the command is computed from the desired force: a controller may map NaN to a finite
    # current (network inversion gave 0.0625 A), so the reference is checked on its own
    with ScriptedRig(tmp_path) as rig:
        assert rig.exchange()["Mode"] == ACTIVE
        rig.daemon.reference = _NaNReference()
        assert_safe(rig.exchange())
        assert "broken force reference" in assert_fault(rig, Fault.NON_FINITE)["reason"]


class _DivergedReference(ref.ForceReference):
    """A reference damper whose state went NaN: NaN until it is started again."""

    kind = "diverged"

    def __init__(self) -> None:
        self.diverged = True

    def reset(self, t_s, x_m):
        self.diverged = False

    def force(self, t_s, x_m, xd_m_s):
        return math.nan if self.diverged else 300.0


def test_a_diverged_force_reference_faults_once_and_starts_again(tmp_path):
    # its NaN state used to stay: the disarm out of FAULT was faulted again on the next frame
    with ScriptedRig(tmp_path) as rig:
        assert rig.exchange()["Mode"] == ACTIVE
        rig.daemon.reference = _DivergedReference()
        assert_safe(rig.exchange())
        assert_fault(rig, Fault.NON_FINITE)
        assert rig.request({"cmd": "reset"})["ok"]
        for _ in range(5):
            assert_safe(rig.exchange())
        faults = [e for e in rig.daemon.events if e["kind"] == "fault"]
        assert len(faults) == 1, faults
        assert rig.daemon.supervisor.state is RigState.IDLE
        assert rig.request({"cmd": "arm"})["ok"]
        cmd = rig.exchange()
        assert cmd["Mode"] == ACTIVE and cmd["DesiredForce"] == pytest.approx(300.0)


def test_the_estimate_goes_on_through_lost_frames(tmp_path):
    # x ramps at 50 mm/s; three frames go missing: the velocity estimate must not read the
    # four periods of travel as one (it read 0.10-0.12 m/s before)
    speed_m_s, period_s = 0.05, 2e-3
    with ScriptedRig(tmp_path) as rig:
        x = 0.001
        for _ in range(150):
            rig.exchange(x=x)
            x += speed_m_s * period_s
        rig.counter = (rig.counter + 3) & 0xF
        x += 3 * speed_m_s * period_s
        for _ in range(3):
            rig.exchange(x=x)
            x += speed_m_s * period_s
        assert rig.daemon.counters["lost_frames"] == 3
        assert rig.daemon.supervisor.state is RigState.ARMED
    samples = np.concatenate(rig.daemon.batches.handed_over())
    xd_after = samples["xd"][-3:]
    assert np.all(np.abs(xd_after - speed_m_s) < 0.01), xd_after


def test_the_estimate_restarts_after_a_gap_the_counter_cannot_tell(tmp_path):
    # x ramps at 50 mm/s; the rig stalls 0.2 s (100 periods: the 4-bit counter moves on only
    # 4), and the first frame after it holds the sample taken before it. Predicting through
    # the counter's 4 periods read 100 periods of travel as 4 and put the velocity estimate
    # far off for many frames; restarted on the stale frame, it read the next one's jump as
    # speed; restarted on the frame after it, it is the ramp's again soon
    speed_m_s, period_s, gap_periods = 0.05, 2e-3, 100
    with ScriptedRig(tmp_path) as rig:
        x = -0.01
        for _ in range(150):
            rig.exchange(x=x)
            x += speed_m_s * period_s
        time.sleep(gap_periods * period_s)  # longer than the sensor timeout: a fault
        rig.exchange(x=x)  # sampled before the gap, sent after it
        rig.counter = (rig.counter + gap_periods - 1) & 0xF
        x += gap_periods * speed_m_s * period_s
        for _ in range(30):
            rig.exchange(x=x)
            x += speed_m_s * period_s
        assert rig.daemon.counters["estimate_restarts"] == 1
        assert_fault(rig, Fault.SENSOR_TIMEOUT)
    samples = np.concatenate(rig.daemon.batches.handed_over())
    xd_after = samples["xd"][-20:]
    assert np.all(np.abs(xd_after - speed_m_s) < 0.01), xd_after


def test_stale_external_force_reference_faults(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        rig.daemon.reference = ref.External(timeout_s=0.05)
        rig.daemon.requests.on_force_ref(400.0, time.monotonic())
        cmd = rig.exchange()
        assert cmd["Mode"] == ACTIVE and cmd["DesiredForce"] == pytest.approx(400.0)
        time.sleep(0.08)
        assert_safe(rig.exchange())
        assert "stale" in assert_fault(rig, Fault.STALE_REFERENCE)["reason"]


def test_bus_error_faults_and_stops_the_loop(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        rig.exchange()
        rig.daemon.bus.shutdown()  # the bus goes away under the daemon
        rig.thread.join(timeout=2)
        assert not rig.thread.is_alive()
        assert_fault(rig, Fault.BUS_ERROR)


def test_commands_are_clamped_to_i_max(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        from mrrig.loop.controllers import ConstantCurrent

        rig.daemon.controller = ConstantCurrent(10.0, 9.0)  # a controller that asks too much
        cmd = rig.exchange()
        assert cmd["CurrentSetpoint"] == pytest.approx(rig.cfg.loop.i_max_a)


def test_rearm_after_fault_is_explicit(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        rig.exchange(EStop=1)
        assert_safe(rig.exchange())
        assert_safe(rig.exchange())
        reply = rig.request({"cmd": "arm"})  # a FAULT is acknowledged before it is armed
        assert not reply["ok"] and "acknowledge it with reset first" in reply["error"]
        assert rig.request({"cmd": "reset"})["ok"]
        assert rig.request({"cmd": "arm"})["ok"]
        assert rig.exchange()["Mode"] == ACTIVE


def test_another_senders_command_on_the_bus_faults_and_blocks_arming(tmp_path):
    """A DamperCommand the daemon did not send (a second daemon on the rig's bus): FAULT, SAFE
    from the next frame, and arming refused until that sender has been quiet for a while."""
    with ScriptedRig(tmp_path) as rig:
        assert rig.exchange()["Mode"] == ACTIVE
        other = can.Bus(interface="virtual", channel=rig.channel, receive_own_messages=False)
        try:
            values = {
                "Mode": "SAFE",
                "CurrentSetpoint": 0.0,
                "SensorCounterEcho": 0,
                "ControllerId": 0,
                "DesiredForce": 0.0,
            }
            other.send(Codec().packer("DAEMON").message("DamperCommand", values))
        finally:
            other.shutdown()
        time.sleep(0.05)
        rig.drain()  # the other sender's frame reached the scripted rig as well
        assert_safe(rig.exchange())
        ev = assert_fault(rig, Fault.FOREIGN_COMMAND)
        assert "another sender's DamperCommand" in ev["reason"]
        assert rig.daemon.counters["foreign_commands"] == 1
        reply = rig.request({"cmd": "arm"})
        assert not reply["ok"] and "second daemon" in reply["error"], reply
        assert_safe(rig.exchange())

        time.sleep(FOREIGN_HOLD_S)  # quiet since: arming is allowed again
        rig.drain()
        # once the fault (and the sensor timeout of the wait) is acknowledged
        assert rig.request({"cmd": "reset"})["ok"]
        assert rig.request({"cmd": "arm"})["ok"]
        assert rig.exchange()["Mode"] == ACTIVE


def test_a_foreign_command_is_one_event_per_episode_even_over_another_fault():
    sup = Supervisor(Limits((-0.05, 0.05), (-1e4, 1e4), 5, 5, 1.0))
    sup.trip(0.0, Fault.FIRMWARE_WATCHDOG, "firmware watchdog tripped")  # the doubled commands
    assert sup.foreign_command(0.100, "DamperCommand")  # recorded over the fault already there
    assert sup.fault is Fault.FOREIGN_COMMAND
    assert sup.foreign_command(0.102, "DamperCommand") == []  # the same sender, same episode
    sup.reset(0.103)
    assert not sup.arm(0.102 + FOREIGN_HOLD_S - 0.01)[0]
    assert sup.arm(0.102 + FOREIGN_HOLD_S)[0]


def test_the_stop_answers_safe_and_disarms_from_that_frame(tmp_path):
    """A stop (duration, signal, bus error) answers the next frame SAFE; that frame is recorded
    disarmed, so the summary's armed frames are the ACTIVE commands and the command's fall to
    0 A is not a step of the controller."""
    rig = ScriptedRig(tmp_path)
    with rig:
        for _ in range(20):
            assert rig.exchange()["Mode"] == ACTIVE
        rig.daemon.request_stop("test stop")
        assert_safe(rig.exchange())
        rig.thread.join(timeout=5)
    d = rig.daemon
    samples = np.concatenate(d.batches.handed_over())
    assert samples["state"][-1] == RigState.IDLE and samples["i_cmd"][-1] == 0.0
    assert (samples["state"][:-1] == RigState.ARMED).all()
    assert d.summary["armed_frames"] == d.counters["commands_active"] == 20
    assert d.summary["i_cmd_step_a"]["max"] == 0.0  # a constant 1.25 A until the stop
    assert any(e["text"] == "state: stopping: test stop (was ARMED)" for e in d.events), d.events


# ---- issue 42: an idle rig's transport fault ends when valid frames resume ------------------
VALID = {"EStop": 0, "LimitTripped": 0, "SensorFault": 0, "Displacement": 0.0, "Force": 0.0}


def _supervisor() -> Supervisor:
    return Supervisor(Limits((-0.05, 0.05), (-1e4, 1e4), 5, 5, 1.0))


@pytest.mark.parametrize("fault", [Fault.SENSOR_TIMEOUT, Fault.LOST_FRAMES, Fault.STALE_FRAME])
def test_a_transport_fault_of_an_idle_rig_clears_with_the_next_valid_frame(fault):
    sup = _supervisor()
    sup.trip(1.0, fault, "a stall")
    (event,) = sup.sensors(1.1, VALID)
    assert (sup.state, sup.fault, sup.reason) == (RigState.IDLE, None, "")
    assert event["kind"] == "state" and event["cleared"] == fault.value
    assert event["text"] == (
        f"state: transport fault cleared: valid sensor frames again after {fault.value}: a"
        " stall (not armed when it came: no reset needed)"
    )
    assert sup.arm(1.2)[0]  # no reset needed


def test_a_transport_fault_of_an_armed_rig_stays_until_reset():
    sup = _supervisor()
    assert sup.arm(0.0)[0]
    sup.trip(1.0, Fault.SENSOR_TIMEOUT, "a stall")
    assert sup.disarm(1.05) == []  # a disarm acknowledges nothing
    assert sup.sensors(1.1, VALID) == [] and sup.state is RigState.FAULT
    sup.trip(1.2, Fault.LOST_FRAMES, "more")  # another transport fault over it: still armed's
    assert sup.sensors(1.3, VALID) == [] and sup.state is RigState.FAULT
    assert not sup.arm(1.4)[0]
    sup.reset(1.5)
    assert sup.arm(1.6)[0]


def test_an_idle_transport_fault_that_another_fault_replaced_stays():
    sup = _supervisor()
    sup.trip(1.0, Fault.SENSOR_TIMEOUT, "a stall")
    sup.foreign_command(1.1, "DamperCommand")  # not a stall: acknowledged by reset only
    assert sup.sensors(1.2, VALID) == [] and sup.fault is Fault.FOREIGN_COMMAND


def test_the_frame_that_ends_an_idle_transport_fault_is_checked_as_any_other():
    sup = _supervisor()
    sup.trip(1.0, Fault.SENSOR_TIMEOUT, "a stall")
    cleared, estop = sup.sensors(1.1, VALID | {"EStop": 1})
    assert cleared["kind"] == "state" and estop["fault"] == Fault.ESTOP.value
    assert sup.state is RigState.FAULT and sup.fault is Fault.ESTOP
    assert sup.sensors(1.2, VALID) == [] and sup.fault is Fault.ESTOP  # needs its reset


def test_an_idle_rig_needs_no_reset_after_a_stall_but_an_armed_one_does(tmp_path):
    """A ScriptedRig: the sensor frames stop past the sensor timeout, then come again. Idle,
    the daemon is back to IDLE with an event and arms without a reset; armed, it stays in
    FAULT, sending SAFE, until reset."""
    idle = {"loop": {"arm_on_start": False}}
    with ScriptedRig(tmp_path, overrides=idle) as rig:  # a 100 ms sensor timeout
        rig.exchange()
        time.sleep(0.3)
        assert rig.daemon.supervisor.fault is Fault.SENSOR_TIMEOUT
        rig.drain()  # its SAFE commands of its own
        rig.exchange()
        assert rig.daemon.supervisor.state is RigState.IDLE
        assert any(
            e["text"].startswith("state: transport fault cleared: valid sensor frames again after"
                                 " sensor_timeout")
            for e in rig.daemon.events
        )  # fmt: skip
        reply = rig.request({"cmd": "arm"})
        assert reply["ok"], reply
        time.sleep(0.3)
        assert rig.daemon.supervisor.fault is Fault.SENSOR_TIMEOUT
        rig.drain()
        assert_safe(rig.exchange())
        assert_safe(rig.exchange())
        assert rig.daemon.supervisor.state is RigState.FAULT
        assert not rig.request({"cmd": "arm"})["ok"]
