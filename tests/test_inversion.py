"""Network inversion (paper eqs 2-14): eq. 14's gradient, the exact default, the scalar path."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
import torch

from mrrig.loop import inversion
from mrrig.loop.inversion import (
    ScalarInverter,
    eq14_gradient,
    exact_inversion,
    gradient_inversion,
)
from mrrig.loop.mlp import MLP
from mrrig.offline.training.lm import MLPModule

NAMES = ["x", "xd", "xdd", "current"]
UNITS = ["m", "m/s", "m/s^2", "A"]
I_MAX = 2.0


def random_model(rng: np.random.Generator, hidden: int = 30, monotone: bool = False) -> MLP:
    """A 4-H-1 force model with random weights; `monotone`: force increases with current."""
    W1 = rng.normal(size=(hidden, 4))
    W2 = rng.normal(size=hidden) * 0.3
    if monotone:
        W1[:, 3] = np.abs(W1[:, 3]) * np.sign(W2)
    return MLP(
        NAMES,
        UNITS,
        "force",
        "N",
        in_mean=[0.0, 0.0, 0.0, 0.9],
        in_std=[0.01, 0.1, 5.0, 0.6],
        out_mean=100.0,
        out_std=500.0,
        W1=W1,
        b1=rng.normal(size=hidden),
        W2=W2,
        b2=0.1,
    )


def bump_model() -> MLP:
    """f(i) = tanh(3 (i - 0.5)) - tanh(3 (i - 1.5)): non-monotone, symmetric about i = 1 A."""
    W1 = np.array([[0.0, 0.0, 0.0, 3.0], [0.0, 0.0, 0.0, 3.0]])
    return MLP(
        NAMES,
        UNITS,
        "force",
        "N",
        in_mean=np.zeros(4),
        in_std=np.ones(4),
        out_mean=0.0,
        out_std=1.0,
        W1=W1,
        b1=[-1.5, -4.5],
        W2=[1.0, -1.0],
        b2=0.0,
    )


def random_features(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack(
        [rng.uniform(-0.02, 0.02, n), rng.uniform(-0.2, 0.2, n), rng.uniform(-10.0, 10.0, n)]
    )


def force(model: MLP, features: np.ndarray, current_a: np.ndarray) -> np.ndarray:
    return model.predict(np.column_stack([features, current_a]))


def test_eq14_gradient_equals_autograd_in_physical_and_standardised_units() -> None:
    rng = np.random.default_rng(1)
    model = random_model(rng)
    X = np.column_stack([random_features(rng, 200), rng.uniform(0.0, I_MAX, 200)])
    f_des = rng.uniform(-500.0, 800.0, 200)
    net = MLPModule(model)
    mean_c, std_c = model.in_mean[3], model.in_std[3]

    i_phys = torch.tensor(X[:, 3], requires_grad=True)
    Xt = torch.cat([torch.tensor(X[:, :3]), i_phys[:, None]], dim=1)
    E = 0.5 * (torch.tensor(f_des) - net(Xt)) ** 2
    E.sum().backward()
    np.testing.assert_allclose(eq14_gradient(model, X, f_des), i_phys.grad.numpy(), rtol=1e-6)

    i_std = torch.tensor((X[:, 3] - mean_c) / std_c, requires_grad=True)
    Xt = torch.cat([torch.tensor(X[:, :3]), (i_std * std_c + mean_c)[:, None]], dim=1)
    E_s = 0.5 * ((torch.tensor(f_des) - net(Xt)) / model.out_std) ** 2
    E_s.sum().backward()
    np.testing.assert_allclose(
        eq14_gradient(model, X, f_des, standardised=True), i_std.grad.numpy(), rtol=1e-6
    )


def test_exact_inversion_reproduces_reachable_force() -> None:
    rng = np.random.default_rng(2)
    model = random_model(rng, monotone=True)
    features = random_features(rng, 500)
    i_true = rng.uniform(0.0, I_MAX, 500)
    f_des = force(model, features, i_true)
    i_star = exact_inversion(model, features, f_des, rng.uniform(0.0, I_MAX, 500), i_max=I_MAX)
    np.testing.assert_allclose(force(model, features, i_star), f_des, rtol=0, atol=1e-6)
    np.testing.assert_allclose(i_star, i_true, rtol=0, atol=1e-8)


@pytest.mark.parametrize("continuity", [0.0, 1.0])
def test_the_grid_in_blocks_of_rows_gives_the_numbers_of_one_product(
    continuity: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    rng = np.random.default_rng(22)
    model = random_model(rng)
    n = 3 * inversion.GRID_BLOCK_ROWS + 5  # three whole blocks and a part
    features = random_features(rng, n)
    f_des = force(model, features, rng.uniform(0.0, I_MAX, n)) + rng.normal(0.0, 30.0, n)
    i_prev = rng.uniform(0.0, I_MAX, n)
    blocks = exact_inversion(model, features, f_des, i_prev, i_max=I_MAX, continuity=continuity)
    monkeypatch.setattr(inversion, "GRID_BLOCK_ROWS", n)
    whole = exact_inversion(model, features, f_des, i_prev, i_max=I_MAX, continuity=continuity)
    np.testing.assert_array_equal(blocks, whole)


@pytest.mark.parametrize("continuity", [0.0, 1.0])
def test_exact_inversion_memory_per_row_stays_below_the_grids_hidden_outputs(
    continuity: float,
) -> None:
    """The N x 33 x 30 hidden outputs on the grid (8 kB a row) never exist at once: a long
    recording's validation rows must not need gigabytes."""
    rng = np.random.default_rng(23)
    model = random_model(rng)
    n = 20000
    features = random_features(rng, n)
    f_des = force(model, features, rng.uniform(0.0, I_MAX, n))
    i_prev = rng.uniform(0.0, I_MAX, n)
    tracemalloc.start()
    try:
        exact_inversion(model, features, f_des, i_prev, i_max=I_MAX, continuity=continuity)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak / n < 33 * 30 * 8 / 2, f"{peak / n:.0f} bytes a row"


