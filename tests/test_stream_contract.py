"""Contract 1.1 on the daemon's side: the rig profile's `actuator_setpoint` role, a profile of
contract 1.0 refusing the STREAM waveform in one line (the daemon's config, an `actuator`
request), and `SetpointStream`, the one ActuatorSetpoint per sensor frame the HIL loop sends."""

from __future__ import annotations

import math

import cantools
import numpy as np
import pytest

from firmware_sim.firmware import Firmware
from mrrig.config import load_config
from mrrig.loop.build import build_controller, build_reference
from mrrig.loop.daemon import Daemon
from mrrig.rigio.canbus.profile import ProfileError, check_profile, contract_profile
from mrrig.rigio.canbus.profile_limits import daemon_limits
from mrrig.rigio.canbus.setpoint import SetpointError, SetpointStream
from mrrig.rigio.control import Preparer, RequestError
from tests.conftest import REPO, rig_config
from tests.test_firmware import QUIET, T
from tests.test_rig_profile import PROFILES, _lab, _profile

NO_TELEMETRY = {
    "controller": {"name": "constant", "current_a": 0.5},
    "telemetry": {"enabled": False},
}
STREAM = {"cmd": "actuator", "waveform": "stream", "amplitude_m": 0.02}


def _daemon(config, **overrides) -> Daemon:
    return Daemon(load_config(config, {**NO_TELEMETRY, **overrides}))


def _preparer(daemon: Daemon) -> Preparer:
    return Preparer(daemon, build_controller, build_reference)


# ---- the profile -------------------------------------------------------------------------
def test_the_contracts_profile_maps_the_setpoint_roles():
    profile = contract_profile()
    assert profile.setpoint_message == "ActuatorSetpoint"
    assert {r: profile.mapped[r].signal for r in ("actuator_setpoint", "setpoint_velocity")} == {
        "actuator_setpoint": "PositionSetpoint",
        "setpoint_velocity": "VelocityFeedforward",
    }
    assert profile.stream_refusal() is None
    assert "ActuatorSetpoint" in profile.packer().messages
    assert profile.protections_off == []


def test_a_profile_of_contract_1_0_loads_as_it_did_and_refuses_stream_in_one_line(tmp_path):
    config = _lab(tmp_path)  # lab-1khz.toml names no role of contract 1.1
    profile = _profile(config)
    assert profile.setpoint_message is None and "actuator_setpoint" not in profile.mapped
    why = profile.stream_refusal()
    assert why is not None and "\n" not in why
    assert str(config) in why and "lab-1khz.dbc" in why and "actuator_setpoint" in why


def test_a_daemon_config_asking_stream_of_a_1_0_profile_is_refused_in_one_line(tmp_path):
    config = _lab(tmp_path)
    with pytest.raises(ProfileError) as err:
        _daemon(config, actuator={"waveform": "stream", "amplitude_m": 0.02, "frequency_hz": 0.0})
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith(f"waveform stream: the rig profile of {config} (lab-1khz.dbc)")
    assert "actuator_setpoint" in text


def test_an_actuator_stream_request_is_refused_by_a_1_0_profile_and_taken_by_1_1(tmp_path):
    lab = _daemon(_lab(tmp_path))
    with pytest.raises(RequestError) as err:
        _preparer(lab).prepare(STREAM)
    assert "\n" not in str(err.value) and "actuator_setpoint" in str(err.value)
    contract = _daemon(rig_config(tmp_path, "unused", None))
    change = _preparer(contract).prepare(STREAM)
    assert change.actuator.waveform == "stream" and change.actuator.amplitude_m == 0.02


@pytest.mark.parametrize(
    ("request_", "error"),
    [
        ({"frequency_hz": 2.0}, "frequency_hz: must be 0 for stream"),
        ({"amplitude_m": 0.0}, "amplitude_m: stream needs its envelope"),
    ],
)
def test_a_stream_request_carries_its_envelope_and_no_frequency(tmp_path, request_, error):
    daemon = _daemon(rig_config(tmp_path, "unused", None))
    with pytest.raises(RequestError) as err:
        _preparer(daemon).prepare({**STREAM, **request_})
    assert error in str(err.value)


