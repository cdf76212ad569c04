"""Network inversion for the instant the command acts on: the coil lag inverted (a model of
the lagged current), the state one period ahead, the last load-cell residual as it is."""

from __future__ import annotations

import math

import numpy as np
import pytest

from damper.plant import BoucWenParams
from mrrig.loop.controllers import ControlInput, Controller, NetworkInversion
from mrrig.loop.inversion import ScalarInverter, exact_inversion, flow_inversion, gradient_inversion
from mrrig.loop.mlp import MLP
from mrrig.offline.simulation import closed_loop
from tests.test_inversion import I_MAX, random_model

DT_S = 1e-3
LAG_TAU_S = 1.0 / 190.0


def _lagged_model():
    model = random_model(np.random.default_rng(31), monotone=True)
    model.meta.update(current_input="lagged", lag_tau_s=LAG_TAU_S)
    return model


def _input(x, xd, xdd, f_meas, f_des, f_des_next=None) -> ControlInput:
    a = [np.array([v]) for v in (x, xd, xdd, f_meas, f_des)]
    return ControlInput(*a, None if f_des_next is None else np.array([f_des_next]))


def test_a_model_of_the_lagged_current_gets_the_command_that_lags_onto_the_root():
    model = _lagged_model()
    ctrl = NetworkInversion(I_MAX, model, dt_s=DT_S)
    share = -math.expm1(-DT_S / LAG_TAU_S)  # eq. 36 over one held period
    state = np.array([[0.002, 0.05, 1.0]])
    root = 0.5 * share * I_MAX  # reachable in one period from u = 0 without clipping
    f_des = model.predict(np.append(state[0], root)[None, :])
    ctrl.reset(1)
    v = ctrl.command(_input(*state[0], 0.0, f_des[0]))[0]
    u = share * v  # the coil's current one period on, from 0
    np.testing.assert_allclose(u, root, atol=1e-6)
    # the controller tracks u from its commands: the next solve starts from there
    v2 = ctrl.command(_input(*state[0], 0.0, f_des[0]))[0]
    np.testing.assert_allclose(u + share * (v2 - u), root, atol=1e-6)


def test_a_model_of_the_commanded_current_is_solved_for_the_command_itself():
    model = random_model(np.random.default_rng(31), monotone=True)
    ctrl = NetworkInversion(I_MAX, model, dt_s=DT_S)
    state = np.array([[0.002, 0.05, 1.0]])
    f_des = model.predict(np.append(state[0], 0.1)[None, :])
    ctrl.reset(1)
    np.testing.assert_allclose(ctrl.command(_input(*state[0], 0.0, f_des[0]))[0], 0.1, atol=1e-6)


def test_a_lagged_model_without_its_lag_is_refused():
    model = random_model(np.random.default_rng(31))
    model.meta.update(current_input="lagged")
    with pytest.raises(ValueError, match="lag_tau_s"):
        NetworkInversion(I_MAX, model)


def test_ahead_solves_at_the_predicted_state_for_the_next_target():
    model = random_model(np.random.default_rng(32), monotone=True)
    x, xd, xdd = 0.004, -0.08, 3.0
    f_now, f_next = 150.0, 180.0
    ctrl = NetworkInversion(I_MAX, model, dt_s=DT_S, ahead=True)
    ctrl.reset(1)
    got = ctrl.command(_input(x, xd, xdd, 0.0, f_now, f_next))
    # eq. 21: constant acceleration over one period
    ahead = [[x + xd * DT_S + 0.5 * xdd * DT_S**2, xd + xdd * DT_S, xdd]]
    want = exact_inversion(model, np.array(ahead), f_next, 0.0, i_max=I_MAX)
    np.testing.assert_allclose(got, want, atol=1e-9)
    present = exact_inversion(model, np.array([[x, xd, xdd]]), f_next, 0.0, i_max=I_MAX)
    assert abs(got[0] - present[0]) > 1e-6  # the prediction matters
    # without the next target: the present instant
    ctrl.reset(1)
    got = ctrl.command(_input(x, xd, xdd, 0.0, f_now))
    want = exact_inversion(model, np.array([[x, xd, xdd]]), f_now, 0.0, i_max=I_MAX)
    np.testing.assert_allclose(got, want, atol=1e-9)