def test_exact_inversion_saturates_at_the_nearest_bound_when_out_of_reach() -> None:
    rng = np.random.default_rng(3)
    model = random_model(rng, monotone=True)
    features = random_features(rng, 100)
    f_lo = force(model, features, np.zeros(100))
    f_hi = force(model, features, np.full(100, I_MAX))
    i_prev = np.full(100, 1.0)
    np.testing.assert_array_equal(
        exact_inversion(model, features, f_hi + 50.0, i_prev, i_max=I_MAX), I_MAX
    )
    np.testing.assert_array_equal(
        exact_inversion(model, features, f_lo - 50.0, i_prev, i_max=I_MAX), 0.0
    )


def test_exact_inversion_saturation_tie_goes_to_the_bound_nearest_previous_command() -> None:
    model = bump_model()
    features = np.zeros((2, 3))
    f_0 = force(model, features[:1], np.zeros(1))
    f_2 = force(model, features[:1], np.full(1, I_MAX))
    assert f_0 == f_2  # the symmetric bump makes both bounds equally far from any force
    out = exact_inversion(model, features, 2.0, np.array([0.3, 1.7]), i_max=I_MAX)
    np.testing.assert_array_equal(out, [0.0, I_MAX])


def test_exact_inversion_picks_the_root_nearest_the_previous_command() -> None:
    model = bump_model()
    features = np.zeros((4, 3))
    i_prev = np.array([0.0, 0.9, 1.1, 2.0])
    i_star = exact_inversion(model, features, 1.0, i_prev, i_max=I_MAX)
    np.testing.assert_allclose(force(model, features, i_star), 1.0, rtol=0, atol=1e-9)
    assert np.all(i_star[:2] < 1.0) and np.all(i_star[2:] > 1.0)  # the roots straddle the peak
    np.testing.assert_allclose(i_star[:2] + i_star[2:][::-1], 2.0, atol=1e-9)  # symmetric


@pytest.mark.parametrize("monotone", [True, False])
def test_scalar_inverter_equals_batch_exact_inversion(monotone: bool) -> None:
    rng = np.random.default_rng(4)
    model = random_model(rng, monotone=monotone)
    features = random_features(rng, 300)
    f_des = force(model, features, rng.uniform(0.0, I_MAX, 300)) + rng.normal(0.0, 30.0, 300)
    i_prev = rng.uniform(0.0, I_MAX, 300)
    batch = exact_inversion(model, features, f_des, i_prev, i_max=I_MAX)
    inv = ScalarInverter(model, I_MAX)
    scalar = [inv.solve(features[n], f_des[n], i_prev[n]) for n in range(300)]
    np.testing.assert_allclose(scalar, batch, rtol=0, atol=1e-9)


