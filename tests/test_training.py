"""`mrrig train` and `mrrig.offline.training`: data loading, features, split, model file and
report."""

import json
import math

import numpy as np
import pytest

from damper.plant import BoucWenParams
from mrrig.cli.main import main as mrrig_main
from mrrig.cli.train import main as train_main
from mrrig.loop.mlp import MLP
from mrrig.offline.bench.matrix import make_plant_force
from mrrig.offline.datasets import DataError, Series, dataset_b, dataset_b_conditions
from mrrig.offline.training import (
    COIL_LAG_TAU_S,
    concatenate,
    features,
    lagged_current,
    load_tidy,
    load_training_data,
    series_fingerprint,
    split_samples,
    train_and_validate,
    train_forward,
)
from tests.conftest import SMALL
from tests.data_files import write_tidy

EPOCHS = 15


def _write_csv(path, header, cols):
    values = zip(*(c.tolist() for c in cols), strict=True)
    rows = [",".join(header)] + [",".join(map(repr, r)) for r in values]
    path.write_text("\n".join(rows) + "\n")


def test_csv_in_cm_and_kn_with_other_names_gives_the_same_model_as_si(tmp_path, small_truth):
    s = small_truth
    si, other = tmp_path / "si.csv", tmp_path / "other.csv"
    _write_csv(
        si, ["t", "x", "xd", "xdd", "current", "force"], [s.t, s.x, s.xd, s.xdd, s.current, s.force]
    )
    _write_csv(
        other,
        ["time_ms", "Pos", "Vel", "Acc", "I", "F"],
        [s.t * 1e3, s.x * 1e2, s.xd * 1e2, s.xdd * 1e2, s.current * 1e3, s.force * 1e-3],
    )
    cols_si = dict(t="t", x="x", xd="xd", xdd="xdd", current="current", force="force")
    cols_other = dict(t="time_ms", x="Pos", xd="Vel", xdd="Acc", current="I", force="F")
    units = dict(t="ms", x="cm", xd="cm/s", xdd="cm/s^2", current="mA", force="kN")
    a = load_training_data([si], cols_si)
    b = load_training_data([other], cols_other, units)
    np.testing.assert_array_equal(a.run_id, b.run_id)
    assert np.unique(a.run_id).size == 12  # a new run wherever time restarts
    ma, _ = train_forward(a, seed=3, max_epochs=EPOCHS)
    mb, _ = train_forward(b, seed=3, max_epochs=EPOCHS)
    for name in ("in_mean", "in_std", "W1", "b1", "W2"):
        np.testing.assert_allclose(getattr(mb, name), getattr(ma, name), rtol=1e-9, atol=1e-9)
    assert mb.b2 == pytest.approx(ma.b2, rel=1e-9, abs=1e-9)
    assert mb.out_std == pytest.approx(ma.out_std, rel=1e-9)


def test_tidy_file_round_trip_is_exact(tmp_path, small_truth):
    path = tmp_path / "tidy.csv"
    write_tidy(path, small_truth)
    back = load_tidy(path)
    for f in ("t", "x", "xd", "xdd", "current", "force", "run_id"):
        np.testing.assert_array_equal(getattr(back, f), getattr(small_truth, f))


def test_tidy_file_without_estimates_gets_kalman_estimates_after_a_warmup(tmp_path, small_b):
    b = small_b
    raw = Series(
        t=b.t, x=b.x_meas, xd=None, xdd=None, current=b.current, force=b.force_meas, run_id=b.run_id
    )
    path = tmp_path / "raw.csv"
    write_tidy(path, raw)
    s = load_training_data([path])
    assert s.xd is not None and np.all(np.isfinite(s.xd))
    keep = b.t > 0.1 - 1e-3  # the filter's first 0.1 s (50 samples) is dropped from every run
    assert len(s) == keep.sum() == len(b) - 50 * 12
    # the estimates are the daemon's: close to the true velocity after the warm-up
    assert np.max(np.abs(s.xd - b.xd[keep])) < 0.05


def test_several_files_keep_their_runs_distinct(small_truth):
    both = concatenate([small_truth, small_truth])
    assert np.unique(both.run_id).size == 2 * np.unique(small_truth.run_id).size
    assert len(both) == 2 * len(small_truth)