def test_ahead_needs_a_model_without_history_inputs():
    hist = MLP(
        ["x", "xd", "xdd", "current", "x_1"],
        ["m", "m/s", "m/s^2", "A", "m"],
        "force",
        "N",
        in_mean=np.zeros(5),
        in_std=np.ones(5),
        out_mean=0.0,
        out_std=1.0,
        W1=np.ones((2, 5)),
        b1=np.zeros(2),
        W2=np.ones(2),
        b2=0.0,
    )
    with pytest.raises(ValueError, match="history"):
        NetworkInversion(I_MAX, hist, ahead=True)


def test_feedback_tau_zero_corrects_by_the_last_residual_as_it_is():
    model = random_model(np.random.default_rng(34), monotone=True)
    ctrl = NetworkInversion(I_MAX, model, feedback_tau_s=0.0, dt_s=DT_S)
    ctrl.reset(1)
    state = np.array([[0.001, 0.02, 0.5]])
    ctrl.command(_input(*state[0], 0.0, 100.0))
    prev = ctrl.command(_input(*state[0], 0.0, 100.0))
    f_meas = 130.0
    got = ctrl.command(_input(*state[0], f_meas, 100.0))
    residual = f_meas - model.predict(np.append(state[0], prev)[None, :])
    want = exact_inversion(model, state, 100.0 - residual, prev, i_max=I_MAX)
    np.testing.assert_allclose(got, want, atol=1e-9)
    with pytest.raises(ValueError, match="feedback_tau_s"):
        NetworkInversion(I_MAX, model, feedback_tau_s=-0.001)


class _Recorder(Controller):
    def reset(self, batch: int = 1) -> None:
        super().reset(batch)
        self.seen: list[tuple[np.ndarray, np.ndarray]] = []

    def command(self, s: ControlInput) -> np.ndarray:
        assert s.f_des_next is not None
        self.seen.append((s.f_des.copy(), s.f_des_next.copy()))
        return np.zeros(np.shape(s.f_des))


def test_closed_loop_gives_the_controller_the_next_target():
    n = 5
    t = np.arange(n) * DT_S
    x = 0.01 * np.sin(2 * np.pi * t)[None, :]
    f_des = np.array([[1.0, 2.0, 3.0, 4.0, 5.0], [10.0, 20.0, 30.0, 40.0, 50.0]])
    ctrl = _Recorder(I_MAX)
    closed_loop(
        ctrl,
        BoucWenParams.preset("paper-volt"),
        DT_S,
        np.repeat(x, 2, 0),
        0 * f_des,
        0 * f_des,
        f_des,
    )
    now = np.array([a for a, _ in ctrl.seen]).T
    nxt = np.array([b for _, b in ctrl.seen]).T
    np.testing.assert_array_equal(now, f_des)
    np.testing.assert_array_equal(nxt[:, :-1], f_des[:, 1:])
    np.testing.assert_array_equal(nxt[:, -1], f_des[:, -1])


def test_ahead_with_feedback_extrapolates_the_residual_to_the_next_instant():
    model = random_model(np.random.default_rng(35), monotone=True)
    ctrl = NetworkInversion(I_MAX, model, feedback_tau_s=0.0, dt_s=DT_S, ahead=True)
    ctrl.reset(1)
    x, xd, xdd = 0.002, 0.03, 0.0  # constant velocity: the state moves, eq. 21
    T = DT_S

    def at(k):
        return np.array([[x + xd * k * T, xd, xdd]])

    def residual(k, f_meas, current):
        return f_meas - model.predict(np.append(at(k)[0], current)[None, :])[0]

    i0 = ctrl.command(_input(*at(0)[0], 100.0, 90.0, 95.0))[0]
    r0 = residual(0, 100.0, 0.0)  # the first instant: no rate yet
    np.testing.assert_allclose(
        i0, exact_inversion(model, at(1), 95.0 - r0, 0.0, i_max=I_MAX), atol=1e-9
    )
    i1 = ctrl.command(_input(*at(1)[0], 120.0, 95.0, 97.0))[0]
    r1 = residual(1, 120.0, i0)
    want = exact_inversion(model, at(2), 97.0 - (2 * r1 - r0), i0, i_max=I_MAX)
    np.testing.assert_allclose(i1, want, atol=1e-9)