def test_scalar_inverter_equals_batch_on_the_two_root_model() -> None:
    model = bump_model()
    i_prev = np.linspace(0.0, I_MAX, 21)
    f_des = np.linspace(-0.5, 2.0, 21)
    features = np.zeros((21, 3))
    batch = exact_inversion(model, features, f_des, i_prev, i_max=I_MAX)
    inv = ScalarInverter(model, I_MAX)
    scalar = [inv.solve(features[n], f_des[n], i_prev[n]) for n in range(21)]
    np.testing.assert_allclose(scalar, batch, rtol=0, atol=1e-9)


def test_gradient_inversion_descends_to_the_exact_root() -> None:
    rng = np.random.default_rng(5)
    model = random_model(rng, monotone=True)
    features = random_features(rng, 50)
    f_des = force(model, features, rng.uniform(0.2, 1.8, 50))
    exact = exact_inversion(model, features, f_des, 1.0, i_max=I_MAX)
    grad = gradient_inversion(
        model,
        features,
        f_des,
        i_max=I_MAX,
        rate=0.05,
        iterations=3000,
        rng=np.random.default_rng(0),
    )
    np.testing.assert_allclose(grad, exact, rtol=0, atol=1e-4)


def test_paper_rate_reduces_the_force_error_from_the_random_start() -> None:
    rng = np.random.default_rng(6)
    model = random_model(rng, monotone=True)
    features = random_features(rng, 200)
    f_des = force(model, features, rng.uniform(0.2, 1.8, 200))
    i0 = np.random.default_rng(7).uniform(0.0, I_MAX, 200)
    i_star = gradient_inversion(model, features, f_des, i_max=I_MAX, i0=i0)
    err0 = np.abs(force(model, features, i0) - f_des)
    err = np.abs(force(model, features, i_star) - f_des)
    assert np.mean(err) < 0.5 * np.mean(err0)


def test_scalar_gradient_path_equals_batch_with_the_same_seed() -> None:
    rng = np.random.default_rng(8)
    model = random_model(rng, monotone=True)
    features = random_features(rng, 20)
    f_des = force(model, features, rng.uniform(0.0, I_MAX, 20))
    batch = gradient_inversion(
        model, features, f_des, i_max=I_MAX, iterations=200, rng=np.random.default_rng(11)
    )
    inv = ScalarInverter(model, I_MAX, method="gradient", iterations=200, seed=11)
    scalar = [inv.solve(features[n], f_des[n], 0.0) for n in range(20)]
    np.testing.assert_allclose(scalar, batch, rtol=0, atol=1e-9)


def _objective(model: MLP, features: np.ndarray, f_des, i_prev, mu: float, i: np.ndarray):
    """J(i) of the regularised solve on currents i (N x M), evaluated through model.predict."""
    n, m = i.shape
    X = np.repeat(np.column_stack([features, np.zeros(len(features))])[:, None, :], m, axis=1)
    X[..., 3] = i
    f = model.predict(X.reshape(-1, 4)).reshape(n, m)
    c_std = model.in_std[model.current_index]
    return (f - f_des[:, None]) ** 2 / model.out_std**2 + mu * (i - i_prev[:, None]) ** 2 / c_std**2


