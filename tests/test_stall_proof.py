"""The process tests' proof (`tests/stall_proof.py`) on made-up runs: what it sets aside and
what it refuses."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest

from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.rigio.rig_session import RigSession
from tests.rig_harness import ThreadRig
from tests.stall_proof import prove

T0_SIM, T0_DAEMON = 1000.0, 998.0  # the two processes' time zeros on CLOCK_MONOTONIC
ON_TIME = {"frames": 5000, "answered_once": 5000, "unanswered": 0, "more_than_once": 0}


def sim_stats(windows=(), trips=(), on_time=ON_TIME) -> dict:
    """Simulator stats: windows (kind, start, end) and watchdog trips (t, gap) in its time."""
    return {
        "clock_t0_s": T0_SIM,
        "answers_on_time": dict(on_time),
        "answers": {"unmatched": 0},
        "stall_windows": [{"kind": k, "start_s": a, "end_s": b} for k, a, b in windows],
        "fault_events": [
            {"t_s": t, "event": f"watchdog: no valid DamperCommand for {gap * 1e3:.1f} ms"}
            for t, gap in trips
        ],
        "echo_us": {"n": 0},
    }


def fault(t_sim: float, reason: str) -> dict:
    return {"t": t_sim + T0_SIM - T0_DAEMON, "reason": reason}


def test_a_sensor_timeout_inside_a_stall_of_the_simulator_is_explained_and_printed(capsys):
    st = sim_stats([("simulator", 3.000, 3.100)])
    proof = prove(st, [fault(3.0205, "no sensor frame for 20.5 ms")], T0_DAEMON)
    assert len(proof.explained) == 1
    assert "simulator stall 100.0 ms [1003.000, 1003.100] s" in capsys.readouterr().out


def test_a_watchdog_trip_is_explained_by_the_transport_stall_that_kept_the_commands():
    st = sim_stats([("transport", 5.000, 5.030)], trips=[(5.021, 0.021)])
    proof = prove(st, [fault(5.090, "firmware watchdog tripped (no valid command for 20 ms)")],
                  T0_DAEMON)  # fmt: skip
    assert proof.explained[0][1].kind == "transport"


def test_a_stall_that_begins_in_the_transport_and_goes_on_in_the_simulator_is_one():
    st = sim_stats([("transport", 2.000, 2.012), ("simulator", 2.010, 2.040)])
    assert prove(st, [fault(2.025, "no sensor frame for 24 ms")], T0_DAEMON).explained


@pytest.mark.parametrize(
    ("windows", "trips", "f"),
    [
        ((), (), fault(3.0, "no sensor frame for 20.5 ms")),  # no stall at all
        ([("simulator", 3.0, 3.008)], (), fault(3.0205, "no sensor frame for 20.5 ms")),  # short
        ([("simulator", 1.0, 1.1)], (), fault(3.0, "no sensor frame for 20.5 ms")),  # elsewhere
        # the daemon's own stall: the firmware's watchdog trips while the simulator runs on
        ([("transport", 7.0, 7.006)], [(7.021, 0.021)], fault(7.08, "firmware watchdog tripped")),
        ((), (), fault(4.0, "non-finite controller output")),  # a controller that failed
        ([("simulator", 3.0, 3.1)], (), fault(3.5, "stale external force reference")),
        # inside a stall, but not a fault a stall causes
        ([("simulator", 3.9, 4.1)], (), fault(4.0, "RuntimeError: the controller's bug")),
    ],
    ids=[
        "none",
        "too-short",
        "elsewhere",
        "daemon-stall",
        "controller",
        "after-the-stall",
        "not-a-stalls-fault",
    ],  # fmt: skip
)
def test_a_fault_no_measured_stall_explains_fails_the_proof(windows, trips, f):
    with pytest.raises(AssertionError, match="no measured stall explains"):
        prove(sim_stats(windows, trips), [f], T0_DAEMON)


def test_a_frame_sent_on_time_without_exactly_one_answer_fails_the_proof():
    on_time = {**ON_TIME, "answered_once": 4999, "more_than_once": 1}
    with pytest.raises(AssertionError, match="more_than_once"):
        prove(sim_stats(on_time=on_time), [], T0_DAEMON)


def test_tracking_is_scored_outside_the_stalls_and_their_settling():
    t = np.arange(0.0, 6.0, 0.002)
    s = np.zeros(t.size, dtype=SAMPLE_DTYPE)
    s["t"] = t + T0_SIM - T0_DAEMON  # daemon time of the simulator's instants
    s["state"] = RigState.ARMED
    s["f_des"] = 500.0 * np.sin(2 * np.pi * t)
    s["f_meas"] = s["f_des"] + 5.0
    s["f_meas"][(t >= 2.25) & (t < 2.45)] = 0.0  # the stall and its settling
    s["state"][(t >= 2.2705) & (t < 3.0)] = RigState.FAULT  # until the operator re-armed
    st = sim_stats([("simulator", 2.25, 2.35)])
    timeout = fault(2.2705, "no sensor frame for 20.5 ms")
    proof = prove(st, [timeout], T0_DAEMON, s, et_bound=0.02)
    assert proof.armed_frames == int((t < 2.25).sum() + (t >= 3.0).sum())
    with pytest.raises(AssertionError, match="0.02"):  # the stall's frames scored
        prove(sim_stats(), [], T0_DAEMON, s, et_bound=0.02)


# ------------------------------------------------- the daemon's own stalls, measured by the kernel
STALE = "sensor frame 12.9 ms old when answered (limit 10 ms): the daemon or the bus stalled"


def kernel(*windows) -> dict:
    """A daemon summary's `kernel_stalls` with windows [t_start, t_end, runq_ms, steal_ms] on
    the daemon's clock."""
    return {
        "measured": True,
        "runq_total_ms": 100.0,
        "runq_max_ms": max((w[2] for w in windows), default=0.0),
        "steal_total_ms": 0.0,
        "steal_max_ms": max((w[3] for w in windows), default=0.0),
        "window_min_ms": 2.0,
        "windows_count": len(windows),
        "windows": [list(w) for w in windows],
    }


