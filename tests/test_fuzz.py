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
import tempfile
import time
from pathlib import Path

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.offline.bench.fuzz import stale_answers_sent_in_time
from mrrig.rigio.control import RequestError, parse_request
from tests.rig_harness import ScriptedRig

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


def test_a_stale_answer_is_set_aside_only_when_the_daemon_recorded_sending_it_in_time():
    """The simulator saw 4 ACTIVE answers reach the bus over 10 ms after their frames; the
    daemon's recording shows which it sent within the limit (the bus took those in late)."""
    samples = np.zeros(4, dtype=SAMPLE_DTYPE)
    samples["t"] = [0.001, 1.001, 2.001, 3.001]  # the loop's reads, on the daemon's clock
    samples["counter"] = [1, 2, 3, 4]
    samples["state"] = [RigState.ARMED, RigState.ARMED, RigState.FAULT, RigState.ARMED]
    samples["latency_us"] = [9_000, 10_500, 9_000, 9_000]
    stats = {
        "stale_answer_age_s": 0.01,
        "clock_t0_s": 100.0,  # the daemon's clock zero is 100.5 s on the same clock
        "stale_answers": [
            {"counter": 1, "frame_s": 0.5, "answer_s": 0.512},  # sent at 9 ms: the bus's
            {"counter": 2, "frame_s": 1.5, "answer_s": 1.512},  # sent at 10.5 ms: the daemon's
            {"counter": 3, "frame_s": 2.5, "answer_s": 2.512},  # not ARMED in the recording
            {"counter": 5, "frame_s": 3.5, "answer_s": 3.512},  # no sample of that frame
        ],
    }
    assert stale_answers_sent_in_time(stats, samples, 100.5) == 1
    assert stale_answers_sent_in_time({**stats, "stale_answers": []}, samples, 100.5) == 0
