"""Start-up refuses a config or model that does not fit, with one line naming file and field."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import REPO

BASE = '[bus]\ninterface = "virtual"\nchannel = "cfg-test"\n'


def run_daemon(tmp_path, text: str) -> subprocess.CompletedProcess:
    cfg = tmp_path / "rig.toml"
    cfg.write_text(text)
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "mrrig",
            "run",
            "--config",
            str(cfg),
            "--duration",
            "0.5",
            "--no-record",
            "--no-telemetry",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ('[bus]\ninterface = "virtual"\n', "bus.channel: missing required field"),
        (BASE + '[loop]\ni_max_a = "two"\n', "loop.i_max_a: expected a number, got 'two'"),
        (BASE + "[loop]\ni_max_a = 9.0\n", "loop.i_max_a: must be in (0, 5] A"),
        (BASE + "[loop]\nperiod = 0.002\n", "loop.period: unknown field"),
        (BASE + '[controller]\nname = "magic"\n', "controller.name: unknown controller 'magic'"),
        (
            BASE + '[controller]\nmodel = "no/such/model.json"\n',
            "controller.model: no/such/model.json not found",
        ),
        (
            BASE + '[controller]\nname = "supervised"\nmodel = "{forward}"\n',
            "controller supervised: the supervised inverse needs a model",
        ),
        (
            BASE + '[controller]\nmodel = "{forward}"\ncontinuity = -0.5\n',
            "controller.continuity: must be >= 0",
        ),
        (
            BASE + '[controller]\nmodel = "{forward}"\nfeedback_tau_s = -0.001\n',
            "controller.feedback_tau_s: must be in [0, 10] s",
        ),
        # issue 32, finding 6: every setting that scales a wait has an upper bound at load
        (
            BASE + "[loop]\ntimeout_periods = 100000000\n",
            "loop.timeout_periods: 100000000 periods of 0.002 s is a sensor timeout of 200000 s",
        ),
        (BASE + "[loop]\ntimeout_periods = 501\n", "(at most 1 s"),
        (BASE + "[loop]\narm_settle_s = 1e6\n", "loop.arm_settle_s: must be in [0, 60] s"),
        # finding 9: a profile's forces inside loop.f_range_n (here its default +-6000 N)
        (
            BASE
            + '[controller]\nname = "constant"\n[reference]\nkind = "csv"\npath = "{profile}"\n',
            "force_n 1e+300 N at t_s 1 s (sample 2; 1 samples in all) is outside loop.f_range_n",
        ),
        (
            BASE
            + '[controller]\nname = "constant"\n[reference]\nkind = "sine"\namplitude_n = 7e3\n',
            "reference: sine from -7000 to 7000 N is outside loop.f_range_n [-6000, 6000] N",
        ),
        (BASE + "[loop\n", "not valid TOML"),
        (BASE + "[reference]\ncurrent_a = nan\n", "reference.current_a: expected a finite number"),
        (
            BASE + "[bus.options]\nreceive_own_messages = true\n",
            "bus.options.receive_own_messages: the daemon must not receive its own frames",
        ),
        (BASE + "[loop]\narm_settle_s = inf\n", "loop.arm_settle_s: expected a finite number"),
    ],
)
def test_bad_config_or_model_stops_startup_with_one_line(tmp_path, sim_model, text, expected):
    profile = tmp_path / "huge.csv"
    profile.write_text("t_s,force_n\n0,0\n1,1e300\n2,0\n")
    text = text.replace("{forward}", str(sim_model)).replace("{profile}", str(profile))
    r = run_daemon(tmp_path, text)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("error: ")
    assert expected in lines[0], lines[0]
    source = str(sim_model) if 'name = "supervised"' in text else str(tmp_path / "rig.toml")
    assert source in lines[0]


def test_a_bad_model_file_names_the_file_and_the_field(tmp_path):
    bad = tmp_path / "model.json"
    bad.write_text('{"format": "mrrig-mlp/1", "input_names": ["x"]}')
    r = run_daemon(tmp_path, BASE + f'[controller]\nmodel = "{bad}"\n')
    assert r.returncode == 2
    line = r.stderr.strip()
    assert "\n" not in line and str(bad) in line


def test_a_multicast_bus_interface_is_refused(tmp_path):
    r = run_daemon(tmp_path, '[bus]\ninterface = "lan_multicast"\nchannel = "x"\n')
    assert r.returncode == 2
    assert "bus.interface" in r.stderr and "multicasts off this machine" in r.stderr
