"""Training on measured data: the time-block hold-out, bad stretches, the command's lag, the
structure search's folds, `mrrig evaluate` (spec/modeling.md 4 C; issue 27)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from damper.plant import BoucWenParams, simulate
from damper.signals import bandlimited_noise
from mrrig.cli.train import main as train_main
from mrrig.loop.estimation import KalmanEstimator, kalman_lanes
from mrrig.offline.datasets import Series
from mrrig.offline.evaluate import main as evaluate_main
from mrrig.offline.training import (
    COIL_LAG_TAU_S,
    INPUT_NAMES,
    INPUT_UNITS,
    block_split,
    coverage_subsample,
    estimate_derivatives,
    exclude_bad_stretches,
    features,
    fit_lag_tau,
    load_training_data,
    select,
    train_and_validate,
)
from mrrig.offline.training import data as training_data
from mrrig.offline.training.data import stretches
from mrrig.offline.training.features import feature_rows
from mrrig.offline.training.lm import train_lm
from mrrig.offline.training.select import FOLDS, Candidate, _folds, command_varies

MEASURED = Path(__file__).resolve().parents[2] / "shared" / "data" / "dyke-mr-damper-ransim-u.csv"
needs_measured = pytest.mark.skipif(not MEASURED.is_file(), reason=f"no {MEASURED}")


def _sim_varying(n_runs=3, seconds=6.0, fs=500.0, seed=5):
    """Simulated rig data with a command that changes within runs (random 0-2 A): truth."""
    rng = np.random.default_rng(seed)
    n = round(seconds * fs)
    t = np.arange(n) / fs
    x, xd, xdd, cur = (np.empty((n_runs, n)) for _ in range(4))
    for j in range(n_runs):
        x[j], xd[j], xdd[j] = bandlimited_noise(n, 1 / fs, 4.0, 0.015, rng)
        cur[j] = np.clip(bandlimited_noise(n, 1 / fs, 3.0, 1.2, rng)[0] + 1.0, 0.0, 2.0)
    f = simulate(BoucWenParams.preset("rig-current"), t, x, xd, cur, 2e-4)
    f = f + rng.normal(0.0, 2.0, f.shape)
    return Series(
        t=np.tile(t, n_runs),
        x=x.ravel(),
        xd=xd.ravel(),
        xdd=xdd.ravel(),
        current=cur.ravel(),
        force=f.ravel(),
        name="varying",
        run_id=np.repeat(np.arange(n_runs), n),
    )


@pytest.fixture(scope="module")
def varying():
    return _sim_varying()


@pytest.fixture(scope="module")
def measured_short(tmp_path_factory):
    """The first 6 s of the measured file and its last 6 s (saturation, drift at its end): two
    runs (the time gap between them starts a new one), as a CSV."""
    lines = MEASURED.read_text().splitlines()
    path = tmp_path_factory.mktemp("measured") / "dyke-short.csv"
    path.write_text("\n".join([lines[0], *lines[1:18000], *lines[-18000:]]) + "\n")
    return path


def test_block_split_holds_out_the_end_of_every_run_and_stops_early_before_it():
    stretch = np.repeat([0, 1], [100, 60])
    sp = block_split(stretch, 0.15)
    assert sp.kind == "blocks"
    np.testing.assert_array_equal(sp.val, np.r_[85:100, 151:160])  # ceil(15 %) of 100, 60
    np.testing.assert_array_equal(sp.stop, np.r_[72:85, 143:151])  # ceil(15 %) of 85, 51
    assert np.intersect1d(sp.train, sp.val).size == 0 and sp.train.size + sp.val.size == 160


def test_the_search_folds_never_touch_any_candidates_hold_out(varying):
    deep = Candidate(history_samples=4, history_signals=("x", "xd"), history_stride=5)
    fold = _folds(varying, [Candidate(), deep], 0.15)
    st = stretches(varying.run_id)
    for c in (Candidate(), deep):
        rows = feature_rows(varying, c.history_samples, c.history_stride)
        held = rows[block_split(st[rows], 0.15).val]
        assert np.all(fold[held] == -1)
    assert set(np.unique(fold)) == {-1, *range(FOLDS)}
    # each fold is a contiguous block of each run
    for r in range(3):
        f = fold[varying.run_id == r]
        f = f[f >= 0]
        assert np.all(np.diff(f) >= 0)


def test_inversion_over_the_budget_is_timed_again_before_a_candidate_is_refused(
    varying, monkeypatch
):
    X, y = features(varying, "lagged")
    model, _ = train_lm(X[:400], y[:400], INPUT_NAMES, INPUT_UNITS, "force", "N", hidden=5,
                        max_epochs=2)  # fmt: skip
    made = []

    class Counted(select.ScalarInverter):  # the real inverter, its passes counted
        def __init__(self, *args, **kwargs):
            made.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(select, "ScalarInverter", Counted)
    fast = select._inversion_us(model, X, y, repeats=2, budget_us=math.inf, rounds=3)
    assert len(made) == 2 * 2  # one round: each repeat prepared and full
    made.clear()
    slow = select._inversion_us(model, X, y, repeats=2, budget_us=0.0, rounds=3)
    assert len(made) == 3 * 2 * 2  # no time is within 0 us: every round
    assert 0.0 < slow[0] and 0.0 < fast[0]


def test_command_lag_is_found_by_the_1d_search(varying):
    assert command_varies(varying)
    tau, _ = fit_lag_tau(varying, np.arange(len(varying)))
    assert tau == pytest.approx(COIL_LAG_TAU_S, rel=0.3)  # the plant's 1/eta, 5.26 ms


def test_coverage_subsample_keeps_the_rare_states_and_its_size():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(20000, 1))
    rows = np.arange(20000)
    sub = coverage_subsample(X, rows, 200, seed=1)
    assert sub.size == 200 and np.all(np.diff(sub) > 0)
    tail = X[:, 0] > 2.25  # the top of 8 bins over +-3 sigma: 1.2 % of the rows
    # half of the subsample round-robin over the 8 bins: about 100 / 8 from the tail, where a
    # random subsample has 200 * 1.2 % = 2.4
    assert tail[sub].sum() >= 10
    np.testing.assert_array_equal(sub, coverage_subsample(X, rows, 200, seed=1))


def test_kalman_lanes_equal_the_daemons_filter_and_blocks_equal_one_pass():
    rng = np.random.default_rng(3)
    t = np.arange(20000) * 0.002
    x = 0.01 * np.sin(2 * np.pi * 3 * t) + rng.normal(0, 1e-5, t.size)
    want = KalmanEstimator(0.002).estimate(x[:3000])
    got = kalman_lanes(x[None, :3000], 0.002)
    for a, b in zip(want, got, strict=True):
        np.testing.assert_allclose(b[0], a, rtol=0, atol=1e-9)
    # a run longer than a block: blocks side by side, each settled by its overlap
    s = Series(t=t, x=x, xd=None, xdd=None, current=np.zeros_like(t), force=np.zeros_like(t))
    whole = kalman_lanes(x[None, :], 0.002)
    est = estimate_derivatives(s)
    keep = t > training_data.KALMAN_WARMUP_S - 0.001
    np.testing.assert_allclose(est.xd, whole[1][0][keep], rtol=0, atol=1e-9)


def test_bad_stretches_found_by_kind_with_their_times_and_keep_all_keeps_them(varying):
    s = _sim_varying(n_runs=1, seconds=12.0, seed=9)
    fs = 500
    s.force[1000:1040] = s.force.max() + 100.0  # a load cell at its limit: flat top
    s.x[3000:3500] = s.x[3000]  # the rig stops: idle
    s.xd[3000:3500] = 0.0
    s.x[5500:] += 0.05  # a drift off at the test's end
    s.xd[5500:] *= 6.0
    kept, ex = exclude_bad_stretches(s)
    kinds = {st["kind"]: st for st in ex["stretches"]}
    assert set(kinds) == {"saturation", "idle", "transient"}
    assert kinds["saturation"]["t_start_s"] <= 1000 / fs <= kinds["saturation"]["t_end_s"]
    assert kinds["idle"]["t_start_s"] <= 3100 / fs and kinds["idle"]["t_end_s"] >= 3400 / fs
    assert kinds["transient"]["t_end_s"] == pytest.approx(s.t[-1])
    assert ex["excluded_samples"] == len(s) - len(kept)
    assert sum(ex["by_kind"].values()) == ex["excluded_samples"]
    same, none = exclude_bad_stretches(s, keep_all=True)
    assert len(same) == len(s) and none["keep_all"] and none["excluded_samples"] == 0


def test_no_bad_stretch_in_the_simulated_matrix(small_b):
    from mrrig.offline.training import measured_series

    _, ex = exclude_bad_stretches(measured_series(small_b))
    assert ex["excluded_samples"] == 0


@needs_measured
def test_measured_file_saturation_and_unsteady_end_are_excluded():
    s = load_training_data([MEASURED])
    assert s.current_unit == "V"
    kept, ex = exclude_bad_stretches(s)
    assert ex["by_kind"]["saturation"] >= 217  # the README's count of flat samples
    assert np.all(np.abs(kept.force) < 4545.0)
    # the unsteady end (drift from about 19.4 s, saturation) goes as one stretch to the end:
    # one run is left, nothing kept after the first excluded sample
    assert np.unique(kept.run_id).size == 1
    first_bad = min(st["t_start_s"] for st in ex["stretches"])
    assert 19.0 < first_bad < 19.6 and kept.t[-1] < first_bad
    assert ex["excluded_samples"] < 0.05 * len(s)


@pytest.mark.long
@needs_measured
def test_random_split_is_optimistic_and_the_block_split_is_the_default(measured_short):
    s, _ = exclude_bad_stretches(load_training_data([measured_short]))
    opts = dict(current_input="lagged", max_epochs=60, supervised=False, restarts=1, seed=0)
    _, _, blocks = train_and_validate(s, **opts)
    _, _, rand = train_and_validate(s, split="random", **opts)
    assert blocks["split"]["kind"] == "blocks" and rand["split"]["kind"] == "random"
    et_b, et_r = blocks["forward"]["et"], rand["forward"]["et"]
    print(f"held-out Et: time blocks {et_b:.4f}, random samples {et_r:.4f}")
    assert et_r < 0.9 * et_b  # neighbours of the random hold-out were trained on


def _train_then_evaluate(tmp_path, data, extra):
    model, report = tmp_path / "m.json", tmp_path / "r.json"
    args = [str(data), "--out", str(model), "--report", str(report), "--no-supervised"]
    assert train_main(args + ["--epochs", "30", "--restarts", "1", *extra]) == 0
    out = tmp_path / "e.json"
    assert evaluate_main([str(model), str(data), "--rows", "holdout", "--json", str(out)]) == 0
    return json.loads(report.read_text()), json.loads(out.read_text())


@pytest.mark.long
@needs_measured
def test_evaluate_gives_the_training_reports_et_on_the_measured_holdout(tmp_path, measured_short):
    r, e = _train_then_evaluate(
        tmp_path, measured_short, ["--current-input", "lagged", "--history", "2"]
    )
    assert r["split"]["kind"] == "blocks"  # mrrig train's default hold-out
    assert r["command_unit"] == "V" and e["command_unit"] == "V"
    assert e["n"] == r["n_val"]
    assert e["forward"]["et"] == r["forward"]["et"]
    assert e["forward"]["rmse_n"] == r["forward"]["rmse_n"]
    assert e["inverse_current_rmse"] == r["network_inversion"]["current_rmse_a"]


@pytest.mark.long
def test_evaluate_on_a_simulator_recording_equals_the_training_report(tmp_path, capsys):
    from mrrig.loop.samples import SAMPLE_DTYPE, RigState
    from mrrig.rigio.recording import Recorder

    v = _sim_varying(n_runs=1, seconds=8.0, seed=11)
    s = np.zeros(len(v), dtype=SAMPLE_DTYPE)
    s["t"], s["x"], s["x_est"], s["xd"], s["xdd"] = v.t, v.x, v.x, v.xd, v.xdd
    s["f_meas"], s["i_cmd"], s["i_meas"] = v.force, v.current, v.current
    s["state"] = RigState.ARMED
    path = tmp_path / "sim.rrd"
    with Recorder(path, "rig1") as rec:
        rec.add_samples(s)
    r, e = _train_then_evaluate(tmp_path, path, ["--current-input", "lagged"])
    assert e["forward"]["et"] == r["forward"]["et"] and e["n"] == r["n_val"]
    plot = tmp_path / "e.png"
    m = str(tmp_path / "m.json")
    assert evaluate_main([m, str(path), "--plot", str(plot), "--window", "1,2"]) == 0
    assert plot.stat().st_size > 10_000
    assert "forward Et" in capsys.readouterr().out


@pytest.mark.long
def test_evaluate_refuses_a_command_in_other_units(tmp_path, varying):
    from mrrig.cli.main import main as mrrig_main

    model = tmp_path / "m.json"
    csv_a = tmp_path / "a.csv"
    csv_v = tmp_path / "v.csv"
    n = 3000
    body = "\n".join(
        f"{t!r},{x!r},{c!r},{f!r}"
        for t, x, c, f in zip(
            varying.t[:n].tolist(),
            varying.x[:n].tolist(),
            varying.current[:n].tolist(),
            varying.force[:n].tolist(),
            strict=True,
        )
    )
    csv_a.write_text("t_s,x_m,current_a,force_n\n" + body + "\n")
    csv_v.write_text("t_s,x_m,command_v,force_n\n" + body + "\n")
    assert (
        train_main(
            [
                str(csv_a),
                "--out",
                str(model),
                "--epochs",
                "5",
                "--restarts",
                "1",
                "--no-supervised",
                "--current-input",
                "lagged",
            ]
        )
        == 0
    )
    assert mrrig_main(["evaluate", str(model), str(csv_v)]) == 2
