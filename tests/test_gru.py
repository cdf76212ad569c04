"""Issue 36, item 4: a recurrent (GRU) forward model, trained with torch, run and inverted by the
daemon in numpy (mrrig/loop/gru.py, mrrig/offline/training/gru.py).

The numpy cell gives torch's numbers; the per-frame solve hits a reachable force and clamps an
unreachable one to the rig's range; the state the controller carries is the model run over
the commands it sent; a GRU file whose command is not in the rig's unit is refused in one line;
the daemon inverting a GRU trained on the simulated matrix tracks the simulator's force
(tests/test_gru_tracking.py: a process module)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from mrrig.config import load_config
from mrrig.loop.build import build_controller
from mrrig.loop.controllers import ControllerSettings, make_controller
from mrrig.loop.gru import GRUModel, GruTracker, affine_solve
from mrrig.loop.mlp import ModelError
from mrrig.loop.model_fit import COST_BUDGET_S, frame_cost_s
from mrrig.loop.state_inversion import GruInversion
from mrrig.loop.twin_model import load_forward_model
from mrrig.offline.datasets import dataset_b
from mrrig.offline.training import measured_series
from mrrig.offline.training.gru import (
    export_gru,
    fit_gru,
    gru_forces,
    model_inputs,
)
from tests.conftest import rig_config

DT_S = 0.002
I_MAX_A = 1.8


@pytest.fixture(scope="module")
def small_series():
    """A small simulated characterization matrix (16 runs of 1 s at 500 Hz, constant current)."""
    return measured_series(
        dataset_b(amplitudes_m=(0.01, 0.02), freqs_hz=(2.0, 4.0), currents_a=(0.0, 0.6, 1.2, 1.8))
    )


@pytest.fixture(scope="module", params=[False, True], ids=["u-read-out", "u-in-cell"])
def model(request, small_series, tmp_path_factory):
    """A GRU of 8 units fitted briefly to it (u in the read-out alone, or in the cell too),
    written and read back as the daemon reads it."""
    m, _ = fit_gru(small_series, seed=0, hidden=8, max_epochs=120, u_in_cell=request.param)
    path = tmp_path_factory.mktemp("gru") / "gru.json"
    m.save(path)
    back = load_forward_model(path)
    assert isinstance(back, GRUModel)
    return back


@pytest.mark.parametrize("n_cell", [3, 4])  # u in the read-out alone, or in the cell too
def test_the_numpy_gru_gives_torchs_numbers(n_cell):
    torch = pytest.importorskip("torch")
    torch.manual_seed(3)
    net = torch.nn.GRU(n_cell, 10, batch_first=True).double()
    head, gain = torch.nn.Linear(10, 1).double(), torch.nn.Linear(10, 1).double()
    rng = np.random.default_rng(0)
    mean, std = np.array([0.0, 0.01, -0.2, 0.9]), np.array([0.01, 0.1, 3.0, 0.6])
    X = mean + std * rng.normal(size=(300, 4)) * 2.0
    meta = {"current_input": "lagged", "lag_tau_s": 0.005}
    m = export_gru(
        net,
        head,
        gain,
        in_mean=mean,
        in_std=std,
        out_mean=120.0,
        out_std=400.0,
        command_unit="A",
        meta=meta,
    )
    with torch.no_grad():
        z = torch.from_numpy((X - mean) / std)[None]
        h = net(z[..., :n_cell])[0]
        want = (120.0 + 400.0 * (head(h) + z[..., 3:4] * gain(h)))[0, :, 0].numpy()
    got = m.predict(X)
    assert np.max(np.abs(got - want)) <= 1e-6 * 400.0
    assert np.std(want) > 10.0  # a force that moves: not a trivial agreement


def test_the_block_holdout_is_scored_from_the_runs_start(small_series, model):
    rows, y, f = gru_forces(model, small_series)
    assert rows.size == len(small_series) and np.isfinite(f).all()
    assert model.metrics["holdout_et"] < 0.5  # a model, if a briefly fitted one


def _tracker(model: GRUModel, frames: int, command_a: float):
    """A tracker advanced `frames` frames on a 3 Hz sine, `command_a` held: (tracker, motion
    at the next sample)."""
    t = np.arange(frames + 1) * DT_S
    w = 2 * np.pi * 3.0
    x, xd, xdd = 0.015 * np.sin(w * t), 0.015 * w * np.cos(w * t), -0.015 * w * w * np.sin(w * t)
    g = GruTracker(model, DT_S, I_MAX_A)
    for k in range(frames):
        g.advance(float(x[k]), float(xd[k]), float(xdd[k]))
        g.command = command_a
    return g, (float(x[frames]), float(xd[frames]), float(xdd[frames]))


@pytest.mark.parametrize("frames", [20, 60, 95])
def test_the_gru_inversion_hits_a_reachable_force(model, frames):
    g, nxt = _tracker(model, frames, 0.9)
    for want in (0.3, 1.4):
        target = g.force_next(*nxt, want)
        g.command = 0.9
        got = g.solve(target, *nxt)
        assert 0.0 < got < I_MAX_A
        assert g.force_next(*nxt, got) == pytest.approx(target, abs=1e-6 * model.out_std)
    assert abs(g.force_next(*nxt, 0.3) - g.force_next(*nxt, 1.4)) > 10.0  # distinct forces


def test_the_gru_inversion_clamps_an_unreachable_force_to_the_rigs_range(model):
    g, nxt = _tracker(model, 20, 0.9)
    ends = {c: g.force_next(*nxt, c) for c in (0.0, I_MAX_A)}
    high, low = max(ends, key=ends.get), min(ends, key=ends.get)
    assert g.solve(max(ends.values()) + 500.0, *nxt) == high
    assert g.solve(min(ends.values()) - 500.0, *nxt) == low


def test_the_state_carried_across_frames_is_the_model_run_over_the_commands_sent(model):
    n = 300
    t = np.arange(n + 1) * DT_S
    w = 2 * np.pi * 2.5
    x, xd, xdd = 0.012 * np.sin(w * t), 0.012 * w * np.cos(w * t), -0.012 * w * w * np.sin(w * t)
    # the damper's force at mid current, a reachable target most of the time
    f_des = model.predict(np.column_stack([x, xd, xdd, np.full(n + 1, 0.9)]))
    f_des *= 1.0 + 0.4 * np.sin(2 * np.pi * 1.5 * t)
    ctrl = make_controller(
        "network_inversion", ControllerSettings(I_MAX_A, DT_S, model=model, ahead=True)
    )
    assert isinstance(ctrl, GruInversion)
    ctrl.reset(1)
    commands, forces = [], []
    for k in range(n):
        commands.append(ctrl.command_one(x[k], xd[k], xdd[k], 0.0, f_des[k], f_des[k + 1]))
        lane = ctrl.lanes[0]
        forces.append(float(model.read_out(lane.h, (lane.u - model.in_mean[3]) / model.in_std[3])))
    # eq. 36 over the commands sent, from the coil off; the first frame's u is 0
    lag = -np.expm1(-DT_S / model.lag_tau_s)
    u = np.zeros(n)
    for k in range(1, n):
        u[k] = u[k - 1] + lag * (commands[k - 1] - u[k - 1])
    want = model.predict(np.column_stack([x[:n], xd[:n], xdd[:n], u]))
    assert np.max(np.abs(np.array(forces) - want)) <= 1e-9 * model.out_std
    assert len(set(np.round(commands, 6))) > 100  # the commands varied


def test_the_daemon_inverts_a_gru_in_amperes_and_refuses_one_in_volts(model, tmp_path):
    amps = tmp_path / "gru-a.json"
    model.save(amps)
    ctrl = build_controller(load_config(rig_config(tmp_path, "ws://127.0.0.1:1/", amps)))
    assert isinstance(ctrl, GruInversion) and ctrl.name == "network_inversion"
    assert ctrl.ahead and ctrl.feedback_tau_s == 0.0  # configs/rig.toml's, as for a network
    cost_s, _ = frame_cost_s(ctrl, DT_S)
    print(f"GRU inversion: work per frame {cost_s * 1e6:.0f} us (median)")
    assert cost_s <= COST_BUDGET_S
    doc = json.loads(amps.read_text())
    doc["input_units"][3] = "V"
    volts = tmp_path / "gru-v.json"
    volts.write_text(json.dumps(doc))
    with pytest.raises(ModelError) as err:
        build_controller(load_config(rig_config(tmp_path, "ws://127.0.0.1:1/", volts)))
    assert re.fullmatch(
        r".*gru-v\.json: input_units\[3\] \(current\): expected A .*'V'", str(err.value)
    )
    doc["input_units"][3] = "A"
    doc["meta"]["sample_period_s"] = 1 / 3004.8  # the state steps once a sample: at 3 kHz
    fast = tmp_path / "gru-3khz.json"
    fast.write_text(json.dumps(doc))
    with pytest.raises(ModelError, match=r"gru-3khz\.json: meta.sample_period_s: a recurrent st"):
        build_controller(load_config(rig_config(tmp_path, "ws://127.0.0.1:1/", fast)))
    doc["meta"]["current_input"] = "sideways"
    volts.write_text(json.dumps(doc))
    with pytest.raises(ModelError, match=r"gru-v\.json: field 'meta.current_input': must be one"):
        load_forward_model(volts)


def test_a_gru_takes_the_exact_solve_without_adaptation(model):
    with pytest.raises(ValueError, match="method 'flow': a GRU forward model is solved exactly"):
        make_controller(
            "network_inversion", ControllerSettings(I_MAX_A, model=model, method="flow")
        )


def test_continuity_pulls_the_solve_toward_the_present_u_as_network_inversions_does(model):
    """The exact solve's objective w_f (f(u) - target)^2 + w_c (u - u_prev)^2
    (mrrig/loop/inversion.py), minimised in closed form for the affine read-out."""
    args = (100.0, 400.0, 0.9, 500.0)  # f_m, gain, u_mean, target: the root u = 1.9
    assert affine_solve(*args, 0.5, 0.0, 3.0, 1.0, 0.0) == pytest.approx(1.9)
    u = affine_solve(*args, 0.5, 0.0, 3.0, 1.0, 160000.0)  # w_c = w_f gain^2: halfway
    assert u == pytest.approx(1.2)
    assert affine_solve(*args, 0.5, 0.0, 1.8, 1.0, 0.0) == 1.8  # out of reach: the end
    if model.u_in_cell:
        with pytest.raises(ValueError, match="continuity: a GRU with u in its cell"):
            make_controller(
                "network_inversion", ControllerSettings(I_MAX_A, model=model, continuity=0.03)
            )
    else:
        assert model.meta["online_continuity"] in (0.0, 0.01, 0.03, 0.1, 0.3, 1.0)


def test_model_inputs_are_causal(small_series):
    """u at a sample depends on commands sent before it: the commanded input is the command
    held over the period before the sample (a run's first sample: its own)."""
    X = model_inputs(small_series, "commanded", 1.0)
    c = small_series.current
    assert X[0, 3] == c[0] and np.array_equal(X[1:450, 3], c[0:449])
