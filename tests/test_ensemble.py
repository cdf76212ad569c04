"""Issue 43 item 1: `mrrig train`'s MLP kinds average several fits (mrrig/offline/training/
ensemble.py): each fold fit of the kind choice is the mean of members that differ in their
initial weights, their rows and the tests they stop on, and the final model the mean of as
many starts, written as one network of their hidden layers side by side, which the daemon
inverts as any other. Pure numerics, seconds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mrrig.cli.train import main as train_main
from mrrig.loop.inversion import ScalarInverter
from mrrig.loop.mlp import MLP
from mrrig.offline.datasets import Series, dataset_b
from mrrig.offline.training.ensemble import average_mlps
from mrrig.offline.training.features import features
from mrrig.offline.training.fit import stretch_split, train_and_validate, train_forward
from mrrig.offline.training.kinds import mlp_kind
from mrrig.offline.training.select import Candidate
from tests.data_files import write_tidy

NAMES = ["x", "xd", "xdd", "current"]
UNITS = ["m", "m/s", "m/s^2", "A"]


def _random_mlp(rng: np.random.Generator, hidden: int) -> MLP:
    """A network of its own standardisation (members fitted on different rows have their own)."""
    return MLP(
        input_names=NAMES,
        input_units=UNITS,
        output_name="force",
        output_unit="N",
        in_mean=rng.normal(0.0, [0.01, 0.1, 1.0, 1.0]),
        in_std=rng.uniform(0.5, 2.0, 4) * [0.01, 0.1, 1.0, 1.0],
        out_mean=float(rng.normal(100.0, 20.0)),
        out_std=float(rng.uniform(100.0, 300.0)),
        W1=rng.normal(0.0, 1.0, (hidden, 4)),
        b1=rng.normal(0.0, 1.0, hidden),
        W2=rng.normal(0.0, 1.0, hidden),
        b2=float(rng.normal()),
        meta={"init_seed": hidden},
    )


def test_the_averaged_network_is_exactly_the_mean_of_its_members_and_the_daemon_inverts_it(
    tmp_path,
):
    rng = np.random.default_rng(1)
    members = [_random_mlp(rng, h) for h in (5, 4, 6)]
    mean = average_mlps(members)
    assert mean.hidden == 15
    assert mean.meta["ensemble"] == {"members": 3, "hidden": [5, 4, 6], "init_seeds": [5, 4, 6]}
    X = rng.normal(0.0, 1.0, (200, 4)) * [0.01, 0.1, 1.0, 1.0] + [0.0, 0.0, 0.0, 1.0]
    want = np.mean([m.predict(X) for m in members], axis=0)
    np.testing.assert_allclose(mean.predict(X), want, rtol=1e-12, atol=1e-9)
    path = tmp_path / "mean.json"
    mean.save(path)
    again = MLP.load(path)
    np.testing.assert_array_equal(again.predict(X), mean.predict(X))
    # the daemon's solve finds the current that gives the members' mean force
    inv = ScalarInverter(again, i_max=3.0)
    for row in X[:20]:
        f_des = float(np.mean([m.predict(np.r_[row[:3], 1.2][None, :])[0] for m in members]))
        i = inv.solve(row[:3], f_des, 1.2)
        assert abs(again.predict(np.r_[row[:3], i][None, :])[0] - f_des) < 1e-6 * abs(f_des) + 1e-6


def test_members_of_other_inputs_are_refused_in_one_line():
    rng = np.random.default_rng(2)
    a, b = _random_mlp(rng, 3), _random_mlp(rng, 3)
    b.input_names = ["x", "xd", "xdd", "lagged"]
    with pytest.raises(ValueError, match="member 1 has inputs") as exc:
        average_mlps([a, b])
    assert "\n" not in str(exc.value)


def _matrix(tests: int = 8) -> Series:
    """A matrix of constant-command tests (one run each): a viscous-friction damper."""
    rate, n = 200.0, 240
    parts = []
    for k in range(tests):
        t = np.arange(n) / rate
        amp, freq, cur = 0.004 + 0.001 * (k % 4), 1.0 + 0.25 * (k % 3), 0.4 * (k % 4)
        w = 2 * np.pi * freq
        x, xd, xdd = amp * np.sin(w * t), amp * w * np.cos(w * t), -amp * w * w * np.sin(w * t)
        f = (500.0 + 800.0 * cur) * xd + (40.0 + 300.0 * cur) * np.tanh(xd / 0.01) + 100.0
        parts.append((t, x, xd, xdd, np.full(n, cur), f, np.full(n, k)))
    return Series(*(np.concatenate([p[j] for p in parts]) for j in range(7)))


def test_a_fold_fit_is_the_mean_of_members_that_stop_on_other_tests():
    """Each member k of a fold fit starts from seed + k: its own initial weights, rows and
    stopping tests (`stretch_split`'s first: every 6th test from the k-th)."""
    sp = stretch_split(np.repeat(np.arange(8), 10), first=1)
    assert set((sp.stop // 10).tolist()) == {1, 7}
    s = _matrix()
    cand = Candidate(history_samples=2, history_stride=2, hidden=4)
    kind = mlp_kind(
        "history MLP",
        cand,
        "toy",
        seed=0,
        max_epochs=4,
        holdout_fraction=0.15,
        i_max=1.2,
        members=3,
    )
    model = kind.fit_fold(s, 1.0)
    assert model.hidden == 12
    assert model.meta["ensemble"]["init_seeds"] == [0, 1, 2]
    feat = dict(history_samples=2, history_stride=2, hidden=4, max_epochs=4, max_fit_rows=3000)
    fits = [
        train_forward(s, seed=k, split="stretches", rows_per_weight=0, **feat)[0] for k in range(3)
    ]
    assert [f.meta["split_rule"] for f in fits][1].endswith("(every 6th from stretch 1), whole")
    _, _, f = kind.forces(model, s)
    Xf, _ = features(s, history_samples=2, history_stride=2)
    np.testing.assert_allclose(f, np.mean([m.predict(Xf) for m in fits], axis=0), atol=1e-9)


def test_the_final_model_averages_its_starts():
    s = _matrix()
    fwd, _, report = train_and_validate(
        s,
        max_epochs=3,
        supervised=False,
        restarts=2,
        average_starts=True,
        hidden=4,
        history_samples=2,
        history_stride=2,
    )
    assert fwd.hidden == 8
    assert report["starts"]["averaged"] and report["starts"]["init_seeds"] == [0, 1]
    one = [
        train_forward(
            s, seed=k, init_seed=k, max_epochs=3, hidden=4, history_samples=2, history_stride=2
        )[0]
        for k in range(2)
    ]
    Xf, _ = features(s, history_samples=2, history_stride=2)
    np.testing.assert_allclose(
        fwd.predict(Xf), np.mean([m.predict(Xf) for m in one], axis=0), atol=1e-9
    )


def test_the_default_train_writes_the_mean_of_its_starts_as_its_folds_were(tmp_path, capsys):
    """`mrrig train`'s default (features auto) on a matrix of tests: the kind choice's fold
    fits average `--restarts` members and the model written is the mean of as many starts,
    one network of their hidden layers, printed as such."""
    paths = []
    for k, cur in enumerate((0.0, 0.8, 1.6)):
        b = dataset_b(duration_s=0.6, amplitudes_m=(0.01,), freqs_hz=(2.0,), currents_a=(cur,))
        paths.append(tmp_path / f"test{k}.csv")
        write_tidy(paths[-1], Series(b.t, b.x, b.xd, b.xdd, b.current, b.force_meas, b.run_id))
    out = tmp_path / "m.json"
    args = [*map(str, paths), "--out", str(out), "--no-supervised", "--report", str(out) + ".r"]
    assert train_main([*args, "--epochs", "5", "--restarts", "2", "--budget-s", "2"]) == 0
    text = capsys.readouterr().out
    model = MLP.load(out)
    per_start = json.loads(Path(str(out) + ".r").read_text())["hidden"]
    assert model.hidden == 2 * per_start
    assert model.meta["ensemble"]["init_seeds"] == [0, 1]
    assert "the mean of 2 starts" in text and f"({2 * per_start} in the averaged network)" in text
