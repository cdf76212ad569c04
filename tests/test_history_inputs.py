"""History inputs of the forward network (issue 5): previous samples of the motion (and, where
chosen, of the current) after (x, xd, xdd, current), in training, in the model file, in the
network-inversion controller (scalar and batch paths) and in the daemon's loop."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mrrig.cli.main import main as mrrig_main
from mrrig.loop.build import build_controller
from mrrig.loop.controllers import ControlInput, NetworkInversion, SupervisedInverse
from mrrig.loop.mlp import MLP
from mrrig.loop.samples import RigState
from mrrig.loop.slew import SlewLimit
from mrrig.offline.datasets import Series
from mrrig.offline.training import (
    COIL_LAG_TAU_S,
    INPUT_NAMES,
    feature_names,
    feature_rows,
    features,
    measured_series,
    train_and_validate,
    train_forward,
)
from tests.data_files import write_tidy
from tests.rig_harness import ScriptedRig

EPOCHS = 15
I_MAX_A = 1.2


@pytest.fixture(scope="module")
def history_model(small_truth, tmp_path_factory) -> MLP:
    """A forward model with 2 samples of (x, xd) history, saved and loaded back."""
    model, _ = train_forward(small_truth, seed=1, max_epochs=EPOCHS, history_samples=2)
    path = tmp_path_factory.mktemp("history") / "fwd-h2.json"
    model.save(path)
    back = MLP.load(path)
    back.meta["path"] = str(path)
    return back


def _hand_series(run_ids: bool = True) -> Series:
    """Two runs (5 and 4 samples) whose every value says which sample it is."""
    k = np.arange(9.0)
    t = np.concatenate([np.arange(5), np.arange(4)]) * 0.002
    return Series(
        t=t,
        x=k,
        xd=10.0 + k,
        xdd=20.0 + k,
        current=30.0 + k,
        force=40.0 + k,
        run_id=np.array([0, 0, 0, 0, 0, 1, 1, 1, 1]) if run_ids else None,
    )


def _random_model(names: list[str], seed: int = 0, output: str = "force") -> MLP:
    rng = np.random.default_rng(seed)
    n, h = len(names), 6
    return MLP(
        input_names=names,
        input_units=["-"] * n,
        output_name=output,
        output_unit="N" if output == "force" else "A",
        in_mean=np.zeros(n),
        in_std=np.ones(n),
        out_mean=0.0,
        out_std=100.0,
        W1=rng.normal(0.0, 0.5, (h, n)),
        b1=rng.normal(0.0, 0.5, h),
        W2=rng.normal(0.0, 1.0, h),
        b2=0.0,
    )


def _instant(x, xd, xdd, f_des) -> ControlInput:
    a = [np.atleast_1d(np.asarray(v, dtype=float)) for v in (x, xd, xdd, f_des)]
    return ControlInput(a[0], a[1], a[2], np.zeros_like(a[0]), a[3])


# ------------------------------------------------------------------------------------ features
def test_history_of_two_gives_exactly_the_previous_samples_within_each_run():
    s = _hand_series()
    X, y = features(s, history_samples=2)
    rows = np.array([2, 3, 4, 7, 8])  # the first 2 samples of each run have no history
    np.testing.assert_array_equal(feature_rows(s, 2), rows)
    expected = np.column_stack(
        [s.x[rows], s.xd[rows], s.xdd[rows], s.current[rows]]
        + [s.x[rows - 1], s.xd[rows - 1], s.x[rows - 2], s.xd[rows - 2]]
    )
    np.testing.assert_array_equal(X, expected)
    np.testing.assert_array_equal(y, s.force[rows])
    # no row reaches back into the other run: every history value is from its own run
    run_of = s.run_id[np.searchsorted(s.x, X[:, [0, 4, 6]])]
    assert np.all(run_of == run_of[:, :1])
    # without run ids, a run starts wherever time does not increase: the same rows
    X2, y2 = features(_hand_series(run_ids=False), history_samples=2)
    np.testing.assert_array_equal(X2, X)
    np.testing.assert_array_equal(y2, y)


def test_history_names_are_signal_and_samples_back_with_the_signals_units():
    names, units = feature_names(2, ("x", "xd"))
    assert names == INPUT_NAMES + ("x_1", "xd_1", "x_2", "xd_2")
    assert units == ("m", "m/s", "m/s^2", "A", "m", "m/s", "m", "m/s")
    assert feature_names(0) == (INPUT_NAMES, ("m", "m/s", "m/s^2", "A"))
    names, units = feature_names(1, ("xdd", "current"))
    assert names[4:] == ("xdd_1", "current_1") and units[4:] == ("m/s^2", "A")


def test_past_current_is_the_lagged_current_when_the_current_input_is_lagged(small_truth):
    s = replace(small_truth, current=np.where(small_truth.t > 0.2, 1.0, 0.2))  # steps in-run
    full, _ = features(s, "lagged", COIL_LAG_TAU_S)
    X, _ = features(s, "lagged", COIL_LAG_TAU_S, history_samples=1, history_signals=("current",))
    rows = feature_rows(s, 1)
    np.testing.assert_array_equal(X[:, 3], full[rows, 3])
    np.testing.assert_array_equal(X[:, 4], full[rows - 1, 3])
    assert np.any(X[:, 4] != X[:, 3])


# ---------------------------------------------------------------------------------- the model
def test_history_model_round_trips_with_its_options(history_model, small_truth):
    m = history_model
    assert m.input_names == ["x", "xd", "xdd", "current", "x_1", "xd_1", "x_2", "xd_2"]
    assert m.input_units[4:] == ["m", "m/s", "m", "m/s"]
    assert m.meta["history_samples"] == 2 and m.meta["history_signals"] == ["x", "xd"]
    assert m.meta["n_samples"] == len(small_truth) - 2 * 12  # 12 runs, 2 samples each dropped
    X, _ = features(small_truth, history_samples=2)
    original, _ = train_forward(small_truth, seed=1, max_epochs=EPOCHS, history_samples=2)
    np.testing.assert_array_equal(m.predict(X[:50]), original.predict(X[:50]))


def _run(s: Series, run: int, n: int) -> Series:
    """The first n samples of one run."""
    rows = np.flatnonzero(s.run_id == run)[:n]
    return Series(
        t=s.t[rows],
        x=s.x[rows],
        xd=s.xd[rows],
        xdd=s.xdd[rows],
        current=s.current[rows],
        force=s.force[rows],
        run_id=s.run_id[rows],
    )


@pytest.mark.parametrize("continuity", [0.0, None])
def test_network_inversion_with_history_hits_the_target_on_the_scalar_and_batch_paths(
    history_model, small_truth, continuity
):
    """Three runs side by side: the controller's features are the training features (from the
    third sample on); with continuity 0 the model's force at its current is the target; one
    batch of three lanes gives the currents of three single-lane (scalar-path) controllers
    (also with the controller's default continuity)."""
    m = history_model
    opts = {} if continuity is None else {"continuity": continuity}
    runs = [1, 6, 10]
    n = 80
    lanes = [_run(small_truth, r, n) for r in runs]
    rng = np.random.default_rng(3)
    i_true = rng.uniform(0.1, 1.1, (len(runs), n))
    f_des = np.zeros((len(runs), n))
    for j, s in enumerate(lanes):
        X, _ = features(s, history_samples=2)  # rows 2 .. n-1
        X[:, 3] = i_true[j, 2:]
        f_des[j, 2:] = m.predict(X)
    batch = NetworkInversion(I_MAX_A, m, **opts)
    batch.reset(len(runs))
    single = [NetworkInversion(I_MAX_A, m, **opts) for _ in runs]
    for c in single:
        c.reset(1)
    got_b, got_s, force_b, force_ref = (np.zeros((len(runs), n)) for _ in range(4))
    for k in range(n):
        s = _instant(
            *(np.array([getattr(lane, f)[k] for lane in lanes]) for f in ("x", "xd", "xdd")),
            f_des[:, k],
        )
        got_b[:, k] = batch.command(s)
        force_b[:, k] = batch.model_force(s, got_b[:, k])
        for j, c in enumerate(single):
            sj = _instant(s.x[j], s.xd[j], s.xdd[j], s.f_des[j])
            got_s[j, k] = c.command(sj)[0]
    for j, s in enumerate(lanes):
        X, _ = features(s, history_samples=2)
        X[:, 3] = got_b[j, 2:]
        force_ref[j, 2:] = m.predict(X)
    scored = np.s_[:, 2:]
    # model_force uses the training features (the history of the same lane)
    np.testing.assert_allclose(force_b[scored], force_ref[scored], rtol=0, atol=1e-9)
    if continuity == 0.0:
        np.testing.assert_allclose(force_b[scored], f_des[scored], rtol=0, atol=1e-3)
    np.testing.assert_allclose(got_s, got_b, rtol=0, atol=1e-6)


def test_history_before_enough_samples_is_the_first_sample_and_past_current_its_own_command():
    m = _random_model(["x", "xd", "xdd", "current", "x_1", "current_1", "x_2", "current_2"])
    m.W1[:, 3], m.W2 = np.abs(m.W1[:, 3]), np.abs(m.W2)  # force rising with the current
    c = NetworkInversion(2.0, m, continuity=0.0)
    c.reset(2)
    xs = [np.array([0.001, -0.002]), np.array([0.003, 0.004]), np.array([0.005, 0.006])]
    cmds = []
    for k, x in enumerate(xs):
        s = _instant(x, 0.1 * x, 10.0 * x, np.array([160.0, 230.0]))
        cmds.append(c.command(s))
        probe = np.array([0.7, 1.3])
        # oldest first: the run's first instant stands in for the missing ones, past command 0 A
        past = [(xs[0], np.zeros(2))] * 2 + [(xs[j], cmds[j]) for j in range(k)]
        (x1, i1), (x2, i2) = past[-1], past[-2]
        rows = np.column_stack([x, 0.1 * x, 10.0 * x, probe, x1, i1, x2, i2])
        np.testing.assert_array_equal(c.model_force(s, probe), m.predict(rows))
    assert np.all((np.array(cmds[:2]) > 0.0) & (np.array(cmds[:2]) < 2.0))  # not 0 A: seen


def test_supervised_inverse_takes_the_same_motion_history(small_truth):
    fwd, sup, r = train_and_validate(
        small_truth, seed=0, max_epochs=5, history_samples=1, history_signals=("x", "current")
    )
    assert fwd.input_names[4:] == ["x_1", "current_1"]
    assert sup is not None and sup.input_names == ["x", "xd", "xdd", "f_des", "x_1"]
    assert sup.meta["history_signals"] == ["x"]
    ctrl = SupervisedInverse(I_MAX_A, sup)
    ctrl.reset(1)
    lane = small_truth.run_id == 4
    for k in range(3):
        s = _instant(
            small_truth.x[lane][k],
            small_truth.xd[lane][k],
            small_truth.xdd[lane][k],
            small_truth.force[lane][k],
        )
        i = ctrl.command(s)
    X = np.column_stack([s.x, s.xd, s.xdd, s.f_des, [small_truth.x[lane][1]]])
    assert i[0] == pytest.approx(float(np.clip(sup.predict(X)[0], 0.0, I_MAX_A)), abs=1e-12)
    assert math.isfinite(r["supervised"]["current_rmse_a"])


# -------------------------------------------------------------------------------- evaluation
@pytest.mark.parametrize("history", [0, 2])
def test_history_is_evaluated_on_held_out_data(small_b, history, capsys):
    """Kalman-estimated kinematics of the noisy small matrix; the numbers are printed (no
    assertion on which is better: with 15 epochs on 2400 samples it is not robust)."""
    s = measured_series(small_b)
    fwd, _, r = train_and_validate(
        s, seed=0, max_epochs=EPOCHS, supervised=False, history_samples=history
    )
    with capsys.disabled():
        print(
            f"\nhistory {history}: held-out forward Et {r['forward']['et']:.4f}, inverse-current "
            f"RMSE {r['network_inversion']['current_rmse_a']:.4f} A ({r['n_val']} samples)"
        )
    assert fwd.n_in == 4 + 2 * history
    assert r["history_samples"] == history
    assert 0.0 < r["forward"]["et"] < 0.5
    assert math.isfinite(r["network_inversion"]["current_rmse_a"])


# ------------------------------------------------------------------------------------ errors
@pytest.mark.parametrize(
    "options, words",
    [
        (["--history", "-1"], "--history must be >= 0"),
        (["--history", "1", "--history-signals", "x,force"], "'force': unknown"),
        (["--history", "1", "--history-signals", "x,x"], "'x': given twice"),
        (["--history-signals", "x"], "--history-signals needs --history"),
    ],
)
def test_bad_history_option_gives_one_line_error(tmp_path, small_truth, capsys, options, words):
    data = tmp_path / "char.csv"
    write_tidy(data, small_truth)
    rc = mrrig_main(["train", str(data), "--out", str(tmp_path / "m.json"), *options])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.startswith("error: ") and words in err and "\n" not in err
    assert not (tmp_path / "m.json").exists()


@pytest.mark.parametrize(
    "names, words",
    [
        (["x", "xd", "xdd", "current", "x_0"], "'x_0'"),
        (["x", "xd", "xdd", "current", "speed_1"], "'speed_1'"),
        (["x", "xd", "xdd", "current", "x_01"], "'x_01'"),
        (["xd", "x", "xdd", "current", "x_1"], "start with x, xd, xdd, current"),
    ],
)
def test_network_inversion_refuses_inputs_that_are_not_history_inputs(names, words):
    with pytest.raises(ValueError, match=words) as exc:
        NetworkInversion(2.0, _random_model(names))
    assert "\n" not in str(exc.value)


def test_supervised_inverse_refuses_past_currents():
    names = ["x", "xd", "xdd", "f_des", "current_1"]
    with pytest.raises(ValueError, match="no past currents"):
        SupervisedInverse(2.0, _random_model(names, output="current"))


def test_feature_options_are_checked_in_the_library(small_truth):
    with pytest.raises(ValueError, match="'force': unknown"):
        features(small_truth, history_samples=1, history_signals=("force",))
    with pytest.raises(ValueError, match=">= 0"):
        features(small_truth, history_samples=-2)
    with pytest.raises(ValueError, match="none given"):
        features(small_truth, history_samples=1, history_signals=())


def test_mrrig_train_with_history_writes_a_model_the_controller_takes(
    tmp_path, small_truth, capsys
):
    data = tmp_path / "char.csv"
    write_tidy(data, small_truth)
    out = tmp_path / "fwd.json"
    argv = ["train", str(data), "--out", str(out), "--epochs", "5", "--no-supervised"]
    assert mrrig_main([*argv, "--history", "3", "--history-signals", "xd,xdd"]) == 0
    assert "history inputs: the previous 3 samples of xd, xdd" in capsys.readouterr().out
    m = MLP.load(out)
    assert m.input_names[4:] == ["xd_1", "xdd_1", "xd_2", "xdd_2", "xd_3", "xdd_3"]
    assert m.meta["history_samples"] == 3 and m.meta["history_signals"] == ["xd", "xdd"]
    NetworkInversion(I_MAX_A, m).reset(1)


# ------------------------------------------------------------------------------------ daemon
def test_daemon_loop_runs_a_history_model_like_the_controller_offline(tmp_path, history_model):
    """The daemon builds the controller from the model file and calls it once per frame
    (batch 1): its commands and model forces are those of the controller replayed offline."""
    rig = ScriptedRig(tmp_path)
    section = replace(
        rig.cfg.controller, name="network_inversion", model=history_model.meta["path"]
    )
    rig.daemon.controller = build_controller(rig.cfg, section)
    with rig:
        for k in range(60):
            x = 0.01 * math.sin(2 * math.pi * 3.0 * 0.002 * k)
            cmd = rig.exchange(x=x, force=250.0)
        assert cmd["ControllerId"] == 1
        rig.daemon.request_stop("test done")
        rig.thread.join(timeout=5)
    s = np.concatenate(rig.daemon.batches.handed_over())
    s = s[s["state"] == RigState.ARMED]
    assert s.size >= 40
    # the daemon's default load-cell feedback (with a history model: the present instant)
    offline = NetworkInversion(
        rig.cfg.loop.i_max_a, history_model, feedback_tau_s=section.feedback_tau_s
    )
    offline.reset(1)
    # the loop's slew limit (loop.max_current_slew_a_per_s) on the replay's commands too, the
    # controller told the command sent where it moved one
    slew = SlewLimit(rig.cfg.loop.max_current_slew_a_per_s, rig.cfg.loop.period_s)
    for row in s:
        inst = ControlInput(
            *(np.array([row[f]]) for f in ("x_est", "xd", "xdd", "f_meas", "f_des"))
        )
        i = offline.command(inst)
        sent = slew.limit(float(i[0]))
        if sent != i[0]:
            offline.command_sent(sent)
        slew.sent(sent)
        assert sent == row["i_cmd"]
        assert offline.model_force(inst, np.array([sent]))[0] == row["f_model"]
