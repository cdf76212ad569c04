"""Excitation signals with exact derivatives: sines and band-limited Gaussian noise."""

from __future__ import annotations

import numpy as np


def sine(
    t_s: np.ndarray, amplitude: float, freq_hz: float, phase: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x = amplitude * sin(2 pi f t + phase), with its first and second derivatives."""
    t_s = np.asarray(t_s, dtype=float)
    w = 2.0 * np.pi * freq_hz
    arg = w * t_s + phase
    s, c = np.sin(arg), np.cos(arg)
    return amplitude * s, amplitude * w * c, -amplitude * w * w * s


def bandlimited_noise(
    n: int,
    dt_s: float,
    f_hi_hz: float,
    peak: float,
    rng: np.random.Generator,
    f_lo_hz: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gaussian white noise band-passed to [f_lo_hz, f_hi_hz], scaled so that max|x| = peak.

    The filter is a brick wall on the FFT bins, so the signal is periodic over n samples and
    its derivatives (spectral, exact for the periodic signal) are returned with it. The DC bin
    is always dropped: the signal has zero mean. The same Generator state gives the same signal.
    """
    if n < 2 or not dt_s > 0.0:
        raise ValueError(f"need n >= 2 and dt_s > 0, got n={n}, dt_s={dt_s}")
    freqs = np.fft.rfftfreq(n, dt_s)
    keep = (freqs >= f_lo_hz) & (freqs <= f_hi_hz) & (freqs > 0.0)
    if n % 2 == 0:
        keep[-1] = False  # the Nyquist bin's derivative is not real
    if not keep.any():
        raise ValueError(
            f"no FFT bin in [{f_lo_hz}, {f_hi_hz}] Hz for n={n}, dt_s={dt_s} "
            f"(resolution {1.0 / (n * dt_s):g} Hz)"
        )
    spec = np.fft.rfft(rng.standard_normal(n)) * keep
    jw = 2j * np.pi * freqs
    x = np.fft.irfft(spec, n)
    xd = np.fft.irfft(spec * jw, n)
    xdd = np.fft.irfft(spec * jw * jw, n)
    scale = peak / np.max(np.abs(x))
    return x * scale, xd * scale, xdd * scale
