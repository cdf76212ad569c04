"""Rig profiles that only look right (issue 40, findings 4 and 11): `mrrig dbc check`, the
daemon's and firmware_sim's start-up refuse a signal that cannot carry its limit (a command
current below loop.i_max_a, a force in kN declared as N), an actuator message without its
waveform, a scale of 0 or an offset of 1e308, each in one line naming the file, the message,
the signal and the numbers, exit 2; and a send the profile cannot encode faults the daemon
SAFE (and the simulator) instead of ending it."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import cantools
import pytest

from mrrig.cli import dbc as dbc_cli
from mrrig.config import load_config
from mrrig.loop.daemon import Daemon
from mrrig.loop.safety import Fault
from mrrig.loop.samples import RigState
from mrrig.rigio.canbus.codec import Codec, CodecError, EncodeError
from mrrig.rigio.canbus.profile import ProfileError, load_profile
from tests.conftest import REPO
from tests.rig_harness import ScriptedRig

PROFILES = REPO / "configs" / "profiles"
CONTRACT_DBC = REPO / "configs" / "mrrig.dbc"

NARROW_CURRENT = (
    " SG_ Current : 8|16@1+ (0.1,0) [0|5000]",
    " SG_ Current : 8|8@1+ (1,0) [0|255]",  # 255 mA: the lab's 2 A does not fit
)
KN_AS_N = ('[-80|80] "kN" HOST', '[-80|80] "N" HOST')  # the load cell in kN, declared as N
NO_WAVEFORM = ('actuator_waveform = "HostMotion.Waveform"', 'actuator_waveform = "absent"')


def _lab(tmp_path: Path, dbc_edit=("", ""), toml_edit=("", ""), sim=False) -> Path:
    """The example lab profile (the daemon's config, or the simulator's) with one edit each to
    its DBC and its config, in a folder of its own."""
    folder = tmp_path / "lab"
    folder.mkdir(exist_ok=True)
    name = "lab-1khz-sim.toml" if sim else "lab-1khz.toml"
    for file, (old, new) in (("lab-1khz.dbc", dbc_edit), (name, toml_edit)):
        text = (PROFILES / file).read_text()
        assert old in text
        (folder / file).write_text(text.replace(old, new) if old else text)
    return folder / name


def _check(config: Path, capsys) -> tuple[int, list[str]]:
    rc = dbc_cli.main(["check", "--config", str(config)])
    return rc, capsys.readouterr().out.splitlines()


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True, timeout=120
    )


def _one_error_line(proc: subprocess.CompletedProcess) -> str:
    """The process's one error line (no traceback)."""
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if "error" in line.lower()]
    assert len(lines) == 1, proc.stderr
    return lines[0]


# ---- (a) a command signal that cannot carry i_max_a ----------------------------------------
def test_dbc_check_refuses_a_command_current_below_i_max(tmp_path, capsys):
    rc, lines = _check(_lab(tmp_path, NARROW_CURRENT), capsys)
    assert rc == 2
    assert lines == [
        "lab-1khz.dbc: HostCommand.Current (command_setpoint) carries [0, 0.255] A, but"
        f" {tmp_path / 'lab' / 'lab-1khz.toml'}'s loop.i_max_a needs [0, 2] A"
    ]


def test_the_daemon_refuses_a_command_current_below_i_max_at_start_up(tmp_path):
    config = _lab(tmp_path, NARROW_CURRENT)
    with pytest.raises(ProfileError, match=r"HostCommand.Current .* loop.i_max_a needs \[0, 2\]"):
        Daemon(load_config(config, {"telemetry": {"enabled": False}}))
    proc = _run("mrrig", "run", "--config", str(config), "--no-telemetry", "--no-record")
    assert proc.returncode == 2, proc.stderr
    assert "HostCommand.Current (command_setpoint) carries [0, 0.255] A" in _one_error_line(proc)


# ---- (c) a force signal a thousandth of f_range_n (kN declared as N) ------------------------
def test_dbc_check_refuses_kilonewtons_declared_as_newtons(tmp_path, capsys):
    rc, lines = _check(_lab(tmp_path, KN_AS_N), capsys)
    assert rc == 2
    source = tmp_path / "lab" / "lab-1khz.toml"
    assert lines == [
        f"lab-1khz.dbc: LabSensors.Load (force) carries [-80, 80] N, but {source}'s"
        " loop.f_range_n needs [-6000, 6000] N"
    ]


