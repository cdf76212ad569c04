"""A rig profile: the lab's DBC and [can.signals] (configs/profiles/lab-1khz.toml, other IDs, mm
and kN, no E2E, 1 kHz), units to SI by the table, the protections that are off named at
start-up, and `mrrig dbc check`: one line per problem, exit 2."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import cantools
import pytest

from mrrig.cli import dbc as dbc_cli
from mrrig.config import load_config
from mrrig.rigio.canbus.profile import ProfileError, check_profile, load_profile, unit_of
from tests.conftest import REPO

PROFILES = REPO / "configs" / "profiles"


def _lab(tmp_path: Path, dbc_edit: tuple[str, str] = ("", ""), toml_edit=("", "")) -> Path:
    """configs/profiles/lab-1khz.{dbc,toml} copied into a folder of their own (the config
    finds its DBC beside it), each with one edit."""
    folder = tmp_path / "lab"
    folder.mkdir()
    for suffix, (old, new) in ((".dbc", dbc_edit), (".toml", toml_edit)):
        text = (PROFILES / f"lab-1khz{suffix}").read_text()
        assert old in text
        (folder / f"lab-1khz{suffix}").write_text(text.replace(old, new, 1) if old else text)
    return folder / "lab-1khz.toml"


def _profile(config: Path):
    cfg = load_config(config)
    return load_profile(cfg.can.dbc, cfg.can.signals, cfg.loop.period_s, cfg.source)


def test_the_lab_profile_reads_mm_and_kn_as_metres_and_newtons(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the DBC is found beside the config, not in the checkout
    profile = _profile(_lab(tmp_path))
    db = cantools.database.load_file(str(PROFILES / "lab-1khz.dbc"))
    msg = db.get_message_by_name("LabSensors")
    frame = msg.encode(
        {"Position": 12.345, "Load": 1.23456, "Enabled": 1, "EStop": 0, "Fault": 0, "Coil": 850}
    )
    parsed = profile.codec.parser().parse(msg.frame_id, frame, 0.0)
    assert parsed.ok and parsed.counter is None
    v = parsed.values
    assert v["Displacement"] == pytest.approx(0.012345)
    assert v["Force"] == pytest.approx(1234.56)
    assert v["CoilCurrent"] == pytest.approx(0.85)
    # the flags the layout lacks read as quiet, and are named off at start-up
    assert (v["LimitTripped"], v["SensorFault"], v["CommandTimeouts"]) == (0.0, 0.0, 0.0)


def test_the_daemons_command_is_packed_in_the_profiles_units(tmp_path):
    profile = _profile(_lab(tmp_path))
    payload = profile.packer().encode(
        "HostCommand",
        {
            "Mode": 1,
            "CurrentSetpoint": 1.2345,
            "SensorCounterEcho": 3,  # roles this layout lacks are left alone
            "ControllerId": 1,
            "DesiredForce": 1200.0,
        },
    )
    db = cantools.database.load_file(str(PROFILES / "lab-1khz.dbc"))
    decoded = db.get_message_by_name("HostCommand").decode(payload)
    assert decoded["Current"] == pytest.approx(1234.5)  # mA
    assert decoded["Force"] == pytest.approx(1.2)  # kN, not 1200 read as newtons
    assert decoded["Active"] == 1


def test_a_fault_flag_is_a_fault_not_the_watchdogs_code_1(tmp_path):
    profile = _profile(_lab(tmp_path))
    values = {"FaultCode": 1.0, "CommandTimeouts": 0.0}
    state, code, label, _ = profile.firmware_status(values)
    # the contract's code 1 is the watchdog's (it does not block arming); a lab's flag is not
    assert (state, code, label) == ("FAULT", -1, "1")


def test_the_start_up_line_names_the_protections_that_are_off(tmp_path, caplog):
    from mrrig.loop.daemon import Daemon

    cfg = load_config(
        _lab(tmp_path),
        {"controller": {"name": "constant", "current_a": 0.5}, "telemetry": {"enabled": False}},
    )
    with caplog.at_level(logging.INFO, "mrrig.loop.daemon"):
        daemon = Daemon(cfg)
    line = next(r for r in caplog.records if "CAN profile" in r.getMessage())
    assert line.levelno == logging.WARNING
    text = line.getMessage()
    for off in ("E2E on LabSensors", "E2E on HostCommand", "the counter echo", "watchdog"):
        assert off in text, text
    assert daemon.packer.messages == ("HostCommand", "HostMotion")


def test_the_contracts_profile_has_every_protection_on():
    profile, problems = check_profile(None, {}, 0.002, "rig.toml")
    assert problems == [] and profile.protections_off == []
    assert profile.codec.layout("RigSensors").e2e


def test_the_daemon_refuses_a_profile_with_its_first_problem_in_one_line(tmp_path):
    config = _lab(tmp_path, ('"mm" HOST', '"in" HOST'))
    with pytest.raises(ProfileError) as err:
        _profile(config)
    assert "LabSensors.Position: unit 'in' not in the unit table" in str(err.value)
    assert "\n" not in str(err.value)


# ---- mrrig dbc check: a test per problem class, one line, exit 2 -----------------------------
@pytest.mark.parametrize(
    ("dbc_edit", "toml_edit", "expected"),
    [
        pytest.param(
            ('"mm" HOST', '"in" HOST'),
            ("", ""),
            "lab-1khz.dbc: LabSensors.Position: unit 'in' not in the unit table (m, mm, um, N,"
            " kN, A, mA, V, degC, Hz, m/s, mm/s)",
            id="unknown unit",
        ),
        pytest.param(
            ("", ""),
            ('force = "LabSensors.Load"\n', ""),
            "can.signals.force: unmapped role, which the loop needs (map it to MESSAGE.SIGNAL"
            " of lab-1khz.dbc)",
            id="unmapped role",
        ),
        pytest.param(
            ("BO_ 770 HostCommand", "BO_ 769 HostCommand"),
            ("", ""),
            "lab-1khz.dbc: ID clash: LabSensors and HostCommand both use 0x301",
            id="ID clash",
        ),
        pytest.param(
            (" SG_ Coil : 51|13@1+", " SG_ Coil : 51|14@1+"),
            ("", ""),
            "lab-1khz.dbc: frame overflow: LabSensors.Coil (14 bits from 51) beyond the frame's"
            " 8 bytes",
            id="frame overflow",
        ),
        pytest.param(
            ("", ""),
            ("period_s = 0.001", "period_s = 0.002"),
            "period mismatch: loop.period_s 0.002 s, but LabSensors's GenMsgCycleTime in"
            " lab-1khz.dbc is 1 ms",
            id="period mismatch",
        ),
    ],
)
def test_dbc_check_names_each_problem_in_one_line(tmp_path, capsys, dbc_edit, toml_edit, expected):
    config = _lab(tmp_path, dbc_edit, toml_edit)
    rc = dbc_cli.main(["check", "--config", str(config)])
    lines = capsys.readouterr().out.splitlines()
    assert rc == 2
    assert len(lines) == 1, lines
    assert lines[0].endswith(expected), lines[0]


def test_dbc_check_passes_both_shipped_profiles(tmp_path, capsys):
    assert dbc_cli.main(["check", "--config", str(PROFILES / "lab-1khz.toml")]) == 0
    assert dbc_cli.main(["check", "--config", str(REPO / "configs" / "rig.toml")]) == 0
    out = capsys.readouterr().out
    assert "protections off" in out and "all on" in out


def test_dbc_show_prints_the_mapping_the_daemon_uses(capsys):
    assert dbc_cli.main(["show", "--config", str(PROFILES / "lab-1khz.toml")]) == 0
    out = capsys.readouterr().out
    assert "force                LabSensors.Load" in out and "kN x 1000" in out
    assert "counter_echo         absent" in out


def test_the_shipped_dbc_files_are_copies_of_nothing_else(tmp_path):
    """The example profile is package data like the contract (mrrig.resources)."""
    from mrrig.resources import shipped

    assert shipped("profiles/lab-1khz.dbc").is_file()
    shutil.copy(shipped("profiles/lab-1khz.dbc"), tmp_path / "x.dbc")
    assert cantools.database.load_file(str(tmp_path / "x.dbc"), strict=True).messages


# ---- the simulator speaks the same profile -------------------------------------------------
def _lab_firmware():
    import dataclasses

    from firmware_sim.config import SensorConfig, SimConfig, load_config
    from firmware_sim.firmware import Firmware

    sim = load_config(PROFILES / "lab-1khz-sim.toml")
    quiet = dataclasses.replace(sim, sensors=SensorConfig(0.0, 0.0, 0.0, 0.02, 5000.0))
    assert isinstance(quiet, SimConfig)
    profile = load_profile(sim.can.dbc, sim.can.signals, None, "lab-1khz-sim.toml")
    return Firmware(quiet, profile), profile


def test_the_simulator_sends_the_lab_layout_at_its_period():
    fw, _ = _lab_firmware()
    db = cantools.database.load_file(str(PROFILES / "lab-1khz.dbc"))
    assert fw.period_s == pytest.approx(0.001)
    frames = [f for k in range(5) for f in fw.tick(k * fw.period_s)]
    # one frame a period, the status roles in it: no RigStatus-like frame of its own
    assert [f.frame_id for f in frames] == [0x301] * 5
    decoded = db.get_message_by_name("LabSensors").decode(frames[-1].data)
    assert decoded["Load"] == pytest.approx(fw.force_n / 1e3, abs=1e-4)  # kN on the wire
    assert decoded["Fault"] == 0
    assert {f.counter for f in frames} == {0, 1, 2, 3, 4}  # its own count: no E2E counter


def test_the_simulator_applies_the_lab_command_in_its_units():
    fw, profile = _lab_firmware()
    for k in range(3):
        for frame in fw.tick(k * fw.period_s):
            fw.sent(frame, k * fw.period_s)
    command = profile.packer().encode(
        "HostCommand", {"Mode": 1, "CurrentSetpoint": 0.75, "DesiredForce": 100.0}
    )
    t_s = 2 * fw.period_s + 0.0003  # on time: the latest frame's answer
    parsed = fw.on_frame(0x302, command, t_s)
    assert parsed is not None and parsed.ok
    assert fw.command_of(parsed.values) == ("ACTIVE", pytest.approx(0.75), 2)
    assert fw.late_commands == 0
    frames = fw.tick(3 * fw.period_s)
    assert fw.coil_command_a == pytest.approx(0.75)
    # a command that comes after the next frame was due is late, by its time alone
    fw.sent(frames[0], 3 * fw.period_s)
    fw.on_frame(0x302, command, 3 * fw.period_s + 0.0015)
    assert fw.late_commands == 1


@pytest.mark.process
@pytest.mark.long
def test_the_demo_on_the_lab_profile_passes_and_names_the_protections_off(tmp_path, sim_model):
    """The daemon and firmware_sim as processes on the lab layout (1 kHz, no E2E, mm and kN)
    through the bridge: the demo's verdict, and the start-up line of each. The simulator's
    config has no [can] of its own (issue 42: it needed a second copy of the table): the demo
    gives it the daemon's (`firmware_sim --rig-config`)."""
    import subprocess
    import sys

    from tests.conftest import zenoh_configs

    zdaemon, zclient, _ = zenoh_configs(tmp_path)
    text = (PROFILES / "lab-1khz.toml").read_text()
    text = text.replace('"configs/zenoh-daemon.json5"', f'"{zdaemon}"')
    text = text.replace('dbc = "lab-1khz.dbc"', f'dbc = "{PROFILES / "lab-1khz.dbc"}"')
    config = tmp_path / "lab.toml"
    config.write_text(text.replace('rig]\nname = "lab"', 'rig]\nname = "lab-test"'))
    sim_text = (PROFILES / "lab-1khz-sim.toml").read_text()
    sim_config = tmp_path / "lab-sim.toml"
    sim_config.write_text(sim_text[: sim_text.index("\n[can]")] + "\n")  # no [can] table
    proc = subprocess.run(
        [sys.executable, "-m", "mrrig", "demo", "--config", str(config), "--model", str(sim_model)]
        + ["--sim-config", str(sim_config), "--zenoh-config", str(zclient)]
        + ["--duration", "8", "--record", str(tmp_path / "lab.rrd")]
        # the operator's re-arming after a transport fault, with room for this VM's stalls (a
        # loaded run of the demo here used the default 3 in 5 s, then stayed in FAULT)
        + ["--max-rearms", "10"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    out = proc.stdout + proc.stderr
    print(out[-4000:])
    assert proc.returncode == 0, out[-3000:]
    assert "demo: PASS" in out
    starts = [
        line for line in out.splitlines() if "CAN profile lab-1khz.dbc: protections off" in line
    ]
    assert len(starts) == 2, starts  # the simulator's and the daemon's
    assert "E2E on LabSensors" in starts[-1] and "the counter echo" in starts[-1]


# ---- issue 42: a lab's first day (roles left out, UTF-8, the usual unit spellings) ----------
def test_roles_left_out_are_absent_and_named_in_one_log_line(tmp_path, caplog, capsys):
    """All 19 roles had to be spelled out, 7 of the lab's as "absent"."""
    config = _lab(tmp_path)
    text = config.read_text()
    absent = [line for line in text.splitlines() if line.split("#")[0].strip().endswith('"absent"')]
    assert len(absent) == 7
    config.write_text("\n".join(x for x in text.splitlines() if x not in absent) + "\n")
    with caplog.at_level(logging.INFO, "mrrig.rigio.canbus.profile"):
        short = _profile(config)
    (tmp_path / "full").mkdir()
    full = _profile(_lab(tmp_path / "full"))
    assert short.mapped == full.mapped and short.protections_off == full.protections_off
    lines = [r.getMessage() for r in caplog.records if "not mapped" in r.getMessage()]
    roles = [line.split(" = ")[0] for line in absent]
    assert lines == [
        f"CAN profile lab-1khz.dbc: not mapped in [can.signals], so absent: {', '.join(roles)}"
    ]
    assert full.unmapped_line() is None
    assert dbc_cli.main(["check", "--config", str(config)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-1] == lines[0]


@pytest.mark.parametrize(
    ("unit", "si"),
    [
        ("N", ("force", 1.0)),
        ("Newton", ("force", 1.0)),
        ("newtons", ("force", 1.0)),
        ("kilonewtons", ("force", 1e3)),
        ("mm", ("length", 1e-3)),
        ("millimetres", ("length", 1e-3)),
        ("m", ("length", 1.0)),
        ("Meter", ("length", 1.0)),
        ("µm", ("length", 1e-6)),
        ("°C", ("temperature", 1.0)),
        ("deg C", ("temperature", 1.0)),
        ("Celsius", ("temperature", 1.0)),
        ("mA", ("current", 1e-3)),
        ("Amps", ("current", 1.0)),
        ("hertz", ("frequency", 1.0)),
        (" V ", ("voltage", 1.0)),
        ("MA", None),  # mega-amperes are not milliamperes: symbols keep their case
        ("in", None),
        ("s", None),
    ],
)
def test_the_unit_table_takes_the_usual_spellings(unit, si):
    assert unit_of(unit) == si


@pytest.mark.parametrize("encoding", ["utf-8", "cp1252"])
def test_a_dbc_with_degrees_celsius_and_newton_reads_in_either_encoding(tmp_path, encoding):
    """A UTF-8 `°C` was read as Latin-1 (`Â°C`) and refused, and so was `Newton`."""
    text = (REPO / "mrrig" / "configs" / "mrrig.dbc").read_text(encoding="utf-8")
    for old, new in (
        ('(0.01,0) [-327.68|327.67] "degC"', '(0.01,0) [-327.68|327.67] "°C"'),
        ('[-83886.08|83886.07] "N" DAEMON', '[-83886.08|83886.07] "Newton" DAEMON'),
    ):
        assert text.count(old) == 1
        text = text.replace(old, new)
    dbc = tmp_path / "lab.dbc"
    dbc.write_bytes(text.encode(encoding))
    profile, problems = check_profile(dbc, {}, 0.002, "lab.toml")
    assert problems == []
    temperature, force = profile.mapped["damper_temperature"], profile.mapped["force"]
    assert (temperature.unit, temperature.factor) == ("°C", 1.0)
    assert (force.unit, force.factor) == ("Newton", 1.0)
