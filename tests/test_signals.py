import numpy as np
import pytest

from damper.signals import bandlimited_noise, sine


def test_sine_returns_the_analytic_derivatives():
    t = np.array([0.0, 0.013, 0.21])
    x, xd, xdd = sine(t, 0.015, 4.0, phase=0.3)
    w = 2 * np.pi * 4.0
    np.testing.assert_allclose(x, 0.015 * np.sin(w * t + 0.3))
    np.testing.assert_allclose(xd, 0.015 * w * np.cos(w * t + 0.3))
    np.testing.assert_allclose(xdd, -(w**2) * x)


def _noise(seed, **kw):
    args = dict(n=4000, dt_s=1e-3, f_hi_hz=3.0, peak=0.025) | kw
    return bandlimited_noise(rng=np.random.default_rng(seed), **args)


def test_noise_peak_is_exact():
    x, _, _ = _noise(1)
    assert np.max(np.abs(x)) == pytest.approx(0.025, rel=1e-12)


def test_noise_has_no_energy_outside_the_band_and_no_mean():
    x, _, _ = _noise(2, f_lo_hz=1.0)
    spec = np.abs(np.fft.rfft(x))
    freqs = np.fft.rfftfreq(x.size, 1e-3)
    outside = (freqs < 1.0) | (freqs > 3.0)
    assert spec[outside].max() < 1e-12 * spec.max()
    assert spec[~outside].min() > 0.0


def test_noise_derivatives_match_finite_differences():
    x, xd, xdd = _noise(3)
    dt = 1e-3
    # periodic central differences; their error at 3 Hz, 1 ms is ~(w dt)^2/6 = 6e-5 relative
    fd1 = (np.roll(x, -1) - np.roll(x, 1)) / (2 * dt)
    fd2 = (np.roll(x, -1) - 2 * x + np.roll(x, 1)) / dt**2
    assert np.max(np.abs(fd1 - xd)) < 1e-3 * np.max(np.abs(xd))
    assert np.max(np.abs(fd2 - xdd)) < 1e-3 * np.max(np.abs(xdd))


def test_noise_is_reproducible_from_the_seed():
    a, b, c = _noise(7)[0], _noise(7)[0], _noise(8)[0]
    np.testing.assert_array_equal(a, b)
    assert np.max(np.abs(a - c)) > 1e-3


def test_noise_band_without_any_bin_is_rejected():
    with pytest.raises(ValueError, match="no FFT bin"):
        _noise(1, n=100, f_hi_hz=3.0)  # resolution 10 Hz
