"""Issue 42: a minimal config (a [bus] table alone) silently got a constant reference and no
motion, and the demo said `FAIL Et n/a` without a reason. Now each gap is one line: in the
daemon's start-up log and as the reason of the demo's Et n/a."""

from __future__ import annotations

import logging

import pytest

from mrrig.cli.demo_report import verdict
from mrrig.config import load_config
from mrrig.config_gaps import config_gaps
from tests.conftest import REPO

MINIMAL = '[bus]\ninterface = "virtual"\nchannel = "gaps"\n'
CONSTANT = {"controller": {"name": "constant", "current_a": 0.5}, "telemetry": {"enabled": False}}


def _minimal(tmp_path, text: str = MINIMAL):
    path = tmp_path / "minimal.toml"
    path.write_text(text)
    return load_config(path, CONSTANT), path


def test_a_minimal_config_names_its_constant_reference_and_still_actuator(tmp_path):
    cfg, path = _minimal(tmp_path)
    assert config_gaps(cfg) == [
        f'{path}: [reference] kind = "constant" (0 N) (the default: no [reference] table): the'
        " desired force never varies, so Et is n/a (eqs 41-43 divide by its spread); to track a"
        ' force set [reference] kind = "bouc_wen", "sine", "noise", "csv", "paper_case" or'
        ' "zenoh"',
        f'{path}: [actuator] waveform = "stop" (the default: no [actuator] table): the actuator'
        " does not move the damper at start (no velocity, hardly a damper force); set [actuator]"
        ' waveform = "sine", amplitude_m and frequency_hz, or move it by request (set_profile, a'
        " plan's step)",
    ]


@pytest.mark.parametrize(
    ("tables", "gaps"),
    [
        ('[reference]\nkind = "sine"\namplitude_n = 0.0\n', ['"sine" with amplitude_n = 0: ']),
        ('[actuator]\nwaveform = "sine"\namplitude_m = 0.01\n', ["frequency_hz = 0"]),
        ('[actuator]\nwaveform = "random"\n', ['waveform = "random" with amplitude_m = 0']),
        ('[actuator]\nwaveform = "hold"\n', ['[actuator] waveform = "hold": ']),
    ],
)
def test_a_reference_or_actuator_that_does_nothing_is_named(tmp_path, tables, gaps):
    cfg, _ = _minimal(tmp_path, MINIMAL + tables)
    found = config_gaps(cfg)
    for gap in gaps:
        assert any(gap in line for line in found), found


def test_the_shipped_configs_name_only_what_they_leave_out():
    assert config_gaps(load_config(REPO / "configs" / "rig.toml")) == []
    (actuator,) = config_gaps(load_config(REPO / "configs" / "can0.toml"))  # a zenoh reference
    assert '[actuator] waveform = "stop" (the default' in actuator  # as can0.toml says


def test_the_daemon_logs_each_gap_once_its_loop_runs(tmp_path, caplog):
    """Not before: a config that cannot start gets its one error line alone."""
    from tests.rig_harness import ScriptedRig

    with caplog.at_level(logging.INFO, "mrrig.loop.daemon"), ScriptedRig(tmp_path) as rig:
        rig.exchange()
        gaps = config_gaps(rig.cfg)  # the harness's: a constant 300 N, no [actuator]
    reference, actuator = gaps
    assert reference.startswith(f'{rig.cfg.source}: [reference] kind = "constant" (300 N): ')
    assert actuator.startswith(f'{rig.cfg.source}: [actuator] waveform = "stop" (the default')
    messages = [r.getMessage() for r in caplog.records]
    assert [m for m in messages if m in gaps] == gaps
    assert messages.index(reference) > messages.index("loop running: one command per sensor frame")
    assert {r.levelno for r in caplog.records if r.getMessage() in gaps} == {logging.WARNING}


def test_the_demos_et_na_says_why(tmp_path):
    cfg, path = _minimal(tmp_path)
    summary = {
        "et": None,
        "frames": 1000,
        "armed_frames": 900,
        "faults": [],
        "reference": "constant",
    }
    ok, text = verdict(summary, gaps=config_gaps(cfg))
    assert not ok and "  FAIL Et n/a <= 0.1" in text
    assert f'  why Et is n/a: {path}: [reference] kind = "constant" (0 N)' in text
    _, text = verdict(summary)  # no config to tell: what the summary shows
    assert (
        "why Et is n/a: the desired force (reference constant) did not vary over the armed" in text
    )
    _, text = verdict(summary | {"armed_frames": 0}, gaps=config_gaps(cfg))
    assert "why Et is n/a: the daemon was armed for fewer than 2 frames" in text
    _, text = verdict(summary | {"et": 0.02})
    assert "why Et" not in text
