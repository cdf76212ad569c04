"""A hybrid simulation's recording (issue 41, item 7: the Rerun layout): the numerical model's
states (the quarter car's body and wheel displacement and velocity, suspension travel, tyre
load; the building's storey drifts) recorded per frame beside the rig's measured stroke and
force, and a "Hybrid simulation" tab of the default blueprint that shows them side by side.

The samples are a real daemon's (the `Daemon` and firmware_sim's `Firmware` in lockstep,
tests/lockstep_rig.py, a 1 s quarter-car run streamed through the simulated servo); the
recording is written by the real `Recorder` and read back from the .rrd. In-process; seconds."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mrrig.config import load_config
from mrrig.hil.reference import run_reference
from mrrig.hil.scenario import load_scenario
from mrrig.hil.stepper import HybridStep
from mrrig.hil.substructure import _fraction_table
from mrrig.loop.daemon import Daemon
from mrrig.offline.layout_check import read_blueprint
from mrrig.offline.review import read_recording
from mrrig.offline.rrd_scan import open_rrd
from mrrig.rigio.recording import FIELD_ENTITIES
from tests.conftest import REPO, rig_config
from tests.lockstep_rig import lockstep_config, run_lockstep
from tests.test_recording import write_recording

MODEL_FIELDS = ("hil_z_body", "hil_v_body", "hil_z_wheel", "hil_v_wheel")


def _daemon_run(tmp_path, scenario: str, seconds: float):
    config = lockstep_config(
        tmp_path,
        controller={"name": "constant", "current_a": 0.5},
        hil={"scenario": str(REPO / scenario), "duration_s": seconds},
    )
    run = run_lockstep(
        config, ("STOP", 0.0, 0.0), seconds + 0.3, preroll_s=0.2, arm=True, actuator_commands=True
    )
    return run.samples


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("hilrec")
    s = _daemon_run(tmp, "configs/hil/quarter-car.toml", 1.0)
    path = tmp / "rig1-hil.rrd"
    write_recording(path, s, [], {"frames_received": int(s.size)})
    return path, s


def test_the_daemon_records_the_quarter_car_s_states_per_frame(recorded):
    """Each streamed frame's body and wheel states are the model's at x_c's frame: x_c is the
    body's displacement less the wheel's, and the road starts the car at rest."""
    _, s = recorded
    run = s[np.isfinite(s["hil_k"])]
    assert run.size == 500 and not np.any(s["state"] == 2)
    for name in MODEL_FIELDS + ("hil_load_n", "hil_acc"):
        assert np.isfinite(run[name]).all(), name
    np.testing.assert_allclose(run["hil_z_body"] - run["hil_z_wheel"], run["hil_x_c"], atol=1e-12)
    assert np.ptp(run["hil_v_wheel"]) > np.ptp(run["hil_v_body"]) > 0.0  # the wheel on the road
    assert np.isnan(run["hil_drift_2"]).all()  # a building's
    assert np.isnan(s["hil_z_body"][~np.isfinite(s["hil_k"])]).all()  # no run: NaN


def test_the_recording_holds_the_model_s_states_beside_the_rig_s_stroke_and_force(recorded):
    path, s = recorded
    entities = {chunk.entity_path for chunk in open_rrd(path).stream()}
    wanted = ("x", "f_meas", "hil_x_c", "hil_setpoint", "hil_load_n", "hil_acc") + MODEL_FIELDS
    for field in wanted:
        assert "/" + FIELD_ENTITIES[field] in entities, field
    back = read_recording(path).samples
    run = np.isfinite(s["hil_k"])
    for field in MODEL_FIELDS + ("hil_x_c", "hil_load_n"):
        np.testing.assert_array_equal(back[field][run], s[field][run])


def test_the_hybrid_simulation_tab_shows_the_rig_beside_the_model(recorded):
    path, _ = recorded
    tabs = {tab.name: tab for tab in read_blueprint(path).children}
    assert "Hybrid simulation" in tabs
    rig, model = tabs["Hybrid simulation"].children
    assert (rig.name, model.name) == ("The rig", "The numerical model")
    shown = {}
    for view in rig.views() + model.views():
        query = view.properties["ViewContents"]["ViewContents:query"]
        shown[view.name] = " ".join(query).replace("$origin", view.origin)
    rig_views, model_views = [v.name for v in rig.views()], [v.name for v in model.views()]
    stroke, force = (shown[n] for n in rig_views)
    assert all(FIELD_ENTITIES[f] in stroke for f in ("x", "hil_x_c", "hil_setpoint"))
    assert all(FIELD_ENTITIES[f] in force for f in ("f_meas", "f_des"))
    model_text = " ".join(shown[n] for n in model_views)
    for entity in ("model/displacement", "model/velocity", "hil/load_n", "hil/acc", "hil_x_c"):
        assert entity in model_text, entity


def test_a_run_s_first_frame_computes_no_matrix_exponential(tmp_path):
    """The model's exact fraction-of-a-frame steps (101 matrix exponentials: 0.6-2.5 s on this
    VM, which a run's first frame paid: a building's arm frame answered 1.4 s late, a stall
    fault) are computed once per model, and the daemon computes them at start."""
    scenario = load_scenario(REPO / "configs/hil/building.toml")
    _fraction_table.cache_clear()
    first, second = scenario.substructure(), scenario.substructure()
    assert first._fractions is second._fractions
    _fraction_table.cache_clear()
    config = rig_config(
        tmp_path,
        "unused",
        None,
        bus={"interface": "virtual"},
        controller={"name": "constant", "current_a": 0.5},
        hil={"scenario": str(REPO / "configs/hil/building.toml")},
    )
    Daemon(load_config(config))
    misses = _fraction_table.cache_info().misses
    HybridStep(scenario)  # what a run's first frame builds
    assert _fraction_table.cache_info().misses == misses == 1


def test_a_building_run_records_its_storey_drifts(tmp_path):
    """Storeys 2 and 3's drifts, frame by frame, are the all-numerical reference's of the same
    frames (the same model and law; the rig's servo and damper in place of the ideal ones)."""
    s = _daemon_run(tmp_path, "configs/hil/building.toml", 1.0)
    run = s[np.isfinite(s["hil_k"])]
    assert run.size == 500 and not np.any(s["state"] == 2)
    assert np.isnan(run["hil_z_body"]).all()
    scenario = dataclasses.replace(
        load_scenario(REPO / "configs/hil/building.toml"), duration_s=1.0
    )
    drifts = run_reference(scenario).outputs["drift_m"][run["hil_k"].astype(int)]
    for j, name in ((1, "hil_drift_2"), (2, "hil_drift_3")):
        assert np.isfinite(run[name]).all()
        assert np.corrcoef(run[name], drifts[:, j])[0, 1] > 0.95, name