def test_lagged_current_is_the_exact_first_order_lag_of_a_held_command():
    t = np.arange(50) * 0.002
    v = np.where(np.arange(50) >= 10, 1.5, 0.0)
    u = lagged_current(v, t, np.zeros(50, dtype=int), COIL_LAG_TAU_S)
    # v steps at sample 10, held from then on: u reaches it at 1 - exp(-(t - t10) / tau)
    expected = np.where(t > t[10], 1.5 * -np.expm1(-(t - t[10]) / COIL_LAG_TAU_S), 0.0)
    np.testing.assert_allclose(u, expected, atol=1e-12)


def test_validation_split_is_disjoint_and_falls_back_to_90_10_for_small_data():
    big = split_samples(20000, seed=1)
    assert (big.train.size, big.val.size) == (12771, 1419)
    assert np.intersect1d(big.train, big.val).size == 0
    small = split_samples(1000, seed=1)
    assert (small.train.size, small.val.size) == (900, 100)
    assert np.intersect1d(small.train, small.val).size == 0
    assert "90/10" in small.rule


TINY = dict(amplitudes_m=(0.015,), freqs_hz=(2.0, 5.0), currents_a=(0.0, 0.6, 1.2))


@pytest.mark.long
def test_small_matrix_report_has_every_number():
    b = dataset_b(duration_s=0.3, **TINY)
    s = Series(
        t=b.t, x=b.x, xd=b.xd, xdd=b.xdd, current=b.current, force=b.force_meas, run_id=b.run_id
    )
    cond = dataset_b_conditions(TINY["amplitudes_m"], TINY["freqs_hz"], TINY["currents_a"])
    plant = make_plant_force(s, BoucWenParams.preset("rig-current"), cond)
    fwd, sup, r = train_and_validate(s, seed=0, max_epochs=EPOCHS, plant_force=plant)
    # time blocks: the last ceil(15 %) = 23 of each of 6 runs of 150 held out
    assert (r["split"]["n_train"], r["split"]["n_val"]) == (762, 138)
    assert r["i_max_a"] == 1.2
    numbers = [r["forward"]["et"], r["forward"]["rmse_n"]]
    for side in ("network_inversion", "network_inversion_online", "supervised"):
        numbers.append(r[side]["current_rmse_a"])
        for kind in ("tracking_model_n", "tracking_plant_n"):
            numbers += [r[side][kind][k] for k in ("p50", "p95", "max", "rms")]
    assert all(isinstance(v, float) and math.isfinite(v) for v in numbers)
    assert sup is not None and sup.input_names == ["x", "xd", "xdd", "f_des"]
    assert fwd.metrics["inverse_current_rmse_a"] == r["network_inversion"]["current_rmse_a"]
    online = r["network_inversion_online"]
    assert fwd.meta["online_continuity"] == online["continuity"]
    assert online["training_rmse_by_continuity"][f"{online['continuity']:g}"] == min(
        online["training_rmse_by_continuity"].values()
    )


def test_plant_force_at_the_data_currents_is_the_data_force(small_b):
    cond = dataset_b_conditions(SMALL["amplitudes_m"], SMALL["freqs_hz"], SMALL["currents_a"])
    plant = make_plant_force(small_b, BoucWenParams.preset("rig-current"), cond)
    rows = np.arange(0, len(small_b), 97)
    np.testing.assert_allclose(plant(rows, small_b.current[rows]), small_b.force[rows], atol=1e-9)


def test_mrrig_train_writes_the_model_with_options_and_fingerprint(tmp_path, small_truth, capsys):
    data = tmp_path / "char.csv"
    write_tidy(data, small_truth)
    out, sup_out, rep = tmp_path / "m" / "fwd.json", tmp_path / "sup.json", tmp_path / "r.json"
    rc = train_main(
        [
            str(data),
            "--out",
            str(out),
            "--epochs",
            "5",
            "--current-input",
            "lagged",
            "--supervised-out",
            str(sup_out),
            "--report",
            str(rep),
            "--seed",
            "2",
        ]
    )
    assert rc == 0
    model = MLP.load(out)
    assert model.input_names == ["x", "xd", "xdd", "current"]
    assert model.meta["current_input"] == "lagged"
    assert model.meta["lag_tau_s"] == pytest.approx(COIL_LAG_TAU_S)
    assert model.meta["data_fingerprint"] == series_fingerprint(load_training_data([data]))
    assert model.meta["split"] == "blocks" and model.meta["holdout_fraction"] == 0.15
    assert model.meta["split_seed"] == 2 and model.meta["data_files"] == [str(data)]
    assert MLP.load(sup_out).output_name == "current"
    report = json.loads(rep.read_text())
    assert report["split"]["n_train"] + report["split"]["n_val"] == len(small_truth)
    # LM's rows (fit + early stopping) are training rows: the hold-out is not among them
    assert model.meta["n_train"] + model.meta["n_val"] == report["split"]["n_train"]
    assert report["current_input"] == "lagged"
    assert "inverse-command RMSE" in capsys.readouterr().out