@pytest.mark.parametrize("mu", [0.3, 1.0, 10.0])
@pytest.mark.parametrize("monotone", [True, False])
def test_continuity_solve_is_the_global_minimiser_of_its_objective(mu: float, monotone) -> None:
    rng = np.random.default_rng(11)
    model = random_model(rng, monotone=monotone)
    features = random_features(rng, 120)
    f_des = force(model, features, rng.uniform(0.0, I_MAX, 120)) + rng.normal(0.0, 50.0, 120)
    i_prev = rng.uniform(0.0, I_MAX, 120)
    got = exact_inversion(model, features, f_des, i_prev, i_max=I_MAX, continuity=mu)
    fine = np.broadcast_to(np.linspace(0.0, I_MAX, 4001), (120, 4001))
    J_fine = _objective(model, features, f_des, i_prev, mu, fine)
    J_got = _objective(model, features, f_des, i_prev, mu, got[:, None])[:, 0]
    assert np.all((got >= 0.0) & (got <= I_MAX))
    # never worse than the best of 4001 currents (to rounding), and close to it in current
    assert np.all(J_got <= J_fine.min(axis=1) + 1e-9)
    best = fine[0][np.argmin(J_fine, axis=1)]
    assert np.max(np.abs(got - best)) <= 2 * I_MAX / 4000


def test_continuity_solve_lies_between_the_root_and_the_previous_command() -> None:
    rng = np.random.default_rng(12)
    model = random_model(rng, monotone=True)
    features = random_features(rng, 300)
    f_des = force(model, features, rng.uniform(0.1, 1.9, 300))
    i_prev = rng.uniform(0.0, I_MAX, 300)
    root = exact_inversion(model, features, f_des, i_prev, i_max=I_MAX)
    reg = exact_inversion(model, features, f_des, i_prev, i_max=I_MAX, continuity=1.0)
    lo, hi = np.minimum(root, i_prev), np.maximum(root, i_prev)
    assert np.all((reg >= lo - 1e-9) & (reg <= hi + 1e-9))
    # and it is a real pull: strictly inside where the root and the previous command differ
    moved = np.abs(root - i_prev) > 0.1
    assert np.all(np.abs(reg[moved] - root[moved]) > 0.0)
    # a negligible weight gives the root back
    tiny = exact_inversion(model, features, f_des, i_prev, i_max=I_MAX, continuity=1e-12)
    np.testing.assert_allclose(tiny, root, atol=1e-5)


@pytest.mark.parametrize("monotone", [True, False])
def test_scalar_inverter_with_continuity_equals_batch(monotone: bool) -> None:
    rng = np.random.default_rng(13)
    model = random_model(rng, monotone=monotone)
    features = random_features(rng, 300)
    f_des = force(model, features, rng.uniform(0.0, I_MAX, 300)) + rng.normal(0.0, 30.0, 300)
    i_prev = rng.uniform(0.0, I_MAX, 300)
    batch = exact_inversion(model, features, f_des, i_prev, i_max=I_MAX, continuity=1.0)
    inv = ScalarInverter(model, I_MAX, continuity=1.0)
    scalar = [inv.solve(features[n], f_des[n], i_prev[n]) for n in range(300)]
    np.testing.assert_allclose(scalar, batch, rtol=0, atol=1e-9)


def test_negative_continuity_is_refused() -> None:
    model = random_model(np.random.default_rng(14))
    with pytest.raises(ValueError, match="continuity"):
        exact_inversion(model, np.zeros((1, 3)), 0.0, 0.0, i_max=I_MAX, continuity=-1.0)
    with pytest.raises(ValueError, match="continuity"):
        ScalarInverter(model, I_MAX, continuity=-1.0)


def test_scalar_inverter_force_is_the_models_force() -> None:
    rng = np.random.default_rng(15)
    model = random_model(rng)
    features = random_features(rng, 50)
    current = rng.uniform(0.0, I_MAX, 50)
    inv = ScalarInverter(model, I_MAX)
    got = [inv.force(features[n], current[n]) for n in range(50)]
    np.testing.assert_allclose(got, force(model, features, current), rtol=1e-12, atol=1e-9)


def _track(
    model: MLP, continuity: float, ahead: bool, seed: int = 16
) -> tuple[list, ScalarInverter]:
    """Inversion along a smooth path of samples, each solved from the previous answer; with
    `ahead`, every sample is first solved on a prediction of it (the sample plus a small
    innovation-sized error), as the daemon does while it waits for the frame."""
    rng = np.random.default_rng(seed)
    n = 400
    t = np.arange(n) * 0.002
    features = np.column_stack(
        [
            0.01 * np.sin(2 * np.pi * 3 * t),
            0.19 * np.cos(2 * np.pi * 3 * t),
            -3.5 * np.sin(2 * np.pi * 3 * t),
        ]
    )
    current = 0.9 + 0.6 * np.sin(2 * np.pi * 1.3 * t)
    f_des = force(model, features, current)
    predicted = features + rng.normal(0.0, [2e-5, 2e-3, 0.05], (n, 3))
    inv = ScalarInverter(model, I_MAX, continuity=continuity)
    out, i_prev = [], 0.0
    for k in range(n):
        if ahead:
            inv.prepare(predicted[k], f_des[k] + rng.normal(0.0, 5.0), i_prev)
        i_prev = inv.solve(features[k], f_des[k], i_prev)
        out.append(i_prev)
    return out, inv


