"""The on-line inverse of the validation report: runs in time order, as the daemon makes it."""

from __future__ import annotations

import numpy as np

from mrrig.loop.inversion import exact_inversion
from mrrig.offline.training import ONLINE_CONTINUITY_CANDIDATES, choose_continuity, online_inversion
from tests.test_inversion import I_MAX, random_features, random_model


def _data(rng: np.random.Generator, n: int):
    model = random_model(rng, monotone=True)
    feats = random_features(rng, n)
    current = rng.uniform(0.0, I_MAX, n)
    X = np.column_stack([feats, current])
    return model, X, model.predict(X) + rng.normal(0.0, 20.0, n)


def test_online_inversion_solves_each_row_from_the_previous_rows_answer() -> None:
    rng = np.random.default_rng(1)
    model, X, f = _data(rng, 60)
    stretch = np.repeat([0, 1, 2], [25, 20, 15])
    got = online_inversion(model, X, f, stretch, I_MAX, continuity=0.1)
    want = np.empty(60)
    for run in range(3):
        prev = 0.0  # each stretch starts from 0 A
        for r in np.flatnonzero(stretch == run):
            want[r] = prev = exact_inversion(
                model, X[r : r + 1, :3], f[r : r + 1], prev, i_max=I_MAX, continuity=0.1
            )[0]
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_online_inversion_never_reads_the_data_current() -> None:
    rng = np.random.default_rng(2)
    model, X, f = _data(rng, 40)
    stretch = np.repeat([0, 1], 20)
    scrambled = X.copy()
    scrambled[:, 3] = rng.uniform(0.0, I_MAX, 40)
    np.testing.assert_array_equal(
        online_inversion(model, X, f, stretch, I_MAX, 0.3),
        online_inversion(model, scrambled, f, stretch, I_MAX, 0.3),
    )


def test_continuity_is_chosen_on_the_training_rows_alone() -> None:
    rng = np.random.default_rng(3)
    model, X, f = _data(rng, 200)
    stretch = np.repeat(np.arange(4), 50)
    train = np.sort(rng.choice(200, 150, replace=False))
    val = np.setdiff1d(np.arange(200), train)
    mu, currents, scores = choose_continuity(model, X, f, stretch, I_MAX, train)
    assert mu in ONLINE_CONTINUITY_CANDIDATES
    assert set(scores) == {f"{c:g}" for c in ONLINE_CONTINUITY_CANDIDATES}
    assert scores[f"{mu:g}"] == min(scores.values())
    # the validation rows' labels play no part: scrambling them changes nothing
    other = X.copy()
    other[val, 3] = rng.uniform(0.0, I_MAX, val.size)
    mu2, currents2, scores2 = choose_continuity(model, other, f, stretch, I_MAX, train)
    assert mu2 == mu and scores2 == scores
    np.testing.assert_array_equal(currents2, currents)