def test_lagged_features_differ_from_commanded_only_where_the_current_changes(small_truth):
    Xc, _ = features(small_truth, "commanded")
    Xl, _ = features(small_truth, "lagged")
    np.testing.assert_array_equal(Xl[:, :3], Xc[:, :3])
    # data set B holds the current constant in each run: the lag starts settled
    np.testing.assert_allclose(Xl[:, 3], Xc[:, 3], atol=1e-12)


def test_data_errors_are_one_line_and_name_the_file(tmp_path, capsys):
    odd = tmp_path / "odd.csv"
    odd.write_text("a,b\n1,2\n")
    with pytest.raises(DataError, match="odd.csv.*--columns"):
        load_training_data([odd])
    missing = tmp_path / "nope.rrd"
    assert mrrig_main(["train", str(missing), "--out", str(tmp_path / "m.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "nope.rrd" in err and "\n" not in err


def test_recording_gives_x_est_i_cmd_f_meas_without_fault_samples_and_splits_runs(tmp_path):
    from mrrig.loop.samples import SAMPLE_DTYPE, RigState
    from mrrig.rigio.recording import Recorder

    n = 300
    s = np.zeros(n, dtype=SAMPLE_DTYPE)
    s["t"] = np.arange(n) * 0.002
    k = np.arange(n)
    s["x"], s["x_est"], s["xd"], s["xdd"] = 1e-3 * k, 1e-3 * k + 1e-6, 0.5, -2.0
    s["f_meas"], s["i_cmd"], s["i_meas"] = 10.0 + k, 0.01 * k, 0.3
    s["state"] = RigState.ARMED
    s["state"][:100] = RigState.IDLE
    s["state"][200:220] = RigState.FAULT
    path = tmp_path / "run.rrd"
    with Recorder(path, "rig1") as rec:
        rec.add_samples(s)
    got = load_training_data([path])
    keep = s["state"] != RigState.FAULT
    keep[:50] = False  # the Kalman filter's first 0.1 s
    assert len(got) == keep.sum()
    np.testing.assert_array_equal(got.x, s["x_est"][keep])
    np.testing.assert_array_equal(got.current, s["i_cmd"][keep])
    np.testing.assert_array_equal(got.force, s["f_meas"][keep])
    # IDLE and ARMED are one run; after the FAULT stretch a new run starts (lag filters restart)
    np.testing.assert_array_equal(np.unique(got.run_id[:150]), [0])
    np.testing.assert_array_equal(np.unique(got.run_id[150:]), [1])


@pytest.mark.long
def test_the_start_with_the_best_online_inverse_on_the_training_rows_is_kept():
    b = dataset_b(duration_s=0.3, **TINY)
    s = Series(
        t=b.t, x=b.x, xd=b.xd, xdd=b.xdd, current=b.current, force=b.force_meas, run_id=b.run_id
    )
    fwd, _, r = train_and_validate(s, seed=3, max_epochs=EPOCHS, supervised=False, restarts=3)
    st = r["starts"]
    assert st["init_seeds"] == [3, 4, 5]
    assert st["kept"] == int(np.argmin(st["training_rmse_a"]))
    assert fwd.meta["init_seed"] == 3 + st["kept"] and fwd.meta["starts"] == 3
    # the kept start is the one trained alone from that seed
    alone, _ = train_forward(s, seed=3, max_epochs=EPOCHS, init_seed=3 + st["kept"])
    np.testing.assert_array_equal(alone.W1, fwd.W1)
    # one start is the seed's own network, as before restarts existed
    one, _, r1 = train_and_validate(s, seed=3, max_epochs=EPOCHS, supervised=False, restarts=1)
    plain, _ = train_forward(s, seed=3, max_epochs=EPOCHS)
    np.testing.assert_array_equal(one.W1, plain.W1)
    assert r1["starts"]["init_seeds"] == [3]