@pytest.mark.parametrize(
    ("dbc_edit", "toml_edit", "expected"),
    [
        pytest.param(
            ("", ""),
            (
                'actuator_frequency = "HostMotion.Frequency"\n',
                'actuator_frequency = "HostMotion'
                '.Frequency"\nactuator_setpoint = "HostMotion.Amplitude"\n',
            ),
            "can.signals.actuator_setpoint: HostMotion carries the actuator too (the setpoint"
            " goes once per sensor frame, in a message of its own)",
            id="setpoint in the actuator's message",
        ),
        pytest.param(
            (
                "BO_ 771 HostMotion: 8 HOST",
                'BO_ 772 HostSetpoint: 8 HOST\n SG_ Target : 0|24@1- (0.001,0) [-50|50] "mm"'
                " LABRIG\n\nBO_ 771 HostMotion: 8 HOST",
            ),
            (
                'actuator_frequency = "HostMotion.Frequency"\n',
                'actuator_frequency = "HostMotion.Frequency"\n'
                'actuator_setpoint = "HostSetpoint.Target"\n',
            ),
            "lab-1khz.dbc: HostMotion.Waveform: value table lacks STREAM (actuator_setpoint"
            " streams)",
            id="no STREAM in the waveform table",
        ),
        pytest.param(
            (
                "BO_ 771 HostMotion: 8 HOST",
                'BO_ 772 HostSetpoint: 8 HOST\n SG_ Rate : 0|16@1- (1,0) [-1000|1000] "mm/s"'
                " LABRIG\n\nBO_ 771 HostMotion: 8 HOST",
            ),
            (
                'actuator_frequency = "HostMotion.Frequency"\n',
                'actuator_frequency = "HostMotion.Frequency"\n'
                'setpoint_velocity = "HostSetpoint.Rate"\n',
            ),
            "can.signals: HostSetpoint carries the setpoint's velocity or echo without"
            ' actuator_setpoint (map it, or declare every setpoint role "absent")',
            id="a velocity without its setpoint",
        ),
    ],
)
def test_a_setpoint_role_the_layout_cannot_stream_with_is_named(
    tmp_path, dbc_edit, toml_edit, expected
):
    cfg = load_config(_lab(tmp_path, dbc_edit, toml_edit))
    profile, problems = check_profile(cfg.can.dbc, cfg.can.signals, cfg.loop.period_s, cfg.source)
    assert profile is None
    assert len(problems) == 1 and problems[0].endswith(expected), problems


def _lab_streaming(tmp_path, target_mm: float = 50.0):
    """lab-1khz with a setpoint message of its own (HostSetpoint.Target, mm, no echo) and
    STREAM in its waveform table."""
    dbc = (PROFILES / "lab-1khz.dbc").read_text()
    dbc = dbc.replace(
        "BO_ 771 HostMotion: 8 HOST",
        "BO_ 772 HostSetpoint: 8 HOST\n SG_ Target :"
        f' 0|24@1- (0.001,0) [-{target_mm:g}|{target_mm:g}] "mm" LABRIG\n\n'
        "BO_ 771 HostMotion: 8 HOST",
    )
    dbc = dbc.replace('VAL_ 771 Waveform 3 "HOLD"', 'VAL_ 771 Waveform 4 "STREAM" 3 "HOLD"')
    dbc = dbc.replace("SG_ Waveform : 0|4@1+ (1,0) [0|3]", "SG_ Waveform : 0|4@1+ (1,0) [0|4]")
    config = _lab(
        tmp_path,
        toml_edit=(
            'actuator_frequency = "HostMotion.Frequency"\n',
            'actuator_frequency = "HostMotion.Frequency"\n'
            'actuator_setpoint = "HostSetpoint.Target"\n'
            'setpoint_velocity = "absent"\nsetpoint_counter_echo = "absent"\n',
        ),
    )
    (config.parent / "lab-1khz.dbc").write_text(dbc)
    return config


