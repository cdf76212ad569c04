"""Issue 32 (hostile input, round two), findings 1 and 9: the limits on what moves the rig
while armed hold over a sequence of requests, and every desired force stays in
`loop.f_range_n`, whatever its source."""

from __future__ import annotations

import time

import pytest

from mrrig.loop import reference as ref
from mrrig.loop.samples import RigState
from tests.rig_harness import ScriptedRig

ACTIVE = 1


def _armed_at(rig: ScriptedRig, amplitude_m: float) -> dict:
    """The actuator at `amplitude_m` while IDLE, then armed; returns the request's base."""
    rig.exchange()  # arm_on_start arms on the first frame
    assert rig.request({"cmd": "disarm"})["ok"]
    start = {"cmd": "actuator", "waveform": "sine", "amplitude_m": amplitude_m, "frequency_hz": 2}
    assert rig.request(start)["ok"]
    assert rig.request({"cmd": "arm"})["ok"]
    assert rig.daemon.supervisor.state is RigState.ARMED
    return start


def test_finding1_a_chain_of_small_steps_cannot_walk_the_amplitude_away(tmp_path):
    """Six requests of +4 mm, each within the 5 mm step: only the first is taken, since the
    second would put the motion 8 mm from what was armed (they took 15 mm to 39 mm)."""
    with ScriptedRig(tmp_path) as rig:
        start = _armed_at(rig, 0.015)
        replies = []
        for k in range(1, 7):
            replies.append(rig.request({**start, "amplitude_m": 0.015 + 0.004 * k}))
            time.sleep(0.005)
        assert replies[0]["ok"], replies[0]
        for r in replies[1:]:
            assert not r["ok"] and "from the amplitude at arming" in r["error"], r
        assert rig.daemon.actuator.amplitude_m == pytest.approx(0.019)
        # down again is fine, and so is the far side of the armed amplitude within the bound
        assert rig.request({**start, "amplitude_m": 0.010})["ok"]
        assert rig.request({"cmd": "actuator", "waveform": "stop"})["ok"]  # always


def test_finding1_the_bound_is_set_again_at_the_next_arming(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        start = _armed_at(rig, 0.015)
        assert rig.request({**start, "amplitude_m": 0.020})["ok"]
        assert not rig.request({**start, "amplitude_m": 0.024})["ok"]
        assert rig.request({"cmd": "disarm"})["ok"]
        assert rig.request({**start, "amplitude_m": 0.024})["ok"]  # not armed: any amplitude
        assert rig.request({"cmd": "arm"})["ok"]
        assert rig.request({**start, "amplitude_m": 0.029})["ok"]  # 5 mm from 24 mm


def test_finding13_a_step_of_exactly_the_limit_is_taken(tmp_path):
    """0.020 - 0.015 is 0.005000000000000001 in floats: refused before as 'a step of 0.005 m
    ... (limit 0.005 m)'."""
    with ScriptedRig(tmp_path) as rig:
        start = _armed_at(rig, 0.015)
        reply = rig.request({**start, "amplitude_m": 0.020})
        assert reply["ok"], reply


def test_finding9_a_force_ref_beyond_the_range_is_clamped_and_counted(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        rig.daemon.reference = ref.External(timeout_s=0.5)
        lo, hi = rig.daemon.cfg.loop.f_range_n
        rig.daemon.requests.on_force_ref(1e300, time.monotonic())
        cmd = rig.exchange()
        assert cmd["Mode"] == ACTIVE
        assert cmd["DesiredForce"] == pytest.approx(hi)
        rig.daemon.requests.on_force_ref(-1e300, time.monotonic())
        assert rig.exchange()["DesiredForce"] == pytest.approx(lo)
        assert rig.daemon.counters["force_refs_clamped"] == 2
        notes = [e for e in rig.daemon.events if e["kind"] == "force_ref_clamped"]
        assert len(notes) == 1 and "outside loop.f_range_n" in notes[0]["reason"], notes


def test_finding9_a_csv_profile_beyond_the_range_is_refused_by_set_profile(tmp_path):
    profiles = tmp_path / "profiles"
    profiles.mkdir()
    (profiles / "huge.csv").write_text("t_s,force_n\n0,0\n0.5,1e300\n1,0\n")
    overrides = {"control": {"profile_dirs": [str(profiles)]}}
    with ScriptedRig(tmp_path, overrides=overrides) as rig:
        rig.exchange()
        assert rig.request({"cmd": "disarm"})["ok"]
        reply = rig.request(
            {"cmd": "set_profile", "kind": "csv", "path": str(profiles / "huge.csv")}
        )
        assert not reply["ok"], reply
        assert "force_n 1e+300 N at t_s 0.5 s" in reply["error"], reply
        assert "outside loop.f_range_n [-6000, 6000] N" in reply["error"], reply
        assert rig.daemon.reference.kind == "constant"


def test_finding9_a_reference_damper_is_clamped_to_the_range(tmp_path):
    """A source known only as it comes (here a sine reference swapped in past the checks, as
    a reference damper's force would be): the desired force sent is the range's bound."""
    with ScriptedRig(tmp_path) as rig:
        rig.daemon.reference = ref.Sine(50_000.0, 0.0, 1.0)
        cmd = rig.exchange()
        assert cmd["DesiredForce"] == pytest.approx(rig.daemon.cfg.loop.f_range_n[1])