@pytest.mark.parametrize("continuity", [0.0, 1.0])
@pytest.mark.parametrize("monotone", [True, False])
def test_solving_ahead_gives_the_full_solves_answers(continuity: float, monotone: bool) -> None:
    model = random_model(np.random.default_rng(17), monotone=monotone)
    full, inv_full = _track(model, continuity, ahead=False)
    ahead, inv = _track(model, continuity, ahead=True)
    np.testing.assert_allclose(ahead, full, rtol=0, atol=1e-6)
    assert inv_full.ahead_used == 0
    # the prediction is close: nearly every sample skips the grid
    assert inv.ahead_used >= 0.9 * len(ahead), (inv.ahead_used, inv.ahead_missed)


def test_a_prepared_solve_is_used_once_and_only_for_its_previous_command() -> None:
    model = random_model(np.random.default_rng(18), monotone=True)
    inv = ScalarInverter(model, I_MAX)
    feat = np.array([0.002, 0.05, -1.0])
    f = float(force(model, feat[None], np.array([1.1]))[0])
    inv.prepare(feat, f, 0.5)
    inv.solve(feat, f, 0.7)  # another previous command: the full solve
    assert (inv.ahead_used, inv.ahead_missed) == (0, 0)
    inv.prepare(feat, f, 0.5)
    assert inv.solve(feat, f, 0.5) == pytest.approx(1.1, abs=1e-6)
    inv.solve(feat, f, 0.5)  # consumed by the first solve
    assert (inv.ahead_used, inv.ahead_missed) == (1, 0)


def test_a_wrong_prediction_falls_back_to_the_full_solve() -> None:
    model = random_model(np.random.default_rng(19), monotone=True)
    inv = ScalarInverter(model, I_MAX)
    feat = np.array([0.002, 0.05, -1.0])
    f_lo, f_hi = force(model, np.array([feat, feat]), np.array([0.5, 1.8]))
    inv.prepare(feat, f_lo, 0.5)  # predicted: a root near 0.5 A; measured: one at 1.8 A
    got = inv.solve(feat, f_hi, 0.5)
    assert (inv.ahead_used, inv.ahead_missed) == (0, 1)
    assert got == pytest.approx(exact_inversion(model, feat[None], f_hi, 0.5, i_max=I_MAX)[0])
    assert got == pytest.approx(1.8, abs=1e-6)


@pytest.mark.parametrize("method", ["exact", "gradient"])
@pytest.mark.parametrize("f_des", [math.nan, math.inf])
def test_a_non_finite_desired_force_has_no_current(method: str, f_des: float) -> None:
    # the bracket's comparisons are all false for NaN: the exact solve gave a finite current
    # (0 A here; 0.0625 A in a daemon whose reference went NaN)
    model = random_model(np.random.default_rng(3), monotone=True)
    inv = ScalarInverter(model, I_MAX, method=method)
    feat = np.array([0.002, 0.05, -1.0])
    inv.prepare(feat, 100.0, 0.5)
    assert math.isnan(inv.solve(feat, f_des, 0.5))


def test_an_ambiguous_root_is_not_followed_ahead() -> None:
    model = bump_model()  # two roots, symmetric about 1 A, for a force below the peak
    inv = ScalarInverter(model, I_MAX)
    zero = np.zeros(3)
    f_pk = float(force(model, zero[None], np.array([1.0]))[0])
    inv.prepare(zero, 0.9 * f_pk, 1.0)  # both roots equally near the previous command
    inv.solve(zero, 0.9 * f_pk, 1.0)
    assert (inv.ahead_used, inv.ahead_missed) == (0, 0)