def test_a_lab_setpoint_in_mm_streams_in_metres(tmp_path):
    config = _lab_streaming(tmp_path)
    profile = _profile(config)
    assert profile.stream_refusal() is None
    assert "the setpoint's counter echo (late setpoints)" in profile.protections_off
    msg = SetpointStream(profile, profile.packer(), 0.02).message(3, 0.012345, 0.1)
    decoded = cantools.database.load_file(str(config.parent / "lab-1khz.dbc")).decode_message(
        msg.arbitration_id, msg.data
    )
    assert decoded["Target"] == pytest.approx(12.345)  # mm on the wire


def test_a_setpoint_signal_narrower_than_the_displacement_range_is_refused(tmp_path):
    cfg = load_config(_lab_streaming(tmp_path, target_mm=10.0))
    profile, problems = check_profile(
        cfg.can.dbc, cfg.can.signals, cfg.loop.period_s, cfg.source, daemon_limits(cfg)
    )
    assert profile is None
    assert problems == [
        "lab-1khz.dbc: HostSetpoint.Target (actuator_setpoint) carries [-0.01, 0.01] m, but"
        f" {cfg.source}'s loop.x_range_m needs [-0.045, 0.045] m"
    ]


def test_a_setpoint_echo_without_an_e2e_counter_to_echo_is_refused(tmp_path):
    config = _lab_streaming(tmp_path)
    dbc = config.parent / "lab-1khz.dbc"
    dbc.write_text(
        dbc.read_text().replace(
            '[-50|50] "mm" LABRIG\n',
            '[-50|50] "mm" LABRIG\n SG_ Echo : 24|4@1+ (1,0) [0|15] "" LABRIG\n',
        )
    )
    toml = config.read_text()
    mapped = 'setpoint_counter_echo = "HostSetpoint.Echo"\n'
    config.write_text(toml.replace('setpoint_counter_echo = "absent"\n', mapped))
    cfg = load_config(config)
    profile, problems = check_profile(cfg.can.dbc, cfg.can.signals, cfg.loop.period_s, cfg.source)
    assert profile is None
    assert problems == [
        f"{cfg.source}: can.signals.setpoint_counter_echo: LabSensors has no E2E counter to echo"
    ]


# ---- SetpointStream ----------------------------------------------------------------------
def test_the_setpoint_stream_sends_the_contracts_test_vector():
    profile = contract_profile()
    stream = SetpointStream(profile, profile.packer(), 0.03)
    for echo in (15, 0, 1, 2, 3):  # rolling counters 0..4
        stream.message(echo, 0.0)
    msg = stream.message(4, 0.012345, 0.1234)
    assert (msg.arbitration_id, msg.is_extended_id, msg.dlc) == (0x212, False, 8)
    assert bytes(msg.data).hex(" ") == "77 45 39 30 00 d2 04 00"


@pytest.mark.parametrize(
    ("echo", "position_m", "velocity_m_s", "error"),
    [
        (1, 0.0301, 0.0, "position 30.100 mm beyond the STREAM envelope +-30 mm"),
        (1, -0.0301, 0.0, "position -30.100 mm beyond the STREAM envelope +-30 mm"),
        (1, math.nan, 0.0, "not finite"),
        (1, 0.0, math.inf, "not finite"),
        (1, 0.0, 5.0, "VelocityFeedforward=5.0 outside"),
        (0, 0.001, 0.0, "sensor frame 0 has its setpoint already"),
    ],
)
def test_the_setpoint_stream_refuses_what_the_daemon_may_not_send(
    echo, position_m, velocity_m_s, error
):
    profile = contract_profile()
    stream = SetpointStream(profile, profile.packer(), 0.03)
    stream.message(0, 0.001)
    with pytest.raises(SetpointError) as err:
        stream.message(echo, position_m, velocity_m_s)
    assert error in str(err.value) and "\n" not in str(err.value)
    assert stream.message(1, 0.03).data  # the envelope itself is within it; nothing was sent


