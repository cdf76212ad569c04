"""Issue 43, item 2: the grey-box forward model, the identified Bouc-Wen twin plus a small
network on its residual (mrrig/loop/greybox.py, mrrig/offline/training/greybox.py), inverted by
the daemon like the other kinds (the residual's derivative in u included) and in `mrrig
train`'s kinds search. Pure numerics on tiny data: seconds."""

from __future__ import annotations

import json
import math
from dataclasses import astuple, replace

import numpy as np
import pytest

from damper.plant import BoucWenParams, simulate
from damper.plant_file import Plant
from mrrig.cli.train_report import format_kinds
from mrrig.loop.controllers import ControllerSettings, make_controller
from mrrig.loop.greybox import (
    RESIDUAL_INPUTS,
    GreyBoxModel,
    GreyBoxTracker,
    force_and_du,
    twin_force_du,
)
from mrrig.loop.mlp import MLP, ModelError
from mrrig.loop.state_inversion import TwinInversion
from mrrig.loop.twin_model import load_forward_model
from mrrig.offline.datasets import Series
from mrrig.offline.evaluate import evaluate_stateful
from mrrig.offline.identify.fit import Run
from mrrig.offline.training.greybox import fit_residual, greybox_run_forces
from mrrig.offline.training.kind_choice import choose_kind
from mrrig.offline.training.kinds import GREYBOX, TWIN, greybox_kind, model_kinds, twin_kind
from tests.data_files import write_tidy

DT_S = 0.002
I_MAX = 2.0
PARAMS = BoucWenParams.preset("paper-volt")
PLANT = Plant(PARAMS, offset_n=12.5, command_unit="A")


def _net(seed: int = 1, hidden: int = 6) -> MLP:
    """A residual network of random weights, large enough to bend the twin's force in u."""
    rng = np.random.default_rng(seed)
    return MLP(
        list(RESIDUAL_INPUTS),
        ["m", "m", "A", "m", "m/s"],
        "force_residual",
        "N",
        np.array([0.0, 0.0, 1.0, 0.0, 0.0]),
        np.array([2e-3, 2e-3, 0.6, 6e-3, 0.08]),
        0.0,
        150.0,
        rng.normal(size=(hidden, 5)),
        rng.normal(size=hidden),
        rng.normal(size=hidden) / hidden,
        0.1,
    )


MODEL = GreyBoxModel(PLANT, "test", _net(), 1e-3)


def _tracker_at(frames: int, command: float) -> tuple[GreyBoxTracker, np.ndarray, np.ndarray]:
    t = np.arange(frames + 2) * DT_S
    w = 2 * np.pi * 2.0
    x, xd = 0.006 * np.sin(w * t), 0.006 * w * np.cos(w * t)
    tr = GreyBoxTracker(MODEL, DT_S, I_MAX)
    for k in range(frames + 1):
        tr.advance(float(x[k]), float(xd[k]))
        tr.command = command
    return tr, x, xd


def test_the_derivative_in_u_matches_finite_differences():
    rng = np.random.default_rng(0)
    z = rng.uniform(-3e-3, 3e-3, 20)
    y = rng.uniform(-5e-3, 5e-3, 20)
    u = rng.uniform(0.0, I_MAX, 20)
    x = rng.uniform(-8e-3, 8e-3, 20)
    xd = rng.uniform(-0.1, 0.1, 20)
    f, d = force_and_du(MODEL, z, y, u, x, xd)
    h = 1e-6
    fd = force_and_du(MODEL, z, y, u + h, x, xd)[0] - force_and_du(MODEL, z, y, u - h, x, xd)[0]
    fd /= 2 * h
    np.testing.assert_allclose(d, fd, rtol=1e-5, atol=1e-3)
    # the residual's share is not negligible: the twin's own derivative differs from the total
    twin_d = twin_force_du(astuple(PARAMS), z, y, u, x, xd)
    assert np.max(np.abs(d - twin_d)) > 10.0