def test_the_daemon_refuses_kilonewtons_declared_as_newtons(tmp_path):
    cfg = load_config(_lab(tmp_path, KN_AS_N), {"telemetry": {"enabled": False}})
    with pytest.raises(ProfileError, match=r"LabSensors.Load \(force\) carries \[-80, 80\] N"):
        Daemon(cfg)


def test_a_signal_that_covers_its_limit_to_half_a_step_passes(tmp_path, capsys):
    """The limit's ends need only round onto the signal's ends: [0|2] A in 0.1 mA steps
    carries i_max_a 2 A exactly, as [-6|6] kN carries f_range_n."""
    edit = (NARROW_CURRENT[0], " SG_ Current : 8|16@1+ (0.1,0) [0|2000]")
    rc, lines = _check(_lab(tmp_path, edit, ("x_range_m = [-0.045", "x_range_m = [-0.05")), capsys)
    assert rc == 0, lines


# ---- (b) an actuator message without its waveform ------------------------------------------
def test_dbc_check_refuses_an_actuator_message_without_its_waveform(tmp_path, capsys):
    rc, lines = _check(_lab(tmp_path, toml_edit=NO_WAVEFORM), capsys)
    assert rc == 2
    assert lines == [
        f"{tmp_path / 'lab' / 'lab-1khz.toml'}: can.signals: HostMotion carries the actuator's"
        " command without actuator_waveform (map each, or declare every actuator_* role"
        ' "absent")'
    ]


def test_firmware_sim_refuses_an_actuator_message_without_its_waveform(tmp_path):
    config = _lab(tmp_path, toml_edit=NO_WAVEFORM, sim=True)
    proc = _run("firmware_sim", "--config", str(config), "--duration", "0.1")
    assert proc.returncode == 2, proc.stderr
    assert "HostMotion carries the actuator's command without actuator_waveform" in (
        _one_error_line(proc)
    )


def test_firmware_sim_refuses_a_displacement_that_cannot_carry_its_stroke(tmp_path):
    config = _lab(tmp_path, toml_edit=("stroke_m = 0.04", "stroke_m = 0.06"), sim=True)
    proc = _run("firmware_sim", "--config", str(config), "--duration", "0.1")
    assert proc.returncode == 2, proc.stderr
    assert "LabSensors.Position (displacement) carries [-0.05, 0.05] m, but" in _one_error_line(
        proc
    )
    assert "actuator.stroke_m needs [-0.06, 0.06] m" in proc.stderr


def test_both_shipped_profiles_carry_their_limits(capsys):
    for config in (PROFILES / "lab-1khz.toml", REPO / "configs" / "rig.toml"):
        rc, lines = _check(config, capsys)
        assert rc == 0, lines
    # the simulator's, with its limits, as firmware_sim loads them
    from firmware_sim.config import load_config as load_sim
    from mrrig.rigio.canbus.profile_limits import firmware_limits

    for path in (PROFILES / "lab-1khz-sim.toml", REPO / "configs" / "sim.toml"):
        c = load_sim(path)
        limits = firmware_limits(c.actuator.stroke_m)
        assert load_profile(c.can.dbc, c.can.signals, None, str(path), limits).mapped


# ---- 11: a scale of 0, an offset of 1e308 ----------------------------------------------------
@pytest.mark.parametrize(
    ("scaling", "why"),
    [
        ("(0,0)", "scale 0 (a signal needs a finite, non-zero scale)"),
        ("(0.001,1E308)", "offset 1e+308 leaves its scale 0.001 below the float resolution"),
        ("(1E305,0)", "24 bits with scale 1e+305 and offset 0 overflow a float"),
    ],
)
def test_a_scaling_that_cannot_be_computed_is_one_line_exit_2(tmp_path, scaling, why):
    config = _lab(
        tmp_path, (" SG_ Position : 0|24@1- (0.001,0)", f" SG_ Position : 0|24@1- {scaling}")
    )
    if scaling == "(1E305,0)":  # its [min|max] would overflow first: none
        text = (config.parent / "lab-1khz.dbc").read_text()
        (config.parent / "lab-1khz.dbc").write_text(text.replace("[-50|50]", "[0|0]"))
    expected = f"lab-1khz.dbc: LabSensors.Position: {why}"
    proc = _run("mrrig", "dbc", "check", "--config", str(config))
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.stdout.splitlines() == [expected]
    # the daemon's start-up, the same line
    run = _run("mrrig", "run", "--config", str(config), "--no-telemetry", "--no-record")
    assert run.returncode == 2, run.stderr
    assert expected in _one_error_line(run)
    # and the codec on its own, naming the file
    with pytest.raises(CodecError) as err:
        Codec(config.parent / "lab-1khz.dbc")
    assert str(err.value) == expected


