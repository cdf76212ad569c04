"""Issue 23's findings, one test (or a few) each: hostile requests and frames, stalls, and
dead or failing parts. Each test is named after its finding and reproduced what the issue
saw before the fix; now it checks the fixed behaviour.

The daemon runs its real loop in a thread on a python-can virtual bus (tests/rig_harness.py),
stepped frame by frame; the findings about the sidecar, the recording and `mrrig run`, which
run as processes, are tests/test_hostile_input_processes.py's (a process module).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import can
import pytest

from mrrig.config import load_config
from mrrig.loop.safety import Fault
from mrrig.loop.samples import RigState
from mrrig.rigio.canbus.codec import Codec
from mrrig.typed_config import ConfigError
from tests.conftest import REPO
from tests.rig_harness import ScriptedRig

ACTIVE, SAFE = 1, 0


def _dirs(tmp_path: Path) -> dict[str, dict]:
    """Config overrides: model and profile directories of the test's own."""
    models, profiles = tmp_path / "models", tmp_path / "profiles"
    models.mkdir(exist_ok=True)
    profiles.mkdir(exist_ok=True)
    return {"control": {"model_dirs": [str(models)], "profile_dirs": [str(profiles)]}}


def _disarm(rig: ScriptedRig) -> None:
    """Disarm after the first frame (which arms it: arm_on_start)."""
    rig.exchange()
    assert rig.request({"cmd": "disarm"})["ok"]
    assert rig.daemon.supervisor.state is RigState.IDLE


def _faults(rig: ScriptedRig) -> list[str]:
    return [e["fault"] for e in rig.daemon.events if e["kind"] == "fault"]


# ---- 1. one request kills the control plane ------------------------------------------------


def test_finding1_a_model_file_nested_deeply_is_refused_and_the_loop_goes_on(tmp_path):
    with ScriptedRig(tmp_path, overrides=_dirs(tmp_path)) as rig:
        bad = tmp_path / "models" / "deep.json"
        bad.write_text("[" * 100_000 + "]" * 100_000)
        _disarm(rig)
        reply = rig.request(
            {"cmd": "set_controller", "name": "network_inversion", "model": str(bad)}
        )
        assert not reply["ok"] and "nested deeper than 32 levels" in reply["error"], reply
        assert rig.request({"cmd": "arm"})["ok"]
        assert rig.exchange()["Mode"] == ACTIVE
        assert rig.daemon.controller.name == "constant"  # unchanged


# ---- 2. files read by the loop, from anywhere ---------------------------------------------
def test_finding2_a_profile_path_outside_the_profile_directories_is_refused(tmp_path):
    with ScriptedRig(tmp_path, overrides=_dirs(tmp_path)) as rig:
        _disarm(rig)
        for path in ("../../etc/passwd", "/etc/passwd", str(tmp_path / "profiles/../x.csv")):
            reply = rig.request({"cmd": "set_profile", "kind": "csv", "path": path})
            assert not reply["ok"] and "outside the allowed directories" in reply["error"], reply
            assert "root:" not in reply["error"]
        assert rig.daemon.reference.kind == "constant"


def test_finding2_a_named_pipe_is_refused_at_once_while_frames_are_answered(tmp_path):
    with ScriptedRig(tmp_path, overrides=_dirs(tmp_path)) as rig:
        fifo = tmp_path / "profiles" / "pipe.csv"
        os.mkfifo(fifo)
        _disarm(rig)
        t0 = time.monotonic()
        reply = rig.request({"cmd": "set_profile", "kind": "csv", "path": str(fifo)})
        assert not reply["ok"] and "not a regular file" in reply["error"], reply
        assert time.monotonic() - t0 < 1.0


def test_finding2_an_oversize_profile_is_refused_and_a_small_one_taken_only_disarmed(tmp_path):
    with ScriptedRig(tmp_path, overrides=_dirs(tmp_path)) as rig:
        big = tmp_path / "profiles" / "big.csv"
        with big.open("wb") as fh:
            fh.truncate(15_800_000)  # sparse: the size is what is checked first
        good = tmp_path / "profiles" / "good.csv"
        good.write_text("t_s,force_n\n0,100\n1,200\n")
        assert rig.exchange()["Mode"] == ACTIVE  # armed at its first frame
        reply = rig.request({"cmd": "set_profile", "kind": "csv", "path": str(good)})
        assert not reply["ok"] and "only when not armed" in reply["error"], reply
        _disarm(rig)
        reply = rig.request({"cmd": "set_profile", "kind": "csv", "path": str(big)})
        assert not reply["ok"] and "over the limit of 4000000" in reply["error"], reply
        reply = rig.request({"cmd": "set_profile", "kind": "csv", "path": str(good)})
        assert reply == {"ok": True, "reference": "csv"}
        assert rig.daemon.reference.kind == "csv"


# ---- 3. frames queued during a stall answered ACTIVE ---------------------------------------
def test_finding3_frames_older_than_the_age_limit_are_answered_safe_and_fault(tmp_path):
    with ScriptedRig(tmp_path, max_frame_age_s=0.01) as rig:
        for _ in range(5):
            assert rig.exchange()["Mode"] == ACTIVE
        # a backlog, as after a 60 ms stall of the daemon: each frame still gets one command
        counters = [rig.sensors(age_s=0.06 - 0.002 * k) for k in range(5)]
        answers = [rig.command() for _ in counters]
        assert [a["SensorCounterEcho"] for a in answers] == counters
        assert all(a["Mode"] == SAFE and a["CurrentSetpoint"] == 0.0 for a in answers)
        assert _faults(rig) == [Fault.STALE_FRAME.value]
        assert rig.daemon.counters["stale_frames"] == 5
        assert "ms old when answered" in rig.daemon.supervisor.reason
    # the summary's latency includes the time the frame waited: the stall shows
    assert rig.daemon.summary["latency_us"]["max"] >= 50_000


