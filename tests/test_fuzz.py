"""Fuzzing the daemon with hypothesis: random and mutated CAN frames, random JSON requests,
and random sequences of requests and frames (a stateful test), against the real daemon loop
(tests/rig_harness.py: the daemon in a thread, the firmware scripted frame by frame).

Invariants: every genuine sensor frame is answered exactly once, echoing its counter; no
command answers anything else; no command exceeds the current limit; no ACTIVE answer to a
stale frame; every request gets a reply; the loop never stops. `mrrig bench fuzz` runs the
same against a live rig (bridge, firmware_sim, daemon as processes).
"""

from __future__ import annotations

import json
import math
import random
import tempfile
import time
from pathlib import Path

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from firmware_sim.runner import RunStats
from mrrig.offline.bench.fuzz import Listener, signal_outcome
from mrrig.offline.bench.fuzz_inputs import chain
from mrrig.offline.bench.fuzz_verdict import failures, motion_beyond_limits
from mrrig.rigio.canbus import Codec, open_bus
from mrrig.rigio.control import RequestError, parse_request
from tests.rig_harness import ScriptedRig
from tests.test_firmware import QUIET, Rig

I_MAX_A = 2.0
FUZZ = settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)

json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=30,
)
requests = st.fixed_dictionaries(
    {"cmd": st.sampled_from(["arm", "disarm", "status", "set_profile", "set_controller",
                             "actuator", "set_model", "reset_adaptation", "bogus"])},
    optional={
        "kind": st.sampled_from(["constant", "sine", "noise", "csv", "zenoh"]) | json_values,
        "amplitude_n": st.floats(allow_nan=True, allow_infinity=True) | json_values,
        "offset_n": st.floats(-1e6, 1e6),
        "name": st.sampled_from(["heaviside", "constant", "network_inversion"]) | json_values,
        "current_a": st.floats(-5, 5),
        "waveform": st.sampled_from(["sine", "stop", "hold"]) | json_values,
        "amplitude_m": st.floats(-1, 1),
        "frequency_hz": st.floats(-10, 100),
        "path": st.sampled_from(["../../etc/passwd", "/dev/zero", "models/x.json"]) | json_values,
    },
)  # fmt: skip


def _junk(data) -> can.Message:
    """A frame that is no valid frame of the rig: 29-bit, remote, of no DBC message, of the
    wrong length, or with a broken CRC (the mutation of a valid RigSensors frame)."""
    kind = data.draw(st.sampled_from(["extended", "remote", "unknown", "short", "crc"]))
    payload = data.draw(st.binary(min_size=0, max_size=8))
    if kind == "extended":
        arb = data.draw(st.sampled_from([0x110, 0x111, 0x210]) | st.integers(0, (1 << 29) - 1))
        return can.Message(arbitration_id=arb, is_extended_id=True, data=payload)
    if kind == "remote":
        arb = data.draw(st.sampled_from([0x110, 0x111]) | st.integers(0, 0x7FF))
        return can.Message(arbitration_id=arb, is_remote_frame=True, dlc=len(payload))
    if kind == "unknown":
        arb = data.draw(
            st.integers(0, 0x7FF).filter(lambda i: i not in (0x110, 0x111, 0x210, 0x211))
        )
        return can.Message(arbitration_id=arb, is_extended_id=False, data=payload)
    if kind == "short":
        return can.Message(arbitration_id=0x110, is_extended_id=False, data=payload[:7])
    return None  # "crc": built by the caller from a valid frame


def _check(cmd: dict, counter: int, stale: bool) -> None:
    assert cmd is not None, f"no command for genuine frame {counter}"
    assert cmd["SensorCounterEcho"] == counter
    assert cmd["CurrentSetpoint"] <= I_MAX_A + 1e-4
    if stale:
        assert cmd["Mode"] == 0, "an ACTIVE answer to a stale frame"


@pytest.mark.process
@FUZZ
@given(data=st.data())
def test_random_and_mutated_frames_never_get_a_command_and_genuine_ones_get_one(tmp_path, data):
    with ScriptedRig(tmp_path, max_frame_age_s=0.05) as rig:
        for _ in range(data.draw(st.integers(1, 12))):
            junk = _junk(data)
            if junk is None:  # a valid frame's CRC byte flipped in some bits
                good = rig.packer.encode(
                    "RigSensors",
                    {"ActuatorEnabled": 1, "LimitTripped": 0, "EStop": 0, "SensorFault": 0,
                     "Displacement": 0.001, "Force": 1.0},
                    counter=(rig.counter + 8) & 0xF,
                )  # fmt: skip
                flip = data.draw(st.integers(1, 255))
                junk = can.Message(
                    arbitration_id=0x110,
                    is_extended_id=False,
                    data=bytes([good[0] ^ flip]) + good[1:],
                )
            junk.timestamp = time.time()
            rig.bus.send(junk)
            stale = data.draw(st.booleans())
            counter = rig.sensors(age_s=0.2 if stale else 0.0)
            _check(rig.command(expect=counter), counter, stale)
        assert rig.command(timeout=0.02) is None, "a command for a frame that was no valid one"
        assert rig.thread.is_alive()


