"""Issue 42, item 1: the daemon's status carries its run's identity as in force (specimen, the
model's path and sha256 as deployed, controller parameters, config and DBC sha256), and
`set_model` changes it; `mrrig status` names the model loaded."""

from __future__ import annotations

from dataclasses import replace

from damper.plant import BoucWenParams
from damper.plant_file import Plant, save_plant
from mrrig.cli.client import format_status
from mrrig.plans.runner import STEP_IDENTITY
from mrrig.rigio.run_identity import file_sha256
from tests.rig_harness import ScriptedRig

PLANT = Plant(BoucWenParams.preset("paper-volt"), offset_n=12.5, command_unit="A")


def test_status_names_the_model_in_force_and_set_model_changes_it(tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    start, other = models / "start.json", models / "other.json"
    save_plant(PLANT, start)
    save_plant(replace(PLANT, offset_n=-40.0), other)
    overrides = {
        "rig": {"specimen": "SN-MR-042"},
        "control": {"model_dirs": [str(models)]},
        "loop": {"timeout_periods": 500},  # the twin's self-check while no frame comes
        "controller": {"model": str(start), "name": "network_inversion"},
    }
    with ScriptedRig(tmp_path, overrides=overrides) as rig:
        rig.exchange()
        ident = rig.request({"cmd": "status"})["status"]["identity"]
        assert ident["specimen"] == "SN-MR-042"
        assert (ident["model_path"], ident["model_sha256"]) == (str(start), file_sha256(start))
        assert ident["run_id"] == rig.daemon.identity["run_id"]
        assert ident["config_sha256"] == rig.daemon.identity["config_sha256"] is not None
        assert ident["dbc_sha256"] == file_sha256(rig.daemon.codec.dbc_path)
        assert set(STEP_IDENTITY) <= set(ident)  # what a plan step's catalog row takes
        assert rig.request({"cmd": "disarm"})["ok"]
        assert rig.request({"cmd": "set_model", "path": str(other)})["ok"]
        status = rig.request({"cmd": "status"})["status"]
        ident = status["identity"]
        assert (ident["model_path"], ident["model_sha256"]) == (str(other), file_sha256(other))
        assert file_sha256(other) != file_sha256(start)
        assert ident["run_id"] == rig.daemon.identity["run_id"]  # the same daemon run
        line = format_status(status).splitlines()[2]
        assert line == (
            f"  model {other} (sha256 {file_sha256(other)[:12]}), specimen SN-MR-042,"
            f" run {ident['run_id']}"
        )