# ---- 4. 29-bit and remote frames taken as 11-bit ones --------------------------------------
def test_finding4_extended_and_remote_frames_are_not_the_dbc_messages(tmp_path):
    packer = Codec().packer("RIG")
    estop = {
        "ActuatorEnabled": 1,
        "LimitTripped": 0,
        "EStop": 1,
        "SensorFault": 0,
        "Displacement": 0.0,
        "Force": 0.0,
    }
    daemon_values = {
        "Mode": "ACTIVE",
        "CurrentSetpoint": 1.0,
        "SensorCounterEcho": 0,
        "ControllerId": 6,
        "DesiredForce": 0.0,
    }
    command = Codec().packer("DAEMON").encode("DamperCommand", daemon_values)
    with ScriptedRig(tmp_path) as rig:
        # a counter no genuine frame near it has: an answer to it would show
        sensors = packer.encode("RigSensors", estop, counter=(rig.counter + 8) & 0xF)
        rig.exchange()
        for frame in (
            can.Message(arbitration_id=0x110, is_extended_id=True, data=sensors),
            can.Message(arbitration_id=0x210, is_extended_id=True, data=command),
            can.Message(arbitration_id=0x110, is_extended_id=False, is_remote_frame=True, dlc=8),
        ):
            frame.timestamp = time.time()
            rig.bus.send(frame)
            # the next command answers the next genuine frame (exchange checks the echo)
            assert rig.exchange()["Mode"] == ACTIVE
        assert _faults(rig) == []
        assert rig.daemon.counters["frames_ignored"] == 3
        assert rig.daemon.counters["foreign_commands"] == 0


# ---- 7. values that should be refused ------------------------------------------------------
@pytest.mark.parametrize(
    ("loop", "message"),
    [
        ({"bad_frame_budget": -1}, "loop.bad_frame_budget, lost_frame_budget: must be >= 0"),
        ({"budget_window_s": -1.0}, "loop.budget_window_s: must be in (0, 60] s"),
        ({"x_range_m": [-1e9, 1e9]}, "loop.x_range_m: must lie in [-0.5, 0.5] m"),
        ({"f_range_n": [-1e9, 1e9]}, "loop.f_range_n: must lie in [-80000, 80000] N"),
        ({"max_frame_age_s": 0.0}, "loop.max_frame_age_s: must be in (0, 1] s"),
    ],
)
def test_finding7_config_values_out_of_range_are_refused(loop, message):
    with pytest.raises(ConfigError) as err:
        load_config(REPO / "configs/rig.toml", {"loop": loop})
    assert str(err.value) == f"{REPO / 'configs/rig.toml'}: {message}"


@pytest.mark.parametrize(
    ("request_", "error"),
    [
        (
            {"kind": "sine", "amplitude_n": 1e308},
            "reference.amplitude_n: must be in [0, 80000] N",
        ),
        (
            {"kind": "sine", "amplitude_n": 5000.0, "offset_n": 2000.0},
            "amplitude_n: offset_n +- amplitude_n reaches 7000 N, outside loop.f_range_n",
        ),
        ({"kind": "sine", "amplitude_n": float("nan")}, "amplitude_n: not a finite number"),
        ({"kind": "sine", "freq_hz": 1e9}, "reference.freq_hz: must be in (0, 250] Hz"),
    ],
)
def test_finding7_request_values_out_of_range_are_refused(tmp_path, request_, error):
    with ScriptedRig(tmp_path) as rig:
        _disarm(rig)
        reply = rig.request({"cmd": "set_profile", **request_})
        assert not reply["ok"] and reply["error"].startswith(error), reply
        assert rig.daemon.reference.kind == "constant"


def test_finding7_the_actuator_moves_only_a_bounded_step_while_armed(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        start = {"cmd": "actuator", "waveform": "sine", "amplitude_m": 0.01, "frequency_hz": 2}
        _disarm(rig)
        assert rig.request(start)["ok"]
        assert rig.request({"cmd": "arm"})["ok"]
        assert rig.request({**start, "amplitude_m": 0.014})["ok"]  # within 5 mm
        reply = rig.request({**start, "amplitude_m": 0.04})
        assert not reply["ok"] and "armed_amplitude_step_m" in reply["error"], reply
        reply = rig.request({**start, "waveform": "random"})
        assert not reply["ok"] and "only when not armed" in reply["error"], reply
        assert rig.request({"cmd": "actuator", "waveform": "stop"})["ok"]  # always


# ---- 8. replayed or forged frames ----------------------------------------------------------
def test_finding8_a_counter_ahead_of_the_time_since_the_last_frame_is_seen(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        for _ in range(3):
            rig.exchange()
        c = rig.sensors()
        rig.command()
        # a replay of an old frame: valid CRC, its counter 11 ahead, 1 ms after the last one
        replayed = rig.sensors(counter=(c + 12) & 0xF)
        assert rig.command()["SensorCounterEcho"] == replayed  # E2E profile 2 cannot refuse it
        assert rig.daemon.counters["sensor_frames_early"] == 1
        suspect = [e for e in rig.daemon.events if e["kind"] == "suspect_frame"]
        assert len(suspect) == 1 and "advanced 12 in" in suspect[0]["reason"]
