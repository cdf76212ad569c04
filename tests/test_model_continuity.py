"""The daemon's network inversion takes the continuity its model was trained with.

`mrrig train` (and the demo's `simulated_matrix_model`) choose the on-line inversion's
continuity on the training rows and keep it in the model file (meta `online_continuity`);
without a `continuity` in `[controller]` the daemon uses it. The test engineer's reason:
with the root alone (continuity 0) the command jumps across the coil's range at the velocity
reversals, where the force hardly depends on the current.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from damper.plant import BoucWenDamper, BoucWenParams
from damper.signals import sine
from mrrig.config import load_config
from mrrig.loop.build import build_controller
from mrrig.loop.mlp import MLP, ModelError
from mrrig.loop.summary import COMMAND_JUMP_A
from mrrig.offline.metrics import error_norm
from mrrig.offline.simulation import closed_loop
from mrrig.offline.training import ONLINE_CONTINUITY_CANDIDATES
from tests.conftest import rig_config

DT_S = 0.002  # the rig's period


def _controller(tmp_path, model, **controller):
    cfg = load_config(rig_config(tmp_path, "ws://127.0.0.1:1/", model, controller=controller))
    return build_controller(cfg)


def _with_meta(tmp_path, model_path, **meta):
    d = json.loads(model_path.read_text())
    for k, v in meta.items():
        if v is None:
            d["meta"].pop(k, None)
        else:
            d["meta"][k] = v
    out = tmp_path / "edited-model.json"
    out.write_text(json.dumps(d))
    return out


def test_the_model_file_carries_the_continuity_chosen_on_its_training_rows(sim_model):
    meta = MLP.load(sim_model).meta
    assert meta["online_continuity"] in ONLINE_CONTINUITY_CANDIDATES
    assert meta["starts"] == 1  # the demo's model: one start, the weights as before


def test_the_daemon_uses_the_model_continuity_unless_the_config_sets_one(tmp_path, sim_model):
    own = MLP.load(sim_model).meta["online_continuity"]
    assert _controller(tmp_path, sim_model).continuity == own
    assert _controller(tmp_path, sim_model, continuity=0.0).continuity == 0.0
    assert _controller(tmp_path, sim_model, continuity=0.3).continuity == 0.3
    older = _with_meta(tmp_path, sim_model, online_continuity=None)
    assert _controller(tmp_path, older).continuity == 0.0  # a model without one: the root


@pytest.mark.parametrize("bad", [-0.1, "0.03", True, float("inf")])
def test_a_bad_model_continuity_is_one_line_naming_the_field(tmp_path, sim_model, bad):
    path = _with_meta(tmp_path, sim_model, online_continuity=bad)
    with pytest.raises(ModelError, match=r"edited-model.json: meta.online_continuity: expected"):
        _controller(tmp_path, path)


def _track(ctrl) -> tuple[float, int]:
    """The demo's run in closed loop at the rig's 2 ms: 15 mm at 2 Hz, the force of a
    reference damper at 0.8 + 0.5 sin(2 pi t) A (configs/rig.toml); Et and the number of
    command jumps, both after the first 0.5 s."""
    params = BoucWenParams.preset("rig-current")
    t = np.arange(0.0, 4.0, DT_S)
    x, xd, xdd = sine(t, 0.015, 2.0)
    i_ref = 0.8 + 0.5 * np.sin(2.0 * np.pi * t)
    ref = BoucWenDamper(params, substep_s=2.5e-4)
    f_des = [ref.reset(x[0], xd[0], i_ref[0])]
    f_des += [ref.step(x[k], xd[k], i_ref[k - 1], DT_S) for k in range(1, t.size)]
    res = closed_loop(ctrl, params, DT_S, x[None], xd[None], xdd[None], np.array([f_des]))
    keep = slice(round(0.5 / DT_S), None)
    jumps = int(np.sum(np.abs(np.diff(res.command[0, keep])) > COMMAND_JUMP_A))
    return error_norm(res.f_des[0, keep], res.f_act[0, keep]), jumps


def test_the_model_continuity_stops_the_jumps_at_reversals_and_tracks_as_well(tmp_path, sim_model):
    et_root, jumps_root = _track(_controller(tmp_path, sim_model, continuity=0.0))
    et_own, jumps_own = _track(_controller(tmp_path, sim_model))
    print(
        f"root: Et {et_root:.4f}, {jumps_root} jumps over {COMMAND_JUMP_A} A; "
        f"the model's continuity: Et {et_own:.4f}, {jumps_own} jumps"
    )
    assert jumps_root >= 10  # the behaviour this default removes (at about 4 reversals a second)
    assert jumps_own == 0
    assert et_own <= et_root
