"""The model's coverage (issue 36, item 2): the model file keeps its training envelope,
`mrrig evaluate` gives the share of rows outside it and the error inside and outside, the
daemon marks every frame against it and the summary, the recording and `mrrig review` count
the armed frames outside."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mrrig.cli.train import main as train_main
from mrrig.loop.coverage import OUTSIDE_BITS, Envelope, band_shares, model_envelope
from mrrig.loop.mlp import MLP, ModelError
from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.loop.summary import format_summary, summarize
from mrrig.offline.evaluate import main as evaluate_main
from mrrig.offline.review import read_recording
from tests.conftest import REPO, OutputWatch, rig_config

LAB = Path(__file__).resolve().parents[2] / "shared" / "data" / "labcontrol-shaking-table"
needs_lab = pytest.mark.skipif(not LAB.is_dir(), reason=f"no {LAB}")


def _envelope() -> Envelope:
    return Envelope(
        lo=(-0.02, -0.5, -20.0, 0.0),
        hi=(0.02, 0.5, 20.0, 2.0),
        bands={"force": None, "xd": None},
        sample_period_s=0.002,
    )


def test_a_frame_is_marked_with_a_bit_per_input_outside_its_range():
    env = _envelope()
    assert env.outside(0.0, 0.0, 0.0, 1.0) == 0
    assert env.outside(0.02, 0.5, -20.0, 2.0) == 0  # the bounds are inside
    assert env.outside(0.0, 0.6, 0.0, 1.0) == OUTSIDE_BITS["xd"]
    assert env.outside(-0.03, 0.0, 25.0, 1.0) == OUTSIDE_BITS["x"] | OUTSIDE_BITS["xdd"]
    assert env.outside(0.0, 0.0, 0.0, 2.5) == OUTSIDE_BITS["command"]
    assert env.outside(math.nan, 0.0, 0.0, 1.0) == OUTSIDE_BITS["x"]  # NaN: not known inside
    rows = np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.6, 0.0, 1.0], [-0.03, 0.0, 25.0, 2.5]])
    assert env.outside_rows(rows).tolist() == [env.outside(*r) for r in rows.tolist()]


def test_band_shares_put_a_sines_power_in_its_band():
    t = np.arange(5000) * 0.002
    v = np.sin(2 * np.pi * 5.0 * t) + 0.1 * np.sin(2 * np.pi * 40.0 * t)
    s = band_shares(v, [(0, 5000)], 0.002)
    assert s is not None and sum(s) == pytest.approx(1.0)
    assert s[2] == pytest.approx(1 / 1.01, rel=1e-3)  # 3-10 Hz
    assert s[4] == pytest.approx(0.01 / 1.01, rel=1e-2)  # 30-100 Hz
    assert band_shares(np.ones(100), [(0, 100)], 0.002) is None


def test_a_bad_envelope_in_a_model_file_is_named_in_one_line():
    doc = _envelope().to_meta()
    assert Envelope.from_meta(doc, "m.json") == _envelope()
    with pytest.raises(ModelError, match=r"^m.json: field 'meta.envelope.lo': expected 4"):
        Envelope.from_meta({**doc, "lo": [0.0, 1.0]}, "m.json")
    with pytest.raises(ModelError, match=r"'meta.envelope.lo': a lower bound above"):
        Envelope.from_meta({**doc, "lo": [0.03, 0.0, 0.0, 0.0]}, "m.json")
    assert model_envelope({}, "old.json") is None  # a model from before envelopes


@pytest.fixture(scope="module")
def zero_volt_model(tmp_path_factory):
    """A model of two 0 V and one 0.87 V Labcontrol tests (A. N. Vargas, Zenodo, DOI
    10.5281/zenodo.4445334), few epochs."""
    out = tmp_path_factory.mktemp("coverage") / "m.json"
    files = [LAB / "ensaio1.1.csv", LAB / "ensaio2.1.csv", LAB / "ensaio1.2.2.csv"]
    args = [*map(str, files), "--out", str(out), "--no-supervised", "--restarts", "1"]
    assert train_main([*args, "--epochs", "30", "--cv-folds", "0", "--features", "manual"]) == 0
    return out


@needs_lab
def test_the_model_file_keeps_the_range_and_spectrum_it_was_trained_on(zero_volt_model):
    model = MLP.load(zero_volt_model)
    env = model_envelope(model.meta, str(zero_volt_model))
    assert env is not None
    assert env.lo[3] == 0.0 and env.hi[3] == pytest.approx(0.8712)  # the commands, V
    assert env.lo[1] < 0.0 < env.hi[1] and env.sample_period_s == pytest.approx(0.01)
    for sig in ("force", "xd"):
        shares = env.bands[sig]
        assert shares is not None and sum(shares) == pytest.approx(1.0)
        assert shares[0] + shares[1] > 0.9  # sines at 0.5-1 Hz: their power below 3 Hz


@needs_lab
def test_evaluate_gives_the_share_outside_and_the_error_inside_and_outside(
    zero_volt_model, tmp_path, capsys
):
    capsys.readouterr()
    out = tmp_path / "e.json"
    # a 3.212 V test: every command beyond the model's 0-0.87 V
    args = [str(zero_volt_model), str(LAB / "ensaio.A.1.csv"), str(LAB / "ensaio3.1.csv")]
    assert evaluate_main([*args, "--json", str(out)]) == 0
    text = capsys.readouterr().out
    print(text)
    c = json.loads(out.read_text())["coverage"]
    n_a1 = json.loads(out.read_text())["per_test"][0]["n"]
    assert c["rows"] == c["inside"]["n"] + c["outside"]["n"]
    assert c["outside_share_by_input"]["command"] == pytest.approx(n_a1 / c["rows"])
    assert c["outside"]["et"] > c["inside"]["et"]  # beyond its range the model is worse
    assert "of the rows outside the model's training envelope" in text
    assert "forward Et inside" in text and "power by band" in text


def _samples(marks: list[float], states: list[int]) -> np.ndarray:
    s = np.zeros(len(marks), dtype=SAMPLE_DTYPE)
    s["t"] = np.arange(len(marks)) * 0.002
    s["outside"], s["state"] = marks, states
    return s


def test_the_summary_counts_armed_frames_outside_by_input():
    a, i = RigState.ARMED, RigState.IDLE
    bits = OUTSIDE_BITS
    s = _samples([0, bits["xd"], bits["xd"] | bits["x"], 0, bits["xd"]], [a, a, a, a, i])
    c = summarize(s, [])["coverage"]
    assert c["armed_frames_marked"] == 4 and c["outside_frames"] == 2
    assert c["outside_share"] == 0.5
    assert c["outside_share_by_input"] == {"x": 0.25, "xd": 0.5, "xdd": 0.0, "command": 0.0}
    assert "50.0% of 4 armed frames outside the model's training envelope" in format_summary(
        summarize(s, [])
    )
    # a run without an envelope (NaN marks) has no coverage line
    none = summarize(_samples([math.nan] * 3, [a] * 3), [])
    assert "coverage" not in none and "coverage" not in format_summary(none)


@pytest.mark.process
def test_a_run_beyond_the_models_velocity_range_shows_its_share_outside(
    tmp_path, bridge, procs, sim_model
):
    """The simulated rig driven at 18 mm, 8 Hz (0.90 m/s) with a model of data set B
    (velocities to 0.75 m/s): the summary, the recording and `mrrig review` count the armed
    frames outside the model's velocity range."""
    env = model_envelope(MLP.load(sim_model).meta, str(sim_model))
    assert env is not None and env.hi[1] < 2 * np.pi * 8.0 * 0.018
    cfg = rig_config(
        tmp_path, bridge, sim_model, actuator={"amplitude_m": 0.018, "frequency_hz": 8.0}
    )
    summary_path, rrd = tmp_path / "summary.json", tmp_path / "run.rrd"
    daemon = procs(
        ["-m", "mrrig", "run", "--config", str(cfg), "--arm", "--record", str(rrd),
         "--summary-json", str(summary_path)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    daemon_out = OutputWatch(daemon, "loop running")
    assert daemon_out.seen.wait(60), daemon_out.text()
    sim = procs(
        ["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge,
         "--duration", "4"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    out = OutputWatch(sim, "rig firmware on")
    assert sim.wait(timeout=60) == 0, out.text()
    out.join()
    daemon.send_signal(signal.SIGTERM)
    daemon.wait(timeout=30)
    daemon_out.join()
    s = json.loads(summary_path.read_text())
    c = s["coverage"]
    print(f"daemon: {c}; faults {s['faults']}")
    samples = read_recording(rrd).samples
    armed = samples[samples["state"] == RigState.ARMED]
    assert armed.size > 500
    # each recorded frame's mark says what its velocity and the model's range say
    beyond = (armed["xd"] < env.lo[1]) | (armed["xd"] > env.hi[1])
    assert np.array_equal((armed["outside"].astype(int) & OUTSIDE_BITS["xd"]) != 0, beyond)
    assert 0.15 < beyond.mean() < 0.6  # a sine of 0.90 m/s peak beyond 0.75 m/s: ~37 %
    # the daemon's count is the recording's (to the frames the recording might have lost)
    assert c["armed_frames_marked"] == pytest.approx(armed.size, rel=0.01)
    assert c["outside_share_by_input"]["xd"] == pytest.approx(beyond.mean(), abs=0.01)
    review = subprocess.run(
        [sys.executable, "-m", "mrrig", "review", str(rrd)],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert review.returncode == 0, review.stdout + review.stderr
    print(review.stdout)
    line = next(ln for ln in review.stdout.splitlines() if ln.startswith("coverage"))
    outside = (armed["outside"] != 0).mean()
    assert f"{outside:.1%} of {armed.size} armed frames outside" in line
    assert f"xd {beyond.mean():.1%}" in line


def test_a_plan_step_can_fail_on_the_share_outside_the_envelope():
    from mrrig.plans.criteria import Criteria, failures, measure
    from mrrig.typed_config import ConfigError, parse

    a = RigState.ARMED
    s = _samples([0, 0, OUTSIDE_BITS["xd"], 0], [a] * 4)
    s["f_des"], s["f_meas"], s["temp_degc"] = [1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 4.0], 25.0
    numbers = measure(s, settle_s=0.0)
    assert numbers.outside_share == 0.25
    strict = parse(Criteria, {"coverage_outside_max": 0.1}, "plan.toml", "step 1.criteria")
    assert failures(strict, numbers, []) == [
        "coverage_outside_max: 25.0% of the samples outside the model's training envelope > 10.0%"
    ]
    assert failures(Criteria(coverage_outside_max=0.3), numbers, []) == []
    s["outside"] = math.nan  # a model without an envelope: nothing to judge by
    assert "keeps no training envelope" in failures(strict, measure(s, 0.0), [])[0]
    with pytest.raises(ConfigError, match="coverage_outside_max: must be in"):
        parse(Criteria, {"coverage_outside_max": 5.0}, "plan.toml", "step 1.criteria")