@pytest.mark.parametrize("frames, command, wanted", [(40, 0.9, 1.3), (90, 0.3, 0.05)])
def test_the_inversion_returns_the_command_that_reproduces_a_desired_force(frames, command, wanted):
    tr, x, xd = _tracker_at(frames, command)
    x1, xd1 = float(x[frames + 1]), float(xd[frames + 1])
    # the force the grey-box gives one period on with `wanted` sent now (the state stepped
    # with the command held, u through eq. 36 over the period)
    d = tr.damper
    z, y, u = d.state
    d.step(x1, xd1, tr.command, DT_S)
    z1, y1, _ = d.state
    d.set_state((z, y, u), tr.x, tr.xd)
    u1 = u + tr.lag * (wanted - u)
    target = float(force_and_du(MODEL, z1, y1, u1, x1, xd1)[0][0])
    got = tr.solve(target, x1, xd1)
    assert got == pytest.approx(wanted, abs=1e-6)
    assert tr.damper.state == (z, y, u)  # the solve leaves the state where it was


def test_a_force_out_of_reach_gets_the_nearest_end_of_the_range():
    tr, x, xd = _tracker_at(40, 0.5)
    x1, xd1 = float(x[41]), float(xd[41])
    f_lo = tr.force(x1, xd1, 0.0)
    f_hi = tr.force(x1, xd1, I_MAX)
    far = max(f_lo, f_hi) + 1e5 if f_hi > f_lo else min(f_lo, f_hi) - 1e5
    assert tr.solve(far, x1, xd1) == I_MAX


def test_the_file_round_trips_and_the_daemon_inverts_it_with_its_residual(tmp_path):
    path = tmp_path / "gb.json"
    MODEL.save(path)
    loaded = load_forward_model(path)
    assert isinstance(loaded, GreyBoxModel)
    f0, d0 = force_and_du(MODEL, 1e-3, 2e-3, 0.7, 4e-3, 0.05)
    f1, d1 = force_and_du(loaded, 1e-3, 2e-3, 0.7, 4e-3, 0.05)
    assert (f0, d0) == (f1, d1)
    ctrl = make_controller(
        "network_inversion", ControllerSettings(I_MAX, dt_s=DT_S, model=loaded, ahead=True)
    )
    assert isinstance(ctrl, TwinInversion)
    assert isinstance(ctrl.lanes[0], GreyBoxTracker)
    _, x, xd = _tracker_at(1, 0.0)
    cmd = [ctrl.command_one(float(x[k]), float(xd[k]), 0.0, 0.0, 200.0, 200.0) for k in range(3)]
    assert all(0.0 <= c <= I_MAX for c in cmd)
    doc = json.loads(path.read_text())
    doc["residual"]["input_names"] = ["x", "xd", "xdd", "current", "z"]
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelError, match="residual: inputs must be") as exc:
        load_forward_model(path)
    assert "\n" not in str(exc.value)


def test_the_residual_network_learns_what_the_twin_misses():
    """The second stage on a twin whose damping is off by 30 % and a friction it lacks."""
    truth = BoucWenParams(**{**PARAMS.__dict__, "c0a": PARAMS.c0a * 1.3})
    t = np.arange(0, 2.0, DT_S)
    runs, val = [], []
    for a, f, v in [(0.01, 1.0, 0.5), (0.008, 2.0, 1.0), (0.012, 1.5, 1.5)]:
        x, xd = a * np.sin(2 * np.pi * f * t), a * 2 * np.pi * f * np.cos(2 * np.pi * f * t)
        cmd = np.full(t.size, v)
        force = simulate(truth, t, x, xd, cmd, 1e-4) + 20 * np.tanh(xd / 0.05)
        runs.append(Run(t, x, xd, cmd, force))
        val.append(np.arange(t.size) >= 0.85 * t.size)
    model, _ = fit_residual(Plant(PARAMS, 0.0, "V"), runs, val, max_epochs=200)
    twin_only = GreyBoxModel(Plant(PARAMS, 0.0, "V"), residual=_net_zero(), substep_s=1e-3)

    def et(m: GreyBoxModel) -> float:
        warm = 100  # scored after the warm-up (`identify.fit.warm_rows`: 0.2 s)
        f = np.concatenate([f[warm:] for f in greybox_run_forces(m, runs)])
        y = np.concatenate([r.force[warm:] for r in runs])
        return float(np.sqrt(np.mean((y - f) ** 2)) / np.std(y))

    assert et(model) < 0.2 * et(twin_only)


def _net_zero() -> MLP:
    n = _net()
    return MLP(
        n.input_names, ["m", "m", "V", "m", "m/s"], n.output_name, n.output_unit,
        n.in_mean, n.in_std, 0.0, 1.0, n.W1, n.b1, np.zeros(n.hidden), 0.0,
    )  # fmt: skip


