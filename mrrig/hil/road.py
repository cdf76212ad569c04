"""ISO 8608 road profiles (spec/hil.md, substructure 1) and bump / pothole events.

The displacement PSD of a class is Gd(n) = Gd(n0) (n / n0)^-2 with n0 = 0.1 cycle/m and the
class's geometric mean Gd(n0) = 16 e-6 m^3 (A) times 4 per class up to H. A profile is the
sum of harmonics over 0.011-2.83 cycle/m (ISO 8608's band), one per frequency line of an
inverse FFT, of amplitude sqrt(2 Gd(n) dn) and seeded random phase: its one-sided PSD is
Gd(n) on every line, so a Welch estimate scatters around Gd(n) only by the estimator's own
variance (tests/test_hil_road.py states the tolerance).

At speed V the road is sampled at dx = V dt, one sample per loop period (n = f / V).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ISO_CLASSES = "ABCDEFGH"
N0_CYCLE_PER_M = 0.1
# ISO 8608's band of spatial frequencies
N_MIN_CYCLE_PER_M = 0.011
N_MAX_CYCLE_PER_M = 2.83


def gd_n0_m3(iso_class: str) -> float:
    """Gd(n0), the class's geometric mean: 16, 64, 256, 1024 e-6 m^3 for A-D (x4 per class)."""
    if iso_class not in ISO_CLASSES or len(iso_class) != 1:
        raise ValueError(f"unknown ISO 8608 class {iso_class!r}; known: {', '.join(ISO_CLASSES)}")
    return 16e-6 * 4.0 ** ISO_CLASSES.index(iso_class)


def gd_m3(n_cycle_per_m: np.ndarray, iso_class: str) -> np.ndarray:
    """Gd(n) = Gd(n0) (n / n0)^-2 (ISO 8608, the displacement PSD, m^3)."""
    n = np.asarray(n_cycle_per_m, dtype=float)
    return gd_n0_m3(iso_class) * (n / N0_CYCLE_PER_M) ** -2.0


@dataclass(frozen=True)
class Bump:
    """A half-sine event: `height_m` > 0 a bump, < 0 a pothole, `length_m` long, starting
    `at_m` along the road."""

    height_m: float
    length_m: float
    at_m: float

    def profile_m(self, x_m: np.ndarray) -> np.ndarray:
        """z(x) = h sin(pi (x - x_b) / l) on [x_b, x_b + l], else 0."""
        phase = (np.asarray(x_m, dtype=float) - self.at_m) / self.length_m
        inside = (phase >= 0.0) & (phase <= 1.0)
        return np.where(inside, self.height_m * np.sin(math.pi * np.clip(phase, 0.0, 1.0)), 0.0)


def spatial_profile_m(
    iso_class: str, length_m: float, dx_m: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """(x, z): a road of `length_m` sampled every `dx_m`, harmonics over ISO 8608's band (those
    the record's length and sampling can hold), seeded phases."""
    if not (length_m > 0.0 and dx_m > 0.0):
        raise ValueError(f"length_m and dx_m must be positive, got {length_m}, {dx_m}")
    n_samples = max(2, math.ceil(length_m / dx_m) + 1)
    dn = 1.0 / (n_samples * dx_m)
    n = np.arange(n_samples // 2 + 1) * dn
    band = (n >= N_MIN_CYCLE_PER_M) & (n <= N_MAX_CYCLE_PER_M)
    amplitude = np.zeros_like(n)
    amplitude[band] = np.sqrt(2.0 * gd_m3(n[band], iso_class) * dn)
    phase = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi, n.size)
    # irfft(X)[j] = sum_k A_k cos(2 pi k j / N + phi_k) for X_k = N/2 A_k e^(i phi_k)
    z = np.fft.irfft(0.5 * n_samples * amplitude * np.exp(1j * phase), n_samples)
    return np.arange(n_samples) * dx_m, z


def road_input_m(
    iso_class: str,
    speed_m_s: float,
    duration_s: float,
    period_s: float,
    seed: int,
    bumps: tuple[Bump, ...] = (),
) -> np.ndarray:
    """The road height under the wheel at every loop period, t_k = k * period_s, k = 0..K
    (K = duration / period), the wheel at x = V t_k; the bumps added on the road."""
    if not speed_m_s > 0.0:
        raise ValueError(f"speed_m_s must be positive, got {speed_m_s}")
    steps = max(1, round(duration_s / period_s))
    x, z = spatial_profile_m(iso_class, speed_m_s * period_s * steps, speed_m_s * period_s, seed)
    x, z = x[: steps + 1], z[: steps + 1]
    for bump in bumps:
        z = z + bump.profile_m(x)
    return z
