"""The all-numerical reference (spec/hil.md, Metrics) and `mrrig hil SCENARIO --reference`: the
simulator's Bouc-Wen damper in the loop of the quarter car and the building, the law's force
through that model's inverse. Short runs: seconds."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mrrig.hil.reference import law_table, percent_change, run_reference
from mrrig.hil.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]


def _scenario(name: str, duration_s: float):
    return dataclasses.replace(load_scenario(f"configs/hil/{name}.toml"), duration_s=duration_s)


def test_the_inverse_gives_the_damper_the_force_the_law_asks() -> None:
    """Where the current is inside its range, the force the damper gives at the next frame is
    the law's force: median error under 1 N, 90 % under 5 N (skyhook on the class C road)."""
    run = run_reference(_scenario("quarter-car", 10.0))
    asked, given, current = run.desired_force_n[:-1], run.force_n[1:], run.current_a[1:]
    inside = np.isfinite(asked) & (current > 0.01) & (current < 1.99) & (np.abs(asked) > 100.0)
    assert inside.sum() > 200
    error = np.abs(given[inside] - asked[inside])
    assert np.median(error) < 1.0 and np.percentile(error, 90) < 5.0


def test_the_reference_damper_takes_energy_from_the_car_and_the_building() -> None:
    for name, law in (("quarter-car", "skyhook"), ("building", "clipped-optimal")):
        fig = run_reference(_scenario(name, 5.0), law).figures()
        assert fig["dissipated_j"] > 0.0


def test_the_law_table_says_what_papers_say_of_the_laws() -> None:
    """On the class C road: skyhook lowers the body acceleration against passive-soft, groundhook
    the tyre load, passive-hard has the least travel and the most body acceleration."""
    rows = {
        r.law: r
        for r in law_table(
            _scenario("quarter-car", 15.0),
            ("skyhook", "groundhook", "passive-soft", "passive-hard"),
        )
    }
    soft, hard = rows["passive-soft"], rows["passive-hard"]
    assert rows["skyhook"].rms_body_acceleration_m_s2 < soft.rms_body_acceleration_m_s2
    assert rows["groundhook"].rms_tyre_load_n < soft.rms_tyre_load_n
    assert hard.rms_suspension_travel_m == min(r.rms_suspension_travel_m for r in rows.values())
    assert hard.rms_body_acceleration_m_s2 == max(
        r.rms_body_acceleration_m_s2 for r in rows.values()
    )
    assert percent_change(90.0, 100.0) == pytest.approx(-10.0)


def test_clipped_optimal_lowers_the_building_s_first_storey_drift() -> None:
    drift = {
        law: run_reference(_scenario("building", 10.0), law).figures()["rms_drift_m_1"]
        for law in ("clipped-optimal", "passive-soft")
    }
    assert drift["clipped-optimal"] < drift["passive-soft"]


def _mrrig(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-m", "mrrig", *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_mrrig_hil_reference_prints_the_vehicle_figures() -> None:
    done = _mrrig("hil", "configs/hil/quarter-car.toml", "--reference", "--duration", "2")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert "class C road at 20 m/s, skyhook, 2 s (1000 frames of 2 ms)" in lines[0]
    assert [line.split()[0] for line in lines[1:]] == ["body", "suspension", "dynamic", "envelope"]


def test_mrrig_hil_with_a_bad_scenario_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('kind = "quarter-car"\n[road]\nspeed_m_s = "fast"\n')
    done = _mrrig("hil", str(bad), "--reference")
    assert done.returncode == 2
    assert done.stderr == f"error: {bad}: road.speed_m_s: expected a number, got 'fast'\n"
    done = _mrrig("hil", "configs/hil/building.toml", "--reference", "--table")
    assert done.returncode == 2 and "--table: the law table is the quarter car's" in done.stderr


def test_a_scenario_whose_reference_strokes_past_the_rig_is_refused_in_one_line() -> None:
    from mrrig.hil.reference import envelope_problem

    fig = {"max_abs_stroke_m": 0.0422, "max_abs_force_n": 1259.0}
    assert envelope_problem(fig, 0.045, 6000.0) is None
    assert envelope_problem(fig, 0.04, 6000.0) == (
        "the reference strokes 42.2 mm, beyond the rig's 40 mm"
    )
    assert envelope_problem(fig, 0.045, 1000.0) == (
        "the reference's force reaches 1259 N, beyond the rig's 1000 N"
    )
    args = ("hil", "configs/hil/quarter-car.toml", "--reference", "--duration", "2")
    done = _mrrig(*args, "--stroke-limit-mm", "0.5")
    assert done.returncode == 2
    assert done.stderr.startswith("error: configs/hil/quarter-car.toml: the reference strokes ")
    assert done.stderr.endswith("beyond the rig's 0.5 mm: it does not fit the rig\n")
    assert _mrrig(*args, "--stroke-limit-mm", "40").returncode == 0


def test_mrrig_hil_help_prints() -> None:
    """argparse %-formats help strings: a bare '% change' made --help a traceback."""
    done = _mrrig("hil", "--help")
    assert done.returncode == 0, done.stderr
    assert "--stroke-limit-mm" in done.stdout and "% change" in done.stdout