def test_the_kind_choice_scores_the_grey_box_beside_the_twin_and_train_prints_it():
    """Three tests of the twin's own force plus a friction it lacks: the grey-box kind (here
    on a twin given, not identified, to keep the test to seconds) is scored on the tests left
    out beside the twin, takes less error than the twin alone, and train's kinds lines show
    it; `model_kinds` (what `mrrig train` searches) builds it."""
    t = np.arange(0, 1.5, DT_S)
    parts = []
    for k, (a, f, v) in enumerate([(0.01, 1.0, 0.4), (0.008, 2.0, 1.0), (0.012, 1.5, 1.6)]):
        x, xd = a * np.sin(2 * np.pi * f * t), a * 2 * np.pi * f * np.cos(2 * np.pi * f * t)
        cmd = np.full(t.size, v)
        force = simulate(PARAMS, t, x, xd, cmd, 1e-4) + 30 * np.tanh(xd / 0.05) + 12.5
        parts.append((t, x, xd, np.gradient(xd, t), cmd, force, np.full(t.size, k)))
    series = Series(*(np.concatenate([p[j] for p in parts]) for j in range(7)))
    tests = np.repeat(np.arange(3), t.size)
    names = ["a.csv", "b.csv", "c.csv"]
    gb = greybox_kind(lambda _s: PLANT, holdout_fraction=0.15, seed=0, i_max=I_MAX)
    twin = replace(twin_kind(holdout_fraction=0.15, i_max=I_MAX), fit=lambda _s: PLANT)
    # the choice by Et alone: this grey-box's work per frame (about 250 us of the daemon's
    # 300 here, idle) went over the budget with the other worker's tests beside it (CI), and
    # the twin won; the budget's own rule is tests/test_features_auto_kinds.py's
    best, rep = choose_kind(
        series, tests, names, [gb, twin], holdout_fraction=0.15, cost_budget_s=math.inf
    )
    k = {r["kind"]: r for r in rep["kinds"]}
    assert set(k) == {GREYBOX, TWIN}
    assert k[GREYBOX]["et"] < 0.5 * k[TWIN]["et"]
    assert best.name == GREYBOX and isinstance(best.model, GreyBoxModel)
    text = "\n".join(format_kinds(rep))
    print(text)
    assert "grey-box: the Bouc-Wen twin and a 8-hidden network on its residual" in text
    search = {"candidates": []}
    kinds, _, _ = model_kinds(
        series, search, seed=0, max_epochs=5, holdout_fraction=0.15, i_max=I_MAX
    )
    assert GREYBOX in [kd.name for kd in kinds]


def test_evaluate_scores_a_grey_box_file_with_its_residual(tmp_path):
    """`mrrig evaluate` on a grey-box file runs the twin and its network (not the twin alone)."""
    t = np.arange(0, 1.0, DT_S)
    x, xd = 0.008 * np.sin(2 * np.pi * 2 * t), 0.008 * 4 * np.pi * np.cos(2 * np.pi * 2 * t)
    cmd = np.full(t.size, 0.8)
    run = Run(t, x, xd, cmd, np.zeros(t.size))
    force = greybox_run_forces(MODEL, [run])[0]  # the data is the grey-box's own force
    series = Series(t, x, xd, np.gradient(xd, t), cmd, force, np.zeros(t.size, int))
    csv = tmp_path / "own.csv"
    write_tidy(csv, series)
    path = tmp_path / "gb.json"
    MODEL.save(path)
    numbers, _ = evaluate_stateful(load_forward_model(path), path, [csv])
    assert numbers["kind"] == "grey-box"
    assert numbers["forward"]["et"] < 0.05  # the twin alone misses the residual's share


def test_identify_refuses_to_map_a_grey_box_file_in_one_line(tmp_path, capsys):
    """`mrrig identify --map-model` maps a twin's or a network's command from V to A; a grey-box
    file's residual network takes the command too, and was written out without it."""
    from mrrig.cli.identify import main

    path = tmp_path / "gb.json"
    MODEL.save(path)
    out = tmp_path / "mapped.json"
    with pytest.raises(SystemExit) as exc:
        main(["--map-model", str(path), "--out", str(out)])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "grey-box model" in err and str(path) in err
    assert not out.exists()
