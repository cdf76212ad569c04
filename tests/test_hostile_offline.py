"""Issue 32, findings 12 and 13 (the offline tools' part): big or broken data and the files
the offline tools and the profile readers take. Each test reproduced what the issue saw
before the fix (an implausible force trained on, a NaN Et with exit 0, a traceback's words
instead of the file and field); now it checks the fixed behaviour. Real files throughout:
CSVs, model files and .rrd recordings written and read back by the real readers, the daemon's
loop (tests/rig_harness.py) for `set_profile`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from mrrig.cli.main import main as mrrig_main
from mrrig.cli.train import main as train_main
from mrrig.loop.mlp import MLP, ModelError
from mrrig.loop.reference import CsvSeries, ForceReferenceError
from mrrig.offline.evaluate import evaluate
from mrrig.offline.review import ReviewError, read_recording
from mrrig.offline.training.stream import segments, training_subset
from mrrig.rigio import force_stream
from tests.rig_harness import ScriptedRig
from tests.test_hostile_input import _dirs, _disarm
from tests.test_measured_data import _sim_varying

TRAIN = ["--features", "manual", "--current-input", "lagged", "--epochs", "5", "--restarts", "1"]
TRAIN += ["--no-supervised"]


def _write_csv(path: Path, runs: int = 3, seconds: float = 6.0, seed: int = 5) -> Path:
    """Simulated rig data (command varying within runs) as a CSV with named headers; time
    restarts in each run."""
    v = _sim_varying(n_runs=runs, seconds=seconds, seed=seed)
    rows = np.column_stack([v.t, v.x, v.force, v.current])
    body = "\n".join(",".join(repr(float(c)) for c in r) for r in rows)
    path.write_text("t_s,x_m,force_n,current_a\n" + body + "\n", encoding="utf-8")
    return path


def _lines(path: Path) -> list[str]:
    return path.read_text(encoding="utf-8").splitlines()


@pytest.fixture(scope="module")
def data_and_model(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("offline")
    data = _write_csv(tmp / "data.csv")
    model = tmp / "m.json"
    assert train_main([str(data), "--out", str(model), *TRAIN]) == 0
    return data, model


# ---- 12. big or broken data ------------------------------------------------------------------
def test_finding12_a_force_sample_beyond_the_load_cells_range_is_excluded_not_trained_on(
    tmp_path, capsys
):
    data = _write_csv(tmp_path / "spike.csv")
    lines = _lines(data)
    cells = lines[1000].split(",")
    cells[2] = "1e30"  # force_n: far beyond the DBC's Force range (+-83886 N)
    lines[1000] = ",".join(cells)
    data.write_text("\n".join(lines) + "\n", encoding="utf-8")
    report = tmp_path / "r.json"
    model = tmp_path / "m.json"
    assert train_main([str(data), "--out", str(model), "--report", str(report), *TRAIN]) == 0
    r = json.loads(report.read_text())
    assert r["excluded"]["by_kind"]["implausible"] >= 1
    kinds = [st["kind"] for st in r["excluded"]["stretches"]]
    assert "implausible" in kinds
    assert r["forward"]["et"] < 1.0  # was 3.5e23: the spike was trained on and scored
    assert "implausible" in capsys.readouterr().out
    # evaluate excludes it the same way: a finite, sane Et (was `forward Et nan`, exit 0)
    out = tmp_path / "e.json"
    assert mrrig_main(["evaluate", str(model), str(data), "--json", str(out)]) == 0
    e = json.loads(out.read_text())
    assert e["excluded"]["by_kind"]["implausible"] >= 1 and e["forward"]["et"] < 1.0


def test_finding12_a_metric_that_is_not_finite_is_an_error_with_its_reason(
    tmp_path, data_and_model, capsys
):
    _, model = data_and_model
    flat = _write_csv(tmp_path / "flat.csv")
    lines = _lines(flat)
    body = [",".join([*ln.split(",")[:2], "100.0", ln.split(",")[3]]) for ln in lines[1:]]
    flat.write_text("\n".join([lines[0], *body]) + "\n", encoding="utf-8")
    # kept as they are, a force that never changes gives an Et of x / 0
    assert mrrig_main(["evaluate", str(model), str(flat), "--keep-all"]) == 1
    err = capsys.readouterr().err
    assert "error:" in err and "forward Et is inf" in err and "does not vary" in err


def test_finding12_evaluate_goes_through_every_sample_a_segment_at_a_time(data_and_model):
    data, model = data_and_model
    mlp = MLP.load(model)
    whole, _ = evaluate(mlp, model, [data])
    parts = list(segments([data], max_rows=7000))  # 3 runs of 3000 samples
    assert [len(s) for _, s in parts] == [6000, 3000]  # cut at a run's start
    chunked, _ = evaluate(mlp, model, [data], max_rows=7000)
    assert chunked["n"] == whole["n"]
    for key in ("et", "rmse_n"):
        assert chunked["forward"][key] == pytest.approx(whole["forward"][key], rel=1e-9)
    assert chunked["inverse_current_rmse"] == pytest.approx(whole["inverse_current_rmse"])
    # a run longer than a segment is cut into segments of that length: every sample read
    cut = list(segments([data], max_rows=2000))
    assert sum(len(s) for _, s in cut) == 9000 and max(len(s) for _, s in cut) == 2000


def test_finding12_train_keeps_a_bounded_subset_of_whole_segments(data_and_model):
    data, _ = data_and_model
    s, report = training_subset([data], max_samples=6000, segment_rows=3000)
    assert report["subset"] == {"samples": 6000, "of_samples": 9000, "max_samples": 6000}
    assert len(s) <= 6000 and np.unique(s.run_id).size == 2  # two whole runs of three


# ---- 13. messages that name the file, the field and the line -------------------------------
def test_finding13_a_model_number_beyond_a_float_is_named_not_an_overflow(
    tmp_path, data_and_model, capsys
):
    data, model = data_and_model
    doc = json.loads(model.read_text())
    doc["W1"][0][0] = 10**400
    bad = tmp_path / "big.json"
    bad.write_text(json.dumps(doc))
    assert mrrig_main(["evaluate", str(bad), str(data)]) == 2
    err = capsys.readouterr().err
    assert f"error: {bad}: field 'W1.0.0': an integer of 401 digits" in err, err


def test_finding13_a_model_scale_that_the_inversion_divides_to_zero_is_refused(data_and_model):
    _, model = data_and_model
    doc = json.loads(model.read_text())
    doc["out_std"] = 1e-200  # squared: 0, and the inversion divides by it (ZeroDivisionError)
    with pytest.raises(ModelError, match=r"x\.json: field 'out_std': must lie in"):
        MLP.from_text(json.dumps(doc), "x.json")


def test_finding13_a_model_meta_field_of_the_wrong_kind_is_named(tmp_path, data_and_model):
    data, model = data_and_model
    doc = json.loads(model.read_text())
    doc["meta"]["excluded"] = 3  # was AttributeError: 'int' object has no attribute 'get'
    bad = tmp_path / "meta.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(ModelError, match=r"meta\.json: field 'meta.excluded': expected an object"):
        evaluate(MLP.load(bad), bad, [data])


def test_finding13_data_without_motion_names_the_file_not_a_series_shape(tmp_path, capsys):
    still = _write_csv(tmp_path / "still.csv")
    lines = _lines(still)
    body = [",".join([ln.split(",")[0], "0.001", *ln.split(",")[2:]]) for ln in lines[1:]]
    still.write_text("\n".join([lines[0], *body]) + "\n", encoding="utf-8")
    assert mrrig_main(["train", str(still), "--out", str(tmp_path / "m.json"), *TRAIN]) == 2
    err = capsys.readouterr().err
    assert f"error: {still}: x does not vary over the" in err, err
    # a force that never changes: every sample a saturated load cell, named with the file
    flat = tmp_path / "flat.csv"
    flat.write_text(
        "\n".join(
            [
                lines[0],
                *[",".join([*ln.split(",")[:2], "5.0", ln.split(",")[3]]) for ln in lines[1:]],
            ]
        )
        + "\n",
        encoding="utf-8",
    )
    assert mrrig_main(["train", str(flat), "--out", str(tmp_path / "m.json"), *TRAIN]) == 2
    err = capsys.readouterr().err
    assert f"error: {flat}: every sample is a bad stretch (saturation" in err, err
    assert "has shape" not in err


def test_finding13_a_profile_row_with_a_missing_field_names_line_and_column(tmp_path):
    profile = tmp_path / "p.csv"
    profile.write_text("t_s,force_n\n0,1\n0.5\n1,2\n", encoding="utf-8")
    # the daemon's reader (start-up, set_profile) and send-force's say the same
    with pytest.raises(ForceReferenceError, match=r"p\.csv:3: .*column 'force_n' missing"):
        CsvSeries(profile)
    with pytest.raises(ValueError, match=r"p\.csv:3: .*column 'force_n' missing"):
        force_stream.load_force_csv(profile)


def test_finding13_a_profile_with_a_byte_order_mark_is_read_by_every_reader(tmp_path):
    text = "t_s,force_n\n0,0\n1,100\n"
    with ScriptedRig(tmp_path, overrides=_dirs(tmp_path)) as rig:
        profile = tmp_path / "profiles" / "bom.csv"
        profile.write_bytes(b"\xef\xbb\xbf" + text.encode())
        t_s, force_n = force_stream.load_force_csv(profile)  # send-force
        assert t_s.tolist() == [0.0, 1.0] and force_n.tolist() == [0.0, 100.0]
        assert CsvSeries(profile).f.tolist() == [0.0, 100.0]  # the daemon's start-up
        _disarm(rig)
        reply = rig.request({"cmd": "set_profile", "kind": "csv", "path": str(profile)})
        assert reply == {"ok": True, "reference": "csv"}, reply
        assert rig.daemon.reference.f.tolist() == [0.0, 100.0]


def test_finding13_an_undecodable_profile_is_named_by_every_reader(tmp_path):
    profile = tmp_path / "latin1.csv"
    profile.write_bytes("t_s,force_n\n0,0\n1,100 \xb5\n".encode("latin-1"))
    with pytest.raises(ForceReferenceError, match=rf"{profile}: not UTF-8 text: byte 0xb5"):
        CsvSeries(profile)
    with pytest.raises(ValueError, match=rf"{profile}: not UTF-8 text: byte 0xb5"):
        force_stream.load_force_csv(profile)


def test_finding13_review_of_another_applications_rrd_says_it_is_not_ours(tmp_path):
    path = tmp_path / "other.rrd"
    rec = rr.RecordingStream("some_other_app")
    rec.save(path)
    for k in range(20):
        rec.set_time("step", sequence=k)
        rec.log("temperature", rr.Scalars(20.0 + k))
    rec.flush()
    rec.disconnect()
    with pytest.raises(ReviewError, match="not an mrrig recording"):
        read_recording(path)
