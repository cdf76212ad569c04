"""Issue 32 (hostile input, round two), findings 14, 15 and 16: a daemon that never hears its
rig faults `no_sensor_frames`; a FAULT needs `reset` before `arm`; error detectors for the
tracking error, the velocity and the damper's temperature, each with its action.

In-process rigs on python-can's virtual bus (tests/rig_harness.py), the sidecar's audit on a
real Zenoh session; the process test with the simulator on a DBC of other IDs is
tests/test_interlocks_other_dbc.py.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import pytest

from mrrig.config import load_config
from mrrig.loop.detectors import Detector, Detectors, DetectorSettings
from mrrig.loop.safety import Fault
from mrrig.loop.samples import RigState
from mrrig.rigio.control import Pending
from mrrig.rigio.rig_topics import keys
from mrrig.typed_config import ConfigError
from tests.conftest import REPO
from tests.rig_harness import ScriptedRig, write_config
from tests.test_sidecar import RIG, _answer_one_request, _collect, running_sidecar

SAFE, ACTIVE = 0, 1
STOP_WAVEFORM = 0  # ActuatorCommand Waveform STOP


def _wait(pred, timeout_s: float = 2.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.002)
    return False


def _faults(rig: ScriptedRig) -> list[dict]:
    return [e for e in rig.daemon.events if e["kind"] == "fault"]


def _ask(rig: ScriptedRig, req: dict) -> dict:
    """A request answered by the loop without sensor frames (it applies one every recv
    timeout)."""
    pending = Pending()
    rig.daemon.submit(req, pending)
    return pending.wait(3.0)


# ---- finding 14: no valid sensor frame ----------------------------------------------------
def test_finding14_a_bus_of_other_ids_faults_no_sensor_frames_naming_them(tmp_path):
    """A rig on a DBC of other IDs: 0 valid sensor frames, frames_ignored counting, faults 0.
    Now: no_sensor_frames within the sensor timeout of the bus's first frame, naming the IDs
    and how many frames; arming at start does not happen."""
    with ScriptedRig(tmp_path) as rig:  # a 100 ms sensor timeout, arm_on_start
        for _ in range(100):  # 200 ms of a foreign rig's two messages
            rig.bus.send(can.Message(arbitration_id=0x510, is_extended_id=False, data=bytes(8)))
            rig.bus.send(can.Message(arbitration_id=0x511, is_extended_id=False, data=bytes(8)))
            time.sleep(0.002)
        assert _wait(lambda: _faults(rig))
        fault = _faults(rig)[0]
        assert fault["fault"] == Fault.NO_SENSOR_FRAMES.value, fault
        assert "0x510 x" in fault["reason"] and "0x511 x" in fault["reason"], fault["reason"]
        assert "no valid RigSensors frame (0x110) within 100 ms" in fault["reason"]
        n = int(re.search(r"carried (\d+) other frames", fault["reason"])[1])
        assert 50 <= n <= 200, fault["reason"]
        # the rig that then appears is answered SAFE: the fault stands until a reset
        assert rig.exchange()["Mode"] == SAFE
        assert rig.daemon.supervisor.state is RigState.FAULT


def test_finding14_an_arm_without_sensor_frames_faults_within_the_sensor_timeout(tmp_path):
    """A silent bus (a rig not streaming yet) is no fault by itself; an arm on it is, one
    sensor timeout later."""
    with ScriptedRig(tmp_path, timeout_periods=10) as rig:
        time.sleep(0.1)
        assert rig.daemon.supervisor.state is RigState.IDLE
        assert _ask(rig, {"cmd": "arm"})["ok"]
        t_armed = time.monotonic()
        assert _wait(lambda: _faults(rig), 1.0)
        waited = time.monotonic() - t_armed
        fault = _faults(rig)[0]
        assert fault["fault"] == Fault.NO_SENSOR_FRAMES.value
        assert "within 20 ms of arming; the bus carried no frames at all" in fault["reason"]
        assert waited < 0.5


def test_finding14_an_arm_at_start_on_a_bus_that_never_carried_a_frame_ends_in_fault(tmp_path):
    """`--arm` (arm_on_start) and not one frame in the whole run: exit code 1, not 0."""
    rig = ScriptedRig(tmp_path)
    with rig:
        time.sleep(0.2)
        assert rig.daemon.supervisor.state is RigState.IDLE  # silent: no fault while it runs
    fault = _faults(rig)[0]
    assert fault["fault"] == Fault.NO_SENSOR_FRAMES.value
    assert re.search(r"in the whole run \([\d.]+ s\); the bus carried no frames at all", (
        fault["reason"]
    )), fault["reason"]  # fmt: skip
    assert rig.daemon.exit_code == 1


# ---- finding 15: reset before arm ---------------------------------------------------------
def test_finding15_a_fault_needs_reset_before_arm(tmp_path):
    """A sensor_timeout tripped while IDLE; the next arm armed the rig ('armed (was FAULT)' in
    the log only). Now arm is refused with one line saying to reset; disarm does not clear
    the fault either; reset does, with an event naming what it acknowledged."""
    over = {"loop": {"arm_on_start": False}}
    with ScriptedRig(tmp_path, overrides=over) as rig:  # a 100 ms sensor timeout
        rig.exchange()
        assert _wait(lambda: _faults(rig), 1.0)  # no more frames: sensor_timeout while IDLE
        assert _faults(rig)[0]["fault"] == Fault.SENSOR_TIMEOUT.value
        refused = _ask(rig, {"cmd": "arm"})
        assert not refused["ok"]
        assert refused["error"].startswith("cannot arm: in FAULT (sensor_timeout: no sensor")
        assert "acknowledge it with reset first (mrrig reset --rig NAME)" in refused["error"]
        assert "\n" not in refused["error"]
        assert _ask(rig, {"cmd": "disarm"})["ok"]
        assert rig.daemon.supervisor.state is RigState.FAULT  # a disarm acknowledges nothing
        reply = _ask(rig, {"cmd": "reset"})
        assert reply == {"ok": True, "state": "IDLE", "message": "reset"}
        texts = [e["text"] for e in rig.daemon.events]
        assert any(
            t.startswith("state: fault acknowledged by reset: sensor_timeout") for t in texts
        )
        assert _ask(rig, {"cmd": "reset"})["message"] == "nothing to reset: IDLE"
        assert rig.request({"cmd": "arm"})["ok"]
        assert rig.exchange()["Mode"] == ACTIVE


def test_finding15_mrrig_reset_is_a_control_request_audited_like_every_other(tmp_path: Path):
    """`mrrig reset --rig NAME` (the client API's `reset`) goes through the sidecar's control
    queryable to the loop, and is audited with its requester."""
    with running_sidecar(tmp_path) as r:
        events = r.observer.declare_subscriber(keys(RIG)["events"])
        time.sleep(0.2)
        seen: list[dict] = []
        player = threading.Thread(target=_answer_one_request, args=(r.loop, seen))
        player.start()
        cli = subprocess.run(
            [sys.executable, "-m", "mrrig", "reset", "--rig", RIG, "--zenoh-config",
             str(tmp_path / "zenoh-client.json5"), "--timeout", "10"],
            capture_output=True, text=True, cwd=REPO, timeout=60,
        )  # fmt: skip
        player.join()
        audits = [e for e in _collect(events, 1) if e["kind"] == "audit"]
        events.undeclare()
    assert cli.returncode == 0, cli.stderr[-2000:]
    assert json.loads(cli.stdout)["ok"] is True
    assert seen[0]["cmd"] == "reset"
    assert audits[0]["request"] == {"cmd": "reset"} and audits[0]["result"]["ok"] is True
    assert "control reset from" in audits[0]["text"]


# ---- finding 16: error detectors ----------------------------------------------------------
def test_finding16_a_detector_acts_once_per_episode_after_its_hold_time():
    d = Detectors(DetectorSettings(tracking_error=Detector(100.0, "warn", 0.01)))
    nan = float("nan")
    assert d.check(0.000, 300.0, 0.0, 0.0, nan) == []  # above, not yet held
    found = d.check(0.010, 300.0, 0.0, 0.0, nan)
    assert [x.name for x in found] == ["tracking_error"] and found[0].value == 300.0
    assert "tracking error |f_meas - f_des| 300.0 N above 100 N for 10 ms" in found[0].text
    assert d.check(0.020, 300.0, 0.0, 0.0, nan) == []  # the same episode
    assert d.check(0.030, 50.0, 0.0, 0.0, nan) == []  # under: the episode ends
    d.check(0.040, 300.0, 0.0, 0.0, nan)
    assert [x.name for x in d.check(0.050, 300.0, 0.0, 0.0, nan)] == ["tracking_error"]


def _status(rig: ScriptedRig, temp_degc: float) -> None:
    values = {
        "State": "RUNNING",
        "CoilCurrent": 0.5,
        "DamperTemperature": temp_degc,
        "FaultCode": 0,
        "CommandTimeouts": 0,
    }
    msg = rig.packer.message("RigStatus", values)
    msg.timestamp = time.time()
    rig.bus.send(msg)


def test_finding16_warn_is_an_event_once_and_the_rig_stays_armed(tmp_path):
    """Tracking error (the default action): the constant reference is 300 N, the load cell
    reads 2000 N for 0.6 s, then the rig stays armed with one warning."""
    with ScriptedRig(tmp_path) as rig:
        assert rig.exchange()["Mode"] == ACTIVE
        end = time.monotonic() + 0.7
        while time.monotonic() < end:
            assert rig.exchange(force=2000.0)["Mode"] == ACTIVE
            time.sleep(0.002)
        warns = [e for e in rig.daemon.events if e["kind"] == "detector"]
        assert len(warns) == 1, warns
        assert warns[0]["level"] == "warning"
        assert (
            "detector tracking_error: tracking error |f_meas - f_des| 1700.0 N"
            in (warns[0]["reason"])
        )
        assert rig.daemon.supervisor.state is RigState.ARMED


def test_finding16_temperature_disarms_to_safe_with_a_fault_naming_it(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        assert rig.exchange()["Mode"] == ACTIVE
        _status(rig, 99.0)  # under the default 100 degC
        for _ in range(5):
            assert rig.exchange()["Mode"] == ACTIVE
        _status(rig, 120.5)
        assert _wait(lambda: rig.exchange()["Mode"] == SAFE)
        fault = _faults(rig)[0]
        assert fault["fault"] == Fault.OVER_TEMPERATURE.value
        assert fault["reason"] == (
            "detector temperature: damper temperature 120.5 degC above 100 degC (action disarm)"
        )
        assert not _ask(rig, {"cmd": "arm"})["ok"]  # a fault like any other: reset first


def test_finding16_velocity_disarms_after_its_hold_time(tmp_path):
    """The estimate's |xd| above 1 m/s for 5 ms: a triangle of 4 mm a period (2 m/s)."""
    over = {"detectors": {"velocity": {"threshold": 1.0, "action": "disarm", "hold_s": 0.005}}}
    with ScriptedRig(tmp_path, overrides=over) as rig:
        assert rig.exchange(x=-0.04)["Mode"] == ACTIVE
        x, step = -0.04, 0.004
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            if abs(x + step) > 0.04:
                step = -step
            x += step
            if rig.exchange(x=x)["Mode"] == SAFE:
                break
            time.sleep(0.001)
        fault = _faults(rig)[0]
        assert fault["fault"] == Fault.OVER_VELOCITY.value, fault
        assert re.match(r"detector velocity: velocity \|xd\| [\d.]+ m/s above 1 m/s for \d+ ms", (
            fault["reason"]
        )), fault["reason"]  # fmt: skip


def test_finding16_stop_disarms_and_stops_the_actuator(tmp_path):
    over = {
        "detectors": {"temperature": {"threshold": 80.0, "action": "stop"}},
        "actuator": {"waveform": "sine", "amplitude_m": 0.01, "frequency_hz": 2.0},
    }
    with ScriptedRig(tmp_path, overrides=over) as rig:
        assert rig.exchange()["Mode"] == ACTIVE
        _status(rig, 85.0)
        assert _wait(lambda: rig.exchange()["Mode"] == SAFE)
        assert _faults(rig)[0]["fault"] == Fault.OVER_TEMPERATURE.value
        assert "(action stop)" in _faults(rig)[0]["reason"]
        end = time.monotonic() + 1.0
        waveform = None
        while time.monotonic() < end and waveform != STOP_WAVEFORM:
            msg = rig.bus.recv(timeout=0.2)
            if msg is not None and msg.arbitration_id == 0x211:
                waveform = rig.parser.parse(msg.arbitration_id, msg.data, 0.0).values["Waveform"]
        assert waveform == STOP_WAVEFORM
        assert rig.daemon.actuator.waveform == "stop"


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        ("[detectors.velocity]\nthreshold = 0\n",
         "detectors.velocity.threshold: must be in (0, 10]"),
        ("[detectors.temperature]\nthreshold = 100\naction = \"shout\"\n",
         "detectors.temperature.action: expected one of 'warn', 'disarm', 'stop', got 'shout'"),
        ("[detectors.tracking_error]\nthreshold = 100\nhold_s = 60\n",
         "detectors.tracking_error.hold_s: must be in [0, 10] s"),
        ("[detectors.velocity]\naction = \"warn\"\n",
         "detectors.velocity.threshold: missing required field"),
    ],
)  # fmt: skip
def test_finding16_detector_settings_are_checked_at_load(tmp_path, toml, message):
    path = write_config(tmp_path, "unused", 3)
    path.write_text(path.read_text() + toml)
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert str(exc.value).startswith(f"{path}: ") and message in str(exc.value), exc.value
