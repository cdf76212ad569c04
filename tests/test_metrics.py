import math

import numpy as np
import pytest

from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.loop.summary import summarize
from mrrig.offline.metrics import error_norm, percentiles, rmse


def test_error_norm_matches_hand_computed_example():
    f_des = np.array([1.0, 3.0, 5.0, 7.0])  # mean 4, sum sq dev = 9+1+1+9 = 20
    f_act = np.array([2.0, 3.0, 4.0, 7.0])  # sum sq err = 1+0+1+0 = 2
    assert error_norm(f_des, f_act) == pytest.approx(np.sqrt(2.0 / 20.0), abs=1e-15)


def test_error_norm_is_zero_for_perfect_tracking_and_one_for_mean_guess():
    f = np.sin(np.linspace(0, 6, 100))
    assert error_norm(f, f) == 0.0
    assert error_norm(f, np.full_like(f, f.mean())) == pytest.approx(1.0)


def test_rmse_and_percentiles():
    assert rmse([0, 0], [3, 4]) == pytest.approx(np.sqrt(12.5))
    p = percentiles(np.arange(101.0), (50, 99))
    assert p == {"p50": 50.0, "p99": 99.0, "max": 100.0}


def test_summary_et_is_undefined_without_a_varying_armed_target():
    s = np.zeros(4, dtype=SAMPLE_DTYPE)
    s["t"] = [0.0, 0.002, 0.004, 0.006]
    s["f_des"] = [100.0, 200.0, 300.0, 400.0]
    s["f_meas"] = [110.0, 190.0, 310.0, 390.0]
    s["state"] = RigState.IDLE
    s["state"][2] = RigState.ARMED  # one armed frame: no spread to normalise by
    assert math.isnan(summarize(s, [])["et"])
    s["state"] = RigState.ARMED
    assert summarize(s, [])["et"] == pytest.approx(error_norm(s["f_des"], s["f_meas"]))
    s["f_des"] = 250.0  # a constant target
    assert math.isnan(summarize(s, [])["et"])