def test_parse_request_only_ever_raises_a_request_error():
    @settings(max_examples=300, deadline=None)
    @given(raw=st.binary(max_size=3000) | json_values.map(lambda v: json.dumps(v).encode()))
    def check(raw: bytes) -> None:
        try:
            req = parse_request(raw)
        except RequestError as exc:
            assert str(exc) and "\n" not in str(exc)
            return
        assert isinstance(req, dict) and isinstance(req["cmd"], str)
        assert not any(isinstance(v, float) and not math.isfinite(v) for v in req.values())

    check()


@pytest.mark.process
@FUZZ
@given(reqs=st.lists(requests, min_size=1, max_size=6))
def test_random_requests_each_get_a_reply_and_the_loop_goes_on(tmp_path, reqs):
    with ScriptedRig(tmp_path) as rig:
        for req in reqs:
            raw = json.dumps(req).encode()  # NaN and Infinity as Python writes them
            try:
                parse_request(raw)
            except RequestError:
                continue  # the sidecar refuses it: it never reaches the daemon
            reply = rig.request(req)
            assert set(reply) >= {"ok"} and (reply["ok"] or reply["error"]), reply
            cmd = rig.exchange()
            assert cmd["CurrentSetpoint"] <= I_MAX_A + 1e-4
        assert rig.thread.is_alive()


class RequestSequences(RuleBasedStateMachine):
    """Random sequences of requests and frames against one running daemon."""

    def __init__(self) -> None:
        super().__init__()
        self.rig = ScriptedRig(Path(tempfile.mkdtemp(prefix="mrrig-fuzz-")), max_frame_age_s=0.05)
        self.rig.__enter__()
        self.replies = 0

    @rule(req=requests)
    def request(self, req) -> None:
        try:
            parse_request(json.dumps(req).encode())
        except RequestError:
            return
        reply = self.rig.request(req)
        assert "ok" in reply, reply
        self.replies += 1

    @rule(stale=st.booleans(), flags=st.sampled_from([{}, {"EStop": 1}, {"SensorFault": 1}]))
    def frame(self, stale, flags) -> None:
        counter = self.rig.sensors(age_s=0.2 if stale else 0.0, **flags)
        _check(self.rig.command(expect=counter), counter, stale)

    @rule()
    def rearm(self) -> None:
        assert "ok" in self.rig.request({"cmd": "arm"})

    @invariant()
    def loop_runs(self) -> None:
        assert self.rig.thread.is_alive()

    def teardown(self) -> None:
        self.rig.__exit__(None, None, None)


RequestSequences.TestCase.settings = settings(
    max_examples=10, stateful_step_count=15, deadline=None
)
test_request_sequences = pytest.mark.process(RequestSequences.TestCase)


def _armed_motion(rig: Rig) -> list[dict]:
    """The firmware's armed_motion as `mrrig bench fuzz` reads it from the stats file."""
    summary = RunStats().summary(rig.fw, 1.0, 0.0)
    return json.loads(json.dumps(summary["armed_motion"]))


def test_bench_fuzz_finds_motion_beyond_the_amplitude_armed_plus_the_step():
    """Issue 32's excursion, on the firmware: six actuator requests of 4 mm, 5 ms apart, while
    ACTIVE took the motion from 15 mm to 39 mm; the daemon's step is 5 mm."""
    rig = Rig()
    rig.actuator("SINE", 0.015, 2.0)
    rig.run(300, answer="SAFE")
    rig.run(10, answer="ACTIVE")
    for request in chain("amplitude", random.Random(1)):
        assert request["amplitude_m"] > 0.015  # this seed steps up
        rig.actuator("SINE", request["amplitude_m"], 2.0)
        rig.run(2, answer="ACTIVE")  # 4 ms; a request every 5 ms
    rig.run(300, answer="ACTIVE")
    (beyond,) = motion_beyond_limits(_armed_motion(rig), 0.005)
    assert beyond["amplitude_at_start_m"] == pytest.approx(0.015)
    assert beyond["amplitude_max_m"] == pytest.approx(0.039)


def test_bench_fuzz_takes_motion_within_the_step_and_a_disarmed_change():
    rig = Rig()
    rig.actuator("SINE", 0.015, 2.0)
    rig.run(300, answer="SAFE")
    rig.run(10, answer="ACTIVE")
    rig.actuator("SINE", 0.020, 2.0)  # one step of 5 mm: within the limit
    rig.run(300, answer="ACTIVE")
    rig.run(1, answer="SAFE")
    rig.actuator("SINE", 0.040, 2.0)  # disarmed: the next arming takes 40 mm
    rig.run(1, answer="SAFE")
    rig.run(300, answer="ACTIVE")
    motion = _armed_motion(rig)
    assert len(motion) == 2 and motion_beyond_limits(motion, 0.005) == []
    assert motion_beyond_limits(motion, 0.004), "the 5 mm step is beyond a 4 mm limit"


