"""`mrrig validate` prints its models' numbers side by side after the last one (issue 42: it
printed one report per model and no table to compare them by). The reports are what
`validate.track_with_attempts` returns (`summarize` of a window's samples); pure, no rig."""

from __future__ import annotations

import json

import numpy as np

from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.loop.summary import summarize
from mrrig.offline.validate import finish, table

PERIOD_S = 0.002


def _report(model: str, noise_n: float, faults: int = 0, attempts: int = 1) -> dict:
    """A validation window of 2 s armed: f_meas = f_des + noise of `noise_n` N."""
    rng = np.random.default_rng(7)
    n = 1000
    s = np.zeros(n, dtype=SAMPLE_DTYPE)
    s["t"] = np.arange(n) * PERIOD_S
    s["f_des"] = 800.0 * np.sin(2 * np.pi * s["t"])
    s["f_meas"] = s["f_des"] + rng.normal(0.0, noise_n, n)
    s["i_cmd"] = np.abs(s["f_des"]) / 800.0
    s["i_meas"] = s["i_cmd"]
    s["latency_us"] = 150.0
    s["state"] = RigState.ARMED
    events = [
        {"t": 1.0, "level": "ERROR", "text": "fault", "kind": "fault", "fault": "x", "reason": "x"}
    ] * faults
    r = summarize(s, events)
    r["i_meas_a"] = {"mean": float(s["i_meas"].mean()), "max": float(s["i_meas"].max())}
    return {"model": model, "setup": "-", **r, "attempts": attempts, "discarded_faults": []}


def test_the_models_numbers_are_printed_side_by_side_with_the_ratio_to_the_best():
    reports = [_report("runs/a/lab.json", 40.0), _report("runs/b/twin.json", 10.0)]
    text = table(reports)
    print(text)
    lines = text.splitlines()
    assert lines[0] == "models side by side:" and lines[1].split()[:3] == ["model", "Et", "/best"]
    rows = {line.split()[0]: line.split() for line in lines[3:]}
    assert set(rows) == {"lab.json", "twin.json"}
    et_a, et_b = reports[0]["et"], reports[1]["et"]
    assert et_b < et_a
    assert rows["lab.json"][1] == f"{et_a:.4f}" and rows["twin.json"][1] == f"{et_b:.4f}"
    assert rows["twin.json"][2] == "1.00" and rows["lab.json"][2] == f"{et_a / et_b:.2f}"
    assert rows["lab.json"][-2:] == ["1", "0"]  # one window tried, no fault


def test_the_same_file_name_in_two_folders_is_told_apart_by_its_path():
    reports = [_report("runs/a/model.json", 40.0), _report("runs/b/model.json", 10.0)]
    rows = [line.split()[0] for line in table(reports).splitlines()[3:]]
    assert rows == ["runs/a/model.json", "runs/b/model.json"]


def test_validate_ends_with_the_table_the_json_and_exit_1_where_a_model_faulted(tmp_path, capsys):
    reports = [_report("a.json", 40.0), _report("b.json", 10.0, faults=1, attempts=3)]
    out = tmp_path / "v.json"
    assert finish(reports, out) == 1
    captured = capsys.readouterr()
    assert "models side by side:" in captured.out
    row_b = next(line for line in captured.out.splitlines() if line.startswith("b.json"))
    assert row_b.split()[-2:] == ["3", "1"]
    assert "faults during the validation of: b.json" in captured.err
    assert [r["model"] for r in json.loads(out.read_text())["reports"]] == ["a.json", "b.json"]
    # one model: its report alone (printed as it ran), no table
    assert finish(reports[:1], None) == 0
    assert "side by side" not in capsys.readouterr().out
