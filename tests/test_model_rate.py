"""Issue 36, item 6: a model trained on data in volts at 3004.8 Hz says so, and the daemon
refuses, with one line, a model whose command unit or history sample period does not fit the
rig (500 Hz, amperes)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mrrig.config import load_config
from mrrig.loop.daemon import Daemon
from mrrig.loop.mlp import MLP, ModelError
from tests.rig_harness import write_config
from tests.test_model_requests import _overrides

DYKE = Path(__file__).resolve().parents[2] / "shared" / "data" / "dyke-mr-damper-ransim-u.csv"
DYKE_PERIOD_S = 1.0 / 3004.8


def _history_model(path: Path, period_s: float, command_unit: str = "A") -> Path:
    """A forward network of x, xd, xdd, current and one earlier sample of x and xd."""
    rng = np.random.default_rng(0)
    names = ["x", "xd", "xdd", "current", "x_1", "xd_1"]
    units = ["m", "m/s", "m/s^2", "A", "m", "m/s"]
    model = MLP(
        names,
        units,
        "force",
        "N",
        np.zeros(6),
        np.ones(6),
        0.0,
        500.0,
        rng.normal(size=(8, 6)),
        np.zeros(8),
        rng.normal(size=8),
        0.0,
        meta={"sample_period_s": period_s, "command_unit": command_unit, "history_samples": 1},
    )
    model.save(path)
    return path


def _start(tmp_path: Path, model: Path) -> Daemon:
    config = write_config(tmp_path, "unused", timeout_periods=50)
    return Daemon(load_config(config, _overrides(tmp_path, model, name="network_inversion")))


def test_a_history_model_trained_at_3kHz_is_refused_by_a_500_hz_rig_with_one_line(tmp_path):
    (tmp_path / "models").mkdir()
    model = _history_model(tmp_path / "dyke.json", DYKE_PERIOD_S)
    with pytest.raises(ModelError) as refused:
        _start(tmp_path, model)
    start = tmp_path / "models" / "start.json"
    assert str(refused.value) == (
        f"{start}: meta.sample_period_s: history inputs trained at 0.000332801 s (3004.8 Hz),"
        " the rig runs at 0.002 s (500 Hz, loop.period_s): retrain on data at the rig's rate"
    )


def test_a_history_model_at_the_rigs_period_starts(tmp_path):
    (tmp_path / "models").mkdir()
    daemon = _start(tmp_path, _history_model(tmp_path / "rig.json", 0.002))
    assert daemon.controller is not None


def test_a_model_commanding_volts_is_refused_with_one_line(tmp_path):
    (tmp_path / "models").mkdir()
    model = _history_model(tmp_path / "volts.json", 0.002, command_unit="V")
    with pytest.raises(ModelError, match=r"meta.command_unit: expected A .* found 'V'"):
        _start(tmp_path, model)


@pytest.mark.long
def test_training_on_volts_at_3004_8_hz_reports_volts_and_the_exact_period(tmp_path):
    """The first 6 s of the Dyke file (times printed to 6 digits): the report's inverse
    numbers are in V, and the model records 1 / 3004.8 s, not the rounded 0.0003 s."""
    head = tmp_path / "dyke-6s.csv"
    lines = DYKE.read_text().splitlines()
    head.write_text("\n".join(lines[: 1 + round(6.0 / DYKE_PERIOD_S)]) + "\n")
    out = tmp_path / "m.json"
    proc = subprocess.run(
        [sys.executable, "-m", "mrrig", "-q", "train", str(head), "--out", str(out)]
        + ["--features", "manual", "--history", "2", "--epochs", "5", "--no-supervised"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    report = proc.stdout
    assert "network inversion: inverse-command RMSE" in report
    inverse = [ln for ln in report.splitlines() if "RMSE" in ln and "inverse" in ln]
    assert inverse and all(" V" in ln and " A," not in ln for ln in inverse), inverse
    assert re.search(r"i_max [0-9.]+ V", report), report
    meta = json.loads(out.read_text())["meta"]
    assert meta["sample_period_s"] == pytest.approx(DYKE_PERIOD_S, rel=1e-4)
