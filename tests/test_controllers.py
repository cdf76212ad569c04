"""Controllers: the daemon's float path `command_one` is `command` on a batch of one."""

from __future__ import annotations

import numpy as np
import pytest

from mrrig.loop.controllers import (
    ContinuousState,
    ControlInput,
    Controller,
    Heaviside,
    NetworkInversion,
)
from tests.test_inversion import I_MAX, random_model


def _controllers() -> dict[str, Controller]:
    model = random_model(np.random.default_rng(21), monotone=True)
    lagged = random_model(np.random.default_rng(21), monotone=True)
    lagged.meta.update(current_input="lagged", lag_tau_s=1.0 / 190.0)
    return {
        "heaviside": Heaviside(I_MAX),
        "continuous_state": ContinuousState(I_MAX),
        "ni_root": NetworkInversion(I_MAX, model),
        "ni_feedback": NetworkInversion(I_MAX, model, feedback_tau_s=0.004),
        "ni_continuity_feedback": NetworkInversion(
            I_MAX, model, feedback_tau_s=0.004, continuity=1.0
        ),
        "ni_flow_lagged_feedback_0": NetworkInversion(
            I_MAX, lagged, method="flow", feedback_tau_s=0.0, ahead=True
        ),
        "ni_lagged_ahead_feedback_0": NetworkInversion(
            I_MAX, lagged, feedback_tau_s=0.0, continuity=0.03, ahead=True
        ),
    }


def _run(seed: int, n: int = 300) -> tuple[np.ndarray, ...]:
    """(x, xd, xdd, f_meas, f_des) of a 3 Hz run at 2 ms, the load cell noisy."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.002
    x = 0.015 * np.sin(2 * np.pi * 3 * t)
    xd = 0.015 * 2 * np.pi * 3 * np.cos(2 * np.pi * 3 * t)
    xdd = -((2 * np.pi * 3) ** 2) * x
    f_meas = 800 * np.sin(2 * np.pi * 3 * t + 0.2) + rng.normal(0, 20, n)
    f_des = 600 * np.sin(2 * np.pi * 3 * t + 0.3)
    return x, xd, xdd, f_meas, f_des


def _pair(name: str) -> tuple[Controller, Controller]:
    """Two fresh, reset instances of the same controller."""
    a, b = _controllers()[name], _controllers()[name]
    a.reset(1)
    b.reset(1)
    return a, b


@pytest.mark.parametrize("name", list(_controllers()))
def test_float_path_equals_the_batch_of_one_over_a_run(name: str) -> None:
    x, xd, xdd, f_meas, f_des = _run(22)
    a, b = _pair(name)
    got, want = [], []
    for k in range(len(x)):
        got.append(a.command_one(x[k], xd[k], xdd[k], f_meas[k], f_des[k]))
        s = ControlInput(*(np.array([v[k]]) for v in (x, xd, xdd, f_meas, f_des)))
        want.append(float(b.command(s)[0]))
    assert all(isinstance(v, float) for v in got)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert 0.0 < np.ptp(want)  # the run exercises the controller


@pytest.mark.parametrize("name", list(_controllers()))
def test_working_ahead_on_a_predicted_state_changes_no_command(name: str) -> None:
    """The daemon calls prepare_one with the predicted next state and target while it waits
    for a frame; the command for the measured frame is the same as without it."""
    x, xd, xdd, f_meas, f_des = _run(23)
    a, b = _pair(name)
    got, want = [], []
    for k in range(len(x)):
        if k:  # the prediction misses the frame by an innovation and the target by a little
            a.prepare_one(x[k] + 2e-5, xd[k] - 3e-3, xdd[k] + 0.1, f_des[k] + 4.0)
        got.append(a.command_one(x[k], xd[k], xdd[k], f_meas[k], f_des[k]))
        want.append(b.command_one(x[k], xd[k], xdd[k], f_meas[k], f_des[k]))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    if isinstance(a, NetworkInversion) and a.method == "exact":
        # the path is exercised; how often it saves the full solve depends on how well the
        # state and the target were predicted (`mrrig bench loop` prints it for the rig)
        assert a._scalar.ahead_used > 0