# ---- a send the profile cannot encode faults SAFE; the loop goes on --------------------------
def test_a_command_the_profile_cannot_encode_faults_safe_and_the_loop_goes_on(tmp_path):
    """On a python-can bus, the daemon armed at 1.25 A with a DamperCommand whose current
    signal stops at 0.5 A (a profile loaded without the start-up check): the ACTIVE command
    cannot be encoded; the daemon faults (BUS_ERROR, naming the signal), answers the frame
    SAFE and answers every frame after it, SAFE."""
    narrow = tmp_path / "narrow.dbc"
    text = CONTRACT_DBC.read_text()
    old = ' SG_ CurrentSetpoint : 16|16@1+ (0.0001,0) [0|6.5535] "A"'
    assert old in text
    narrow.write_text(text.replace(old, old.replace("6.5535", "0.5")))
    profile = load_profile(narrow, {}, None, "test")  # no limits: encoding raises at send
    with pytest.raises(EncodeError):
        profile.packer().encode("DamperCommand", {"Mode": 1, "CurrentSetpoint": 1.25})
    with ScriptedRig(tmp_path) as rig:
        rig.daemon.packer = profile.packer()
        cmd = rig.exchange()
        assert (cmd["Mode"], cmd["CurrentSetpoint"]) == (0, 0.0)  # SAFE, for this very frame
        assert rig.daemon.counters["safe_commands_unprompted"] == 0  # not the sensor timeout's
        assert rig.daemon.supervisor.state is RigState.FAULT
        assert rig.daemon.supervisor.fault is Fault.BUS_ERROR
        assert "CurrentSetpoint=1.25 outside [0, 0.5]" in rig.daemon.supervisor.reason
        for _ in range(20):  # the loop goes on, in FAULT, every frame answered SAFE
            assert rig.exchange()["Mode"] == 0
        assert rig.thread.is_alive()
        assert rig.daemon.counters["send_failures"] == 1


# ---- the simulator: a frame it cannot encode faults it, not the process ----------------------
def test_a_sensor_frame_the_profile_cannot_encode_faults_the_simulator(tmp_path):
    from firmware_sim.config import FaultSpec, SensorConfig
    from firmware_sim.config import load_config as load_sim
    from firmware_sim.firmware import Firmware

    path = PROFILES / "lab-1khz-sim.toml"
    sim = load_sim(path)
    # a spike beyond LabSensors.Position's 50 mm, for the frames of 2 to 4 ms
    sim = dataclasses.replace(sim, sensors=SensorConfig(0.0, 0.0, 0.0, 0.06, 0.0))
    profile = load_profile(sim.can.dbc, sim.can.signals, None, str(path))
    fw = Firmware(sim, profile, (FaultSpec("sensor_spike", 0.002, 0.002),))
    db = cantools.database.load_file(str(PROFILES / "lab-1khz.dbc"))
    lab = db.get_message_by_name("LabSensors")
    sent = [fw.tick(k * fw.period_s) for k in range(8)]
    assert [len(f) for f in sent] == [1, 1, 0, 0, 1, 1, 1, 1]  # not sent while it cannot be
    assert fw.unsendable is not None and "Displacement=0.06" in fw.unsendable
    assert (fw.state, fw.fault_code, fw.coil_command_a) == ("FAULT", "SENSOR_FAULT", 0.0)
    after = lab.decode(sent[4][0].data)
    assert after["Fault"] == 1  # the next frame it can send says so
    command = profile.packer()
    for k in range(8, 14):  # valid SAFE commands clear it once its frames encode again
        for frame in fw.tick(k * fw.period_s):
            fw.sent(frame, k * fw.period_s)
        fw.on_frame(0x302, command.encode("HostCommand", {"Mode": 0}), k * fw.period_s + 1e-4)
    assert fw.unsendable is None and fw.state != "FAULT"