def stale(t_daemon: float) -> dict:
    return {"t": t_daemon, "reason": STALE, "fault": "stale_frame"}


def test_a_stale_frame_inside_a_stall_the_kernel_measured_is_attributed_and_printed(capsys):
    """The CI failure: a frame 12.9 ms old when answered, no stall the simulator measured;
    the daemon's loop waited 14.2 ms on the run queue in the pass that answered it."""
    proof = prove(
        sim_stats(), [stale(12.345)], T0_DAEMON, kernel=kernel([12.331, 12.346, 14.2, 0.0])
    )
    ((f, w),) = proof.explained
    assert w.kind == "kernel" and w.runq_ms == 14.2
    out = capsys.readouterr().out
    assert (
        "stale_frame at t=12.345 s: daemon waited 14.2 ms on the run queue in [12.331, 12.346] s"
        in out
    )


def test_a_sensor_timeout_the_vms_steal_explains_is_attributed_with_its_figure(capsys):
    """20.5 ms without a frame: two passes next to it lost 6.1 ms on the run queue and 10 ms
    (one tick) to steal: 16.1 ms, within DETECT_S of the gap."""
    k = kernel([7.479, 7.486, 6.1, 0.0], [7.486, 7.500, 0.0, 10.0])
    prove(sim_stats(), [{"t": 7.5, "reason": "no sensor frame for 20.5 ms"}], T0_DAEMON, kernel=k)
    out = capsys.readouterr().out
    assert (
        "daemon waited 6.1 ms on the run queue and lost 10 ms to the VM's steal in [7.479, 7.500] s"
        in out
    )


def test_a_stale_frame_while_another_daemon_thread_waited_on_a_run_queue_is_attributed(capsys):
    """CI: validate's loop answered a frame 10.8 ms late, its own thread never on a run queue:
    the process's pipe-server thread (holding the GIL, maybe) waited 11.5 ms on one."""
    k = kernel([12.331, 12.346, 0.1, 0.0, 11.5])
    proof = prove(sim_stats(), [stale(12.345)], T0_DAEMON, kernel=k)
    ((f, w),) = proof.explained
    assert w.kind == "kernel" and w.others_ms == 11.5
    assert "another of its threads (the GIL's holder?) 11.5 ms" in capsys.readouterr().out
    with pytest.raises(AssertionError, match="no measured stall explains"):  # 4 ms: too little
        prove(sim_stats(), [stale(12.345)], T0_DAEMON, kernel=kernel([12.331, 12.346, 0, 0, 4]))


