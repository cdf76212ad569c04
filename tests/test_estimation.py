import numpy as np
import pytest

from mrrig.loop.estimation import KalmanEstimator, finite_difference
from mrrig.offline.bench.estimation import AMPLITUDES_M, FREQUENCIES_HZ, noisy_sine_run
from mrrig.offline.metrics import rmse

DT_S = 0.002


def test_kalman_beats_finite_difference_on_velocity_and_acceleration_on_noisy_runs():
    rng = np.random.default_rng(7)
    skip = 100  # 0.2 s of filter start-up
    est = KalmanEstimator(DT_S)
    kf_v, fd_v, kf_a, fd_a = [], [], [], []
    for amp in AMPLITUDES_M:
        for freq in FREQUENCIES_HZ:
            x, xd_true, xdd_true = noisy_sine_run(amp, freq, rng, duration_s=1.5)
            _, xd, xdd = est.estimate(x)
            fxd, fxdd = finite_difference(x, DT_S)
            kf_v.append(rmse(xd[skip:], xd_true[skip:]))
            fd_v.append(rmse(fxd[skip:], xd_true[skip:]))
            kf_a.append(rmse(xdd[skip:], xdd_true[skip:]))
            fd_a.append(rmse(fxdd[skip:], xdd_true[skip:]))
    med = [float(np.median(v)) for v in (kf_v, fd_v, kf_a, fd_a)]
    msg = (
        f"median RMSE velocity KF {med[0]:.4f} vs FD {med[1]:.4f} m/s, "
        f"acceleration KF {med[2]:.3f} vs FD {med[3]:.3f} m/s^2"
    )
    assert med[0] < med[1], msg
    assert med[2] < med[3], msg


def test_eq24_measurement_variance_shrinks_as_speed_grows():
    est = KalmanEstimator(DT_S, r0=4e-10)
    speeds = np.linspace(0.0, 1.0, 11)
    r = np.array([est.measurement_variance(v) for v in speeds])
    assert r[0] == pytest.approx(4e-10)
    assert np.all(np.diff(r) < 0)
    assert est.measurement_variance(-0.75) == est.measurement_variance(0.75)
    assert est.measurement_variance(0.75) == pytest.approx(4e-10 / 1.75)


def test_eq24_filter_uses_the_predicted_velocity_for_r():
    est = KalmanEstimator(DT_S, r0=4e-10)
    est.reset(0.0)
    est.kf.x = np.array([[0.01], [-0.6], [3.0]])
    prior_xd = (est.kf.F @ est.kf.x)[1, 0]
    est.update(0.0085)
    assert est.kf.R[0, 0] == pytest.approx(4e-10 / (1.0 + abs(prior_xd)), rel=1e-12)


def test_estimate_of_a_series_equals_sample_by_sample_update():
    rng = np.random.default_rng(3)
    x, _, _ = noisy_sine_run(0.015, 4.0, rng, duration_s=0.5)
    x[50:53] = np.nan  # a gap: missing samples in both paths
    batch = np.column_stack(KalmanEstimator(DT_S).estimate(x))
    est = KalmanEstimator(DT_S)
    est.reset(float(x[0]))
    step = np.array([est.update(None if np.isnan(v) else float(v)) for v in x])
    np.testing.assert_array_equal(batch, step)


def test_missing_sample_keeps_the_prediction():
    rng = np.random.default_rng(4)
    x, _, _ = noisy_sine_run(0.02, 5.0, rng, duration_s=0.2)
    est = KalmanEstimator(DT_S)
    est.estimate(x)
    kf = est.kf
    x_prev, p_prev = kf.x.copy(), kf.P.copy()
    got = est.update(None)
    np.testing.assert_allclose(got, (kf.F @ x_prev)[:, 0], rtol=1e-14, atol=0)
    np.testing.assert_allclose(kf.P, kf.F @ p_prev @ kf.F.T + kf.Q, rtol=1e-14)
    x_prev = kf.x.copy()
    got = est.predict_only()
    np.testing.assert_allclose(got, (kf.F @ x_prev)[:, 0], rtol=1e-14, atol=0)


def test_exact_on_noiseless_constant_acceleration_after_convergence():
    t = np.arange(1000) * DT_S
    x0, v0, a0 = -0.01, 0.3, -4.0
    x = x0 + v0 * t + 0.5 * a0 * t * t
    xf, xd, xdd = KalmanEstimator(DT_S).estimate(x)
    late = t >= 1.0
    np.testing.assert_allclose(xf[late], x[late], atol=1e-9)
    np.testing.assert_allclose(xd[late], v0 + a0 * t[late], atol=1e-7)
    np.testing.assert_allclose(xdd[late], a0, atol=1e-5)


def test_finite_difference_is_causal():
    rng = np.random.default_rng(5)
    x, _, _ = noisy_sine_run(0.01, 3.0, rng, duration_s=0.4)
    changed = x.copy()
    changed[120:] += 0.003
    a, b = finite_difference(x, DT_S), finite_difference(changed, DT_S)
    for before, after in zip(a, b, strict=True):
        np.testing.assert_array_equal(before[:120], after[:120])
        assert not np.array_equal(before[120:], after[120:])


def test_finite_difference_eqs_15_16_settle_to_velocity_and_acceleration():
    t = np.arange(500) * DT_S
    xd, _ = finite_difference(0.002 + 0.25 * t, DT_S)
    _, xdd = finite_difference(0.5 * 6.0 * t * t, DT_S)
    assert xd[-1] == pytest.approx(0.25, rel=1e-9)
    assert xdd[-1] == pytest.approx(6.0, rel=1e-9)


def _noisy_sine(seconds: float, seed: int) -> np.ndarray:
    """A 15 mm, 4 Hz stroke sampled at the rig's 2 ms with 20 um of sensor noise."""
    t = np.arange(0, seconds, 0.002)
    return 0.015 * np.sin(2 * np.pi * 4 * t) + np.random.default_rng(seed).normal(0, 2e-5, t.size)


def test_realtime_kalman_equals_filterpy_kalman():
    from mrrig.loop.estimation import KalmanEstimator, RealtimeKalman

    x = _noisy_sine(2.0, seed=3)
    ref, fast = KalmanEstimator(0.002), RealtimeKalman(0.002)
    ref.reset(x[0])
    fast.reset(x[0])
    for k, v in enumerate(x):
        meas = None if k % 97 == 50 else float(v)  # a few missing samples too
        a, b = ref.update(meas), fast.update(meas)
        assert np.allclose(a, b, rtol=1e-9, atol=1e-12), (k, a, b)


def test_realtime_kalman_prepared_ahead_is_the_same_filter_and_affine_in_the_measurement():
    from mrrig.loop.estimation import RealtimeKalman

    x = _noisy_sine(1.0, seed=4)
    plain, ahead = RealtimeKalman(0.002), RealtimeKalman(0.002)
    plain.reset(x[0])
    ahead.reset(x[0])
    for k, v in enumerate(x):
        meas = None if k % 61 == 30 else float(v)
        ahead.prepare()
        ahead.prepare()  # idempotent until the update
        prior, gain = ahead.prior, ahead.gain
        got = ahead.update(meas)
        assert got == plain.update(meas), k
        if meas is None:
            assert got == prior
        else:
            want = [p + g * (meas - prior[0]) for p, g in zip(prior, gain, strict=True)]
            assert np.allclose(got, want, rtol=1e-12, atol=1e-15), k