def test_the_setpoint_stream_of_a_1_0_profile_is_refused(tmp_path):
    profile = _profile(_lab(tmp_path))
    with pytest.raises(SetpointError) as err:
        SetpointStream(profile, profile.packer(), 0.02)
    assert "actuator_setpoint" in str(err.value)


def test_the_firmware_follows_the_setpoint_stream_answering_each_sensor_frame():
    """The daemon's stream and the simulated firmware, both through the DBC: each setpoint
    echoes the frame it answers, and the piston is there one period later."""
    profile = contract_profile()
    fw = Firmware(QUIET, profile)
    packer = profile.packer()
    stream = SetpointStream(profile, packer, 0.03)
    parser = profile.codec.parser()
    command = packer.message("ActuatorCommand", {"Waveform": "STREAM", "Amplitude": 0.03})
    fw.on_frame(command.arbitration_id, bytes(command.data), 0.0)
    targets = [0.02 * math.sin(2 * math.pi * 2.0 * k * T) for k in range(100)]
    measured = []
    for k, x in enumerate(targets + [0.0]):
        for frame in fw.tick(k * T):
            fw.sent(frame, k * T)
            parsed = parser.parse(frame.frame_id, frame.data, k * T)
            if parsed.name == "RigSensors":
                measured.append(parsed.values["Displacement"])
                msg = stream.message(parsed.counter, x)
                assert fw.on_frame(msg.arbitration_id, bytes(msg.data), k * T + 5e-4).ok
    # the servo-hydraulic actuator's steady state: the transfer function at 2 Hz, behind the
    # setpoint by the period it waits to be applied (firmware_sim/actuator.py)
    h = fw.servo.params.transfer(2.0) * np.exp(-2j * math.pi * 2.0 * T)
    k = np.arange(50, 100)  # after the start's transient
    expected = np.abs(h) * 0.02 * np.sin(2 * math.pi * 2.0 * k * T + np.angle(h))
    assert np.max(np.abs(np.asarray(measured)[k + 1] - expected)) <= 0.02 * 0.02
    assert fw.late_setpoints == 0 and fw.fault_code == "NONE"


def test_the_shipped_contract_dbc_is_version_1_1():
    db = cantools.database.load_file(str(REPO / "configs" / "mrrig.dbc"))
    assert db.version == "mrrig CAN contract 1.1"


def test_dbc_show_names_the_setpoint_message_or_none(capsys):
    from mrrig.cli import dbc as dbc_cli

    assert dbc_cli.main(["show", "--config", str(REPO / "configs" / "rig.toml")]) == 0
    out = capsys.readouterr().out
    assert "actuator_setpoint    ActuatorSetpoint.PositionSetpoint" in out
    assert (
        "setpoint (sent): ActuatorSetpoint, 8 bytes, 11-bit, 2 ms, E2E profile 2 (Data ID 99)"
        in out
    )
    assert dbc_cli.main(["show", "--config", str(PROFILES / "lab-1khz.toml")]) == 0
    out = capsys.readouterr().out
    assert "actuator_setpoint    absent" in out and "setpoint (sent): none" in out


def test_a_plan_step_on_a_stream_is_not_judged_as_a_damper_at_rest(tmp_path):
    from mrrig.plans.feasibility import before_arming
    from tests.test_feasibility import step_of

    step = step_of(
        tmp_path,
        "streamed",
        """
        actuator = { waveform = "stream", amplitude_m = 0.02 }
        reference = { kind = "sine", amplitude_n = 300.0, freq_hz = 1.0 }
        """,
    )
    p = before_arming(step)
    assert p.low is None and "STREAM stroke" in p.text()