@pytest.mark.parametrize(
    ("windows", "f"),
    [
        ([], stale(12.345)),  # the kernel measured nothing
        ([[11.000, 11.015, 14.2, 0.0]], stale(12.345)),  # elsewhere
        ([[12.331, 12.346, 3.0, 0.0]], stale(12.345)),  # too little for 12.9 ms
        ([[12.400, 12.420, 20.0, 0.0]], stale(12.345)),  # well after the answer
        # a daemon stall does not lose frames on the bus
        ([[2.990, 3.010, 20.0, 0.0]], {"t": 3.0, "reason": "3 sensor frames lost"}),
        # inside a kernel window, but not a fault a stall causes
        ([[3.990, 4.010, 20.0, 0.0]], {"t": 4.0, "reason": "RuntimeError: the controller's bug"}),
    ],
    ids=["none", "elsewhere", "too-little", "after", "lost-frames", "not-a-stalls-fault"],
)
def test_a_fault_the_kernels_measurements_do_not_explain_still_fails(windows, f):
    with pytest.raises(AssertionError, match="no measured stall explains.*the kernel's near them"):
        prove(sim_stats(), [f], T0_DAEMON, kernel=kernel(*windows))


def test_a_fault_outside_every_window_names_the_kernels_figures_near_it():
    k = kernel([12.250, 12.264, 14.0, 0.0])
    with pytest.raises(AssertionError, match=r"daemon waited 14.0 ms .* \[12.250, 12.264\] s"):
        prove(sim_stats(), [stale(12.345)], T0_DAEMON, kernel=k)


def test_the_frames_before_a_fault_the_kernel_explains_are_set_aside_from_tracking():
    t = np.arange(0.0, 4.0, 0.002)
    s = np.zeros(t.size, dtype=SAMPLE_DTYPE)
    s["t"], s["state"] = t, RigState.ARMED
    s["f_des"] = 500.0 * np.sin(2 * np.pi * t)
    s["f_meas"] = s["f_des"] + 5.0
    s["f_meas"][(t >= 2.0) & (t < 2.1)] = 0.0  # the stall and its settling
    s["state"][t >= 2.016] = RigState.FAULT
    k = kernel([2.001, 2.016, 14.2, 0.0])
    proof = prove(sim_stats(), [stale(2.016)], 0.0, s, et_bound=0.02, kernel=k)
    assert proof.armed_frames == int((t < 2.001).sum())


# ----------------------------------------------- the daemon and the simulator's loop, in-process
def _armed_session(tmp_path, rig: ThreadRig) -> RigSession:
    cfg = rig.daemon_config(
        tmp_path,
        controller={"name": "constant", "current_a": 0.5},
        actuator={"waveform": "sine", "amplitude_m": 0.01, "frequency_hz": 2.0},
    )
    return RigSession(cfg)


@pytest.mark.process
def test_a_controller_that_raises_once_is_a_fault_no_stall_explains(tmp_path):
    """A fault of the daemon's own (its controller raised, a test's hook): the simulator ran
    on time, so the proof refuses it, whatever else the machine did meanwhile."""
    with ThreadRig() as rig, _armed_session(tmp_path, rig) as session:
        session.request(cmd="arm")
        time.sleep(0.3)
        controller = session.loop.daemon.controller
        command_one = controller.command_one

        def raise_once(*args):
            controller.command_one = command_one
            raise RuntimeError("the controller's bug")

        controller.command_one = raise_once
        time.sleep(0.3)
        assert session.state() is RigState.FAULT
        with pytest.raises(AssertionError, match="no measured stall explains.*controller's bug"):
            rig.explain_faults(session)


@pytest.mark.process
def test_a_stall_of_the_simulator_explains_the_fault_it_causes_and_is_printed(tmp_path, capsys):
    """The simulator's loop held up 100 ms: the daemon's sensor timeout (25 periods here)
    faults it; the simulator measured the stall, and the proof prints its window."""
    with ThreadRig() as rig, _armed_session(tmp_path, rig) as session:
        session.request(cmd="arm")
        time.sleep(0.3)
        rig.hold(0.1)
        time.sleep(0.3)
        assert session.state() is RigState.FAULT
        rig.explain_faults(session)
    out = capsys.readouterr().out
    print(out)
    assert re.search(r"fault at t=.*no sensor frame.*inside the simulator stall 1\d\d\.\d ms", out)
