"""`mrrig.offline.rnn_training`: the RNN of paper eq. 40 trained for closed-loop (parallel-mode)
use."""

import json

import numpy as np
import pytest

from damper.plant import BoucWenParams, simulate
from damper.signals import bandlimited_noise
from mrrig.loop.controllers import RNN_INPUTS, ControlInput, RecurrentInverse, rnn_features
from mrrig.offline.datasets import Series, dataset_a_training
from mrrig.offline.metrics import error_norm
from mrrig.offline.rnn_training import (
    LAGS,
    V_COLUMNS,
    Segments,
    _parallel,
    _Weights,
    holdout_blocks,
    parallel_lm,
    perturb_feedback,
    rollout,
    train_rnn,
)
from mrrig.offline.simulation import closed_loop

DT_S = 1e-3
VMAX_V = 12.0


@pytest.fixture(scope="module")
def small_a() -> Series:
    """14 s in the manner of data set A (7 blocks of 2 s: block 5 is held out)."""
    rng = np.random.default_rng(11)
    n = 14000
    t = np.arange(n) * DT_S
    x, xd, xdd = bandlimited_noise(n, DT_S, 3.0, 0.025, rng)
    v = np.maximum(bandlimited_noise(n, DT_S, 4.0, 6.0, rng)[0] + 6.0, 0.0)
    f = simulate(BoucWenParams.preset("paper-volt"), t, x, xd, v)
    return Series(t=t, x=x, xd=xd, xdd=xdd, current=v, force=f, name="small A")


@pytest.fixture(scope="module")
def noisy_fit(small_a):
    """Stage 1 only, a few epochs: a network that is not the identity on its feedback."""
    return train_rnn(small_a, seed=0, max_epochs=8, fine_tune=False)


def test_noise_perturbs_only_the_fed_back_voltages():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(20000, len(RNN_INPUTS)))
    Xn = perturb_feedback(X, 0.7, rng)
    np.testing.assert_array_equal(Xn[:, :4], X[:, :4])  # f_d(k), f_d(k-1), x(k), x(k-1)
    d = Xn[:, V_COLUMNS] - X[:, V_COLUMNS]
    assert RNN_INPUTS[V_COLUMNS] == tuple(f"v_{j}" for j in range(1, 7))
    np.testing.assert_allclose(d.std(axis=0), 0.7, rtol=0.03)
    assert abs(np.corrcoef(d[:, 0], d[:, 1])[0, 1]) < 0.03  # independent per lag
    np.testing.assert_array_equal(perturb_feedback(X, 0.0, rng), X)


def test_holdout_blocks_are_every_tenth_block_and_disjoint_from_the_fitted_ones():
    fit, held = holdout_blocks(100_000, 2000)
    assert [(s.start, s.stop) for s in held] == [
        (b * 2000, b * 2000 + 2000) for b in (5, 15, 25, 35, 45)
    ]
    covered = np.zeros(100_000, int)
    for s in fit + held:
        covered[s] += 1
    assert np.all(covered == 1)
    with pytest.raises(ValueError):
        holdout_blocks(10_000, 2000)  # 5 blocks: none to hold out at offset 5


def test_rollout_feeds_back_its_own_outputs_as_the_controller_does(small_a, noisy_fit):
    model, _ = noisy_fit
    seg = Segments.cut(small_a, [slice(1000, 1600), slice(7000, 7600)])
    v_hat = rollout(model, seg)
    ctrl = RecurrentInverse(VMAX_V, model)
    ctrl.reset(2)
    cmds = np.empty_like(v_hat)
    for k in range(seg.f.shape[1]):
        s = ControlInput(
            x=seg.x[:, k],
            xd=seg.x[:, k] * 0,
            xdd=seg.x[:, k] * 0,
            f_meas=seg.f[:, k],
            f_des=seg.f[:, k],
        )
        cmds[:, k] = ctrl.command(s)
    np.testing.assert_allclose(v_hat, cmds, rtol=0, atol=1e-12)
    # eq. 40 with the network's own past outputs as v(k-1..k-6), not the recorded voltages
    for b in range(2):
        own = np.clip(model.predict(rnn_features(seg.f[b], seg.x[b], v_hat[b])), 0, VMAX_V)
        np.testing.assert_allclose(own, v_hat[b, LAGS:], atol=1e-12)
        forced = np.clip(model.predict(rnn_features(seg.f[b], seg.x[b], seg.v[b])), 0, VMAX_V)
        assert np.max(np.abs(forced - v_hat[b, LAGS:])) > 0.1


def test_parallel_jacobian_matches_central_differences(small_a, noisy_fit):
    model, _ = noisy_fit
    seg = Segments.cut(small_a, [slice(2000, 2150), slice(9000, 9150)])
    wt = _Weights(model)
    w = wt.pack()
    v_hat, Jt = _parallel(wt, w, seg, VMAX_V, stride=1)
    assert Jt.shape == (wt.n_params, seg.f.size)
    h = 1e-6
    for p in (0, 17, wt.n_a - 1, wt.n_a + 3, wt.n_params - 1):
        wp, wm = w.copy(), w.copy()
        wp[p] += h
        wm[p] -= h
        dv = _parallel(wt, wp, seg, VMAX_V, None)[0] - _parallel(wt, wm, seg, VMAX_V, None)[0]
        fd = (dv / (2 * h) / model.out_std).T.ravel()  # sample-major, like Jt's columns
        np.testing.assert_allclose(Jt[p], fd, rtol=1e-5, atol=1e-6 * np.max(np.abs(fd)))