def test_bench_fuzz_finds_a_frequency_raised_while_armed():
    rig = Rig()
    rig.actuator("SINE", 0.015, 2.0)
    rig.run(10, answer="SAFE")
    rig.run(10, answer="ACTIVE")
    for request in chain("frequency", random.Random(1)):
        rig.actuator("SINE", 0.015, request["frequency_hz"])
        rig.run(2, answer="ACTIVE")
    rig.run(round(QUIET.actuator.ramp_s / 0.002), answer="ACTIVE")
    (beyond,) = motion_beyond_limits(_armed_motion(rig), 0.005)
    assert beyond["frequency_max_hz"] == pytest.approx(5.0)


def test_bench_fuzz_chains_of_force_values_rise_past_the_range_to_1e300():
    forces = chain("force_ref", random.Random(0))
    assert len(forces) == 7 and abs(forces[-1]) == 1e300
    assert max(abs(f) for f in forces[:-1]) > 6000.0
    profiles = chain("set_profile", random.Random(1))
    assert all(r["cmd"] == "set_profile" for r in profiles)


def test_bench_fuzz_a_signal_that_killed_the_daemon_active_is_a_failure(tmp_path):
    """SIGHUP killed the daemon at once (rc -1), its last command ACTIVE, no summary."""
    outcome, ok = signal_outcome(-1, True, False, tmp_path / "none.json")
    assert not ok
    assert outcome == ("ended, exit code -1, last command ACTIVE, actuator not stopped, no summary")
    summary = tmp_path / "summary.json"
    summary.write_text("{}")
    assert signal_outcome(0, False, True, summary) == (
        "ended SAFE (exit code 0, summary written)",
        True,
    )
    assert signal_outcome(None, True, False, summary) == ("ignored", True)


def test_bench_fuzz_fails_on_each_count_that_is_not_0():
    clean = {
        "crashes": [], "commands_above_limit": 0, "desired_force_out_of_range": 0,
        "motion_beyond_limits": 0, "active_applied_to_stale": 0,
        "active_applied_to_invalid": 0, "active_answers_invalid": 0, "requests_unanswered": 0,
        "max_commanded_current_a": 2.0, "armed_without_lease": 0, "faulty_bus_not_aborted": 0,
        "runs_missing_from_catalog": [],
    }  # fmt: skip
    assert failures(clean, 2.0) == []
    for name in clean:
        listed = name in ("crashes", "runs_missing_from_catalog")
        bad = {**clean, name: ["x"] if listed else 3}
        assert failures(bad, 2.0) == [name]


def test_bench_fuzz_counts_a_recording_whose_run_is_neither_catalogued_nor_journalled(tmp_path):
    """Issue 40: a run is in the catalog, or journalled beside its recording and replayed into
    it; a recording with neither is a lost run."""
    from mrrig.catalog import register_run
    from mrrig.catalog.journal import journal_path, write_journal
    from mrrig.offline.bench.fuzz_faulty_bus import runs_missing
    from tests.test_catalog import run

    catalog = tmp_path / "catalog.sqlite"
    recs = [tmp_path / f"fuzz-{n}.rrd" for n in range(3)]
    for p in recs:
        p.write_bytes(b"RRF2")
    register_run(catalog, run(0, recording_path=str(recs[0])))
    journalled = run(1, recording_path=str(recs[1]))
    write_journal(journal_path(journalled, str(catalog), None), journalled, str(catalog), None)
    assert runs_missing(recs, catalog) == ["fuzz-2.rrd"]


@pytest.mark.process
def test_bench_fuzz_listener_counts_commands_above_the_limits_and_to_no_genuine_frame(bridge):
    """Through the bridge, as in a campaign: an ACTIVE command of 2.5 A (limit 2 A) with a
    desired force of 7000 N (range 6000 N) answering a genuine frame, and one answering a
    counter no genuine frame had."""
    codec = Codec()
    listener = Listener(bridge, 2.0, (-6000.0, 6000.0))
    listener.start()
    bus = open_bus("remote", bridge)
    try:
        rig, daemon = codec.packer("RIG"), codec.packer("DAEMON")
        sensors = rig.message(
            "RigSensors",
            {"ActuatorEnabled": 1, "LimitTripped": 0, "EStop": 0, "SensorFault": 0,
             "Displacement": 0.001, "Force": 10.0},
        )  # fmt: skip
        bus.send(sensors)
        counter = codec.parser().parse_message(sensors).counter
        for echo, current_a, force_n in ((counter, 2.5, 7000.0), ((counter + 5) % 16, 1.0, 0.0)):
            time.sleep(0.05)
            bus.send(
                daemon.message(
                    "DamperCommand",
                    {
                        "Mode": "ACTIVE",
                        "CurrentSetpoint": current_a,
                        "SensorCounterEcho": echo,
                        "ControllerId": 1,
                        "DesiredForce": force_n,
                    },
                )  # fmt: skip
            )
        deadline = time.monotonic() + 5.0
        while listener.commands < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        bus.shutdown()
        listener.stop()
    assert listener.commands == 2
    assert (listener.above_limit, listener.force_out_of_range) == (1, 1)
    assert listener.active_unmatched == 1 and listener.last_mode == 1