def test_the_flow_ends_where_the_papers_1000_descent_steps_end():
    model = random_model(np.random.default_rng(36), monotone=True)
    rng = np.random.default_rng(37)
    feats = rng.normal(size=(200, 3)) * [0.01, 0.1, 5.0]
    f_des = rng.uniform(-400.0, 600.0, 200)
    i0 = rng.uniform(0.0, I_MAX, 200)
    want = gradient_inversion(model, feats, f_des, i_max=I_MAX, i0=i0)
    err = {
        n: np.abs(flow_inversion(model, feats, f_des, i_max=I_MAX, i0=i0, steps=n) - want)
        for n in (1, 4, 64)
    }
    assert err[64].max() < 0.01 * I_MAX
    assert err[1].mean() > err[4].mean() > err[64].mean()  # converges with the steps
    with pytest.raises(ValueError, match="steps"):
        flow_inversion(model, feats, f_des, i_max=I_MAX, steps=0)


def test_the_descent_run_longer_stays_on_the_flow_and_ends_at_the_root():
    """`bench paper --descent-sweep`'s rows: the flow at longer descent times is the paper's
    descent with more iterations, and at descent time 100 it is the exact root."""
    model = random_model(np.random.default_rng(36), monotone=True)
    rng = np.random.default_rng(37)
    feats = rng.normal(size=(200, 3)) * [0.01, 0.1, 5.0]
    f_des = rng.uniform(-400.0, 600.0, 200)
    i0 = rng.uniform(0.0, I_MAX, 200)
    longer = gradient_inversion(model, feats, f_des, i_max=I_MAX, i0=i0, iterations=10_000)
    flow = flow_inversion(model, feats, f_des, i_max=I_MAX, i0=i0, duration=10.0)
    assert np.abs(flow - longer).max() < 1e-3 * I_MAX
    # 4 steps for the whole of it overshoot where the force bends: the steps grow with it
    few = flow_inversion(model, feats, f_des, i_max=I_MAX, i0=i0, duration=100.0, steps=4)
    root = exact_inversion(model, feats, f_des, i0, i_max=I_MAX)
    end = flow_inversion(model, feats, f_des, i_max=I_MAX, i0=i0, duration=100.0)
    np.testing.assert_allclose(end, root, atol=1e-9)
    assert np.abs(few - root).max() > 0.1 * I_MAX
    # the scalar path takes the same steps
    inv = ScalarInverter(model, I_MAX)
    rows = zip(feats[:20], f_des[:20], i0[:20], strict=True)
    one = [inv.flow(f, d, s, 100.0) for f, d, s in rows]
    np.testing.assert_allclose(one, root[:20], atol=1e-9)


def test_network_inversion_by_the_flow_uses_it_from_the_current_now():
    model = random_model(np.random.default_rng(38), monotone=True)
    ctrl = NetworkInversion(I_MAX, model, method="flow", dt_s=DT_S)
    ctrl.reset(1)
    state = np.array([[0.001, 0.02, 0.5]])
    first = ctrl.command(_input(*state[0], 0.0, 100.0))
    got = ctrl.command(_input(*state[0], 0.0, 150.0))
    want = flow_inversion(model, state, 150.0, i_max=I_MAX, i0=first)
    np.testing.assert_allclose(got, want, atol=1e-12)
