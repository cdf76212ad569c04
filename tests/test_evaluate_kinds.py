"""`mrrig evaluate` on the stateful kinds `mrrig train --features auto` writes: a Bouc-Wen twin
(a plant file) and a GRU (`mrrig-gru/1`), scored as `training.kinds` scores them (each stretch
run from rest / the zero state), Et per test, and a twin in V refused on data in A."""

import json

import numpy as np
import pytest

from damper.plant import BoucWenParams
from damper.plant_file import Plant, save_plant
from mrrig.offline import evaluate
from mrrig.offline.datasets import DataError
from mrrig.offline.training.gru import fit_gru, gru_forces
from mrrig.offline.training.kinds import twin_kind
from mrrig.offline.training.report import EtSum
from mrrig.offline.training.stream import prepare, segments

DYKE = "/work/shared/data/dyke-mr-damper-ransim-u.csv"
ROWS = 3000  # about 1 s of the Dyke record


@pytest.fixture
def short_dyke(tmp_path):
    lines = open(DYKE, encoding="utf-8").read().splitlines()[: ROWS + 1]
    path = tmp_path / "dyke-short.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _series(path):
    [(_, raw)] = list(segments([path], None, None))
    series, _ = prepare(path, raw, False)
    return series


def _kinds_et(forces, model, series):
    _, y, f = forces(model, series)
    s = EtSum()
    s.add(y, f)
    return s.numbers()["et"]


def _evaluate(capsys, tmp_path, model, data):
    out = tmp_path / "numbers.json"
    assert evaluate.main([str(model), str(data), "--json", str(out)]) == 0
    return capsys.readouterr().out, json.loads(out.read_text(encoding="utf-8"))


def test_evaluate_scores_a_twin_plant_file_as_kinds_scores_it(tmp_path, short_dyke, capsys):
    plant = Plant(BoucWenParams.preset("paper-volt"), offset_n=12.5, command_unit="V")
    path = tmp_path / "twin.json"
    save_plant(plant, path)
    text, numbers = _evaluate(capsys, tmp_path, path, short_dyke)
    series = _series(short_dyke)
    expected = _kinds_et(twin_kind(holdout_fraction=0.2, i_max=1.0).forces, plant, series)
    assert np.isfinite(expected)
    assert numbers["forward"]["et"] == pytest.approx(expected, abs=1e-9)
    assert numbers["per_test"][0]["et"] == pytest.approx(expected, abs=1e-9)
    assert f"{short_dyke}: Et {expected:.4f}" in text
    assert "inverse command RMSE: does not apply to a Bouc-Wen twin" in text


def test_evaluate_scores_a_gru_file_as_kinds_scores_it(tmp_path, short_dyke, capsys):
    series = _series(short_dyke)
    model, _ = fit_gru(series, hidden=4, max_epochs=2)
    path = tmp_path / "gru.json"
    model.save(path)
    text, numbers = _evaluate(capsys, tmp_path, path, short_dyke)
    expected = _kinds_et(gru_forces, model, series)
    assert np.isfinite(expected)
    assert numbers["forward"]["et"] == pytest.approx(expected, abs=1e-9)
    assert numbers["per_test"][0]["et"] == pytest.approx(expected, abs=1e-9)
    assert f"{short_dyke}: Et {expected:.4f}" in text
    assert "inverse command RMSE: does not apply to a GRU" in text
    assert numbers["coverage"] is not None  # the GRU keeps its training envelope
    assert "coverage:" in text and "envelope (SI)" in text


def test_a_twin_in_volts_on_data_in_amperes_is_refused_in_one_line(tmp_path, short_dyke):
    plant = Plant(BoucWenParams.preset("paper-volt"), offset_n=0.0, command_unit="V")
    path = tmp_path / "twin-v.json"
    save_plant(plant, path)
    amps = tmp_path / "dyke-amps.csv"
    text = short_dyke.read_text(encoding="utf-8")
    amps.write_text(text.replace("command_v", "current_a", 1), encoding="utf-8")
    with pytest.raises(DataError) as err:
        evaluate.main([str(path), str(amps)])
    msg = str(err.value)
    assert "\n" not in msg
    assert msg == f"{amps}: command in A, but the model's command input is in V"