def test_parallel_lm_descends_the_unrolled_error(small_a, noisy_fit):
    model, _ = noisy_fit
    fit_blocks, _ = holdout_blocks(len(small_a), 2000)
    fit = Segments.cut(small_a, fit_blocks)
    # early stop on the fitted segments themselves, every sample a Jacobian row: each accepted
    # LM step must lower the parallel-mode MSE, so the last epoch is the best
    tuned, info = parallel_lm(model, fit, fit, VMAX_V, max_epochs=3, stride=1)
    assert info["best_epoch"] == info["epochs"] == 3
    assert info["held_out_mse_v2"] < 0.9 * info["held_out_mse_before_v2"]
    mse = [float(np.mean((rollout(m, fit) - fit.v) ** 2)) for m in (model, tuned)]
    assert mse == pytest.approx([info["held_out_mse_before_v2"], info["held_out_mse_v2"]])
    np.testing.assert_array_equal(tuned.in_std, model.in_std)  # only the weights move


def test_parallel_lm_returns_the_best_held_out_epoch(small_a, noisy_fit):
    model, _ = noisy_fit
    fit_blocks, held_blocks = holdout_blocks(len(small_a), 2000)
    fit, held = Segments.cut(small_a, fit_blocks[:3]), Segments.cut(small_a, held_blocks)
    tuned, info = parallel_lm(model, fit, held, VMAX_V, max_epochs=4)
    assert 0 <= info["best_epoch"] <= info["epochs"] <= 4
    assert float(np.mean((rollout(tuned, held) - held.v) ** 2)) == pytest.approx(
        info["held_out_mse_v2"]
    )
    assert info["held_out_mse_v2"] <= info["held_out_mse_before_v2"]


def test_train_rnn_keeps_eq_40_and_reports_its_procedure(small_a):
    model, info = train_rnn(small_a, seed=1, max_epochs=4)
    assert tuple(model.input_names) == RNN_INPUTS and model.output_name == "current"
    assert model.hidden == 30
    assert info["held_out_blocks"] == [(10000, 12000)]
    assert info["noise_v"] == 1.0 and 1 <= info["parallel"]["epochs"] <= 4
    for key in ("seconds", "epochs", "held_out_et", "teacher_forced_et"):
        assert np.isfinite(info[key])
    RecurrentInverse(VMAX_V, model)  # accepted by the controller


@pytest.mark.long
def test_rnn_tracks_held_out_stretches_of_data_set_a_in_closed_loop():
    """Closed loop against the plant on the held-out 2 s blocks of data set A's TRAINING signal
    (10, 30, 50 s: noise; 70 s: 6 V; 90 s: sine), never on the validation cases. The bound is
    0.1, the supervised inverse MLP's best validation Et in `mrrig bench paper`: the teacher-forced
    RNN gives 0.25-0.6 on these blocks (it drifts to 0 V or Vmax). The first 0.1 s are left
    out: the plant starts at rest (u = 0, z = 0) where the recorded force does not."""
    train = dataset_a_training()
    model, info = train_rnn(train, seed=0, max_epochs=1000)
    held = [slice(a, b) for a, b in info["held_out_blocks"]]

    def cut(a):
        return np.stack([a[s] for s in held])

    res = closed_loop(
        RecurrentInverse(VMAX_V, model),
        BoucWenParams.preset("paper-volt"),
        DT_S,
        cut(train.x),
        cut(train.xd),
        cut(train.xdd),
        cut(train.force),
    )
    et = [error_norm(res.f_des[b, 100:], res.f_act[b, 100:]) for b in range(len(held))]
    print("closed-loop Et on held-out training blocks:", np.round(et, 4))
    assert max(et) < 0.1


@pytest.mark.long
def test_bench_paper_rnn_only_trains_and_prints_the_rnn_row_alone(tmp_path, capsys):
    """`mrrig bench paper --rnn-only`: the RNN trained as the full run trains it, run in the
    paper's loop on the seven cases, its row printed beside the paper's (epochs cut to 2)."""
    from mrrig.offline.bench.paper import PAPER_TABLE_6, main

    out = tmp_path / "rnn.json"
    assert main(["--rnn-only", "--epochs", "2", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert list(r["table6"]) == ["rnn"] and len(r["table6"]["rnn"]) == 7
    assert all(np.isfinite(r["table6"]["rnn"]))
    assert r["training"]["rnn"]["epochs"] <= 2 and r["training"]["rnn"]["parallel"]["epochs"] <= 2
    lines = capsys.readouterr().out.splitlines()
    row, paper = lines[3], lines[4]
    assert row.startswith("RNN (eq. 40)") and row.split()[-7:] == [
        f"{e:.4f}" for e in r["table6"]["rnn"]
    ]
    assert paper.split()[-7:] == [f"{e:.4f}" for e in PAPER_TABLE_6["rnn"]]
    assert any("what differs from the paper" in line for line in lines)
    assert lines[-1].startswith("RNN trained on data set A (seed 0)")
