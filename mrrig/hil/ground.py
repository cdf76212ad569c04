"""Seeded ground acceleration for the building (spec/hil.md, substructure 2): white noise through
a Kanai-Tajimi filter, times an envelope, scaled to a peak ground acceleration.

Kanai-Tajimi (Kanai 1957, Tajimi 1960): x_f'' + 2 zeta_g w_g x_f' + w_g^2 x_f = -w(t) and
a_g = x_f'' + w = -(2 zeta_g w_g x_f' + w_g^2 x_f), whose PSD is
S0 (w_g^4 + 4 zeta_g^2 w_g^2 w^2) / ((w_g^2 - w^2)^2 + 4 zeta_g^2 w_g^2 w^2).
Envelope (Shinozuka & Sato 1967's shape): (t / t1)^2 rising, 1 up to t2, exp(-c (t - t2)) after.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mrrig.hil.substructure import zoh


@dataclass(frozen=True)
class GroundMotion:
    """Kanai-Tajimi ground motion. The defaults fit the 1:10 scale model of Dyke et al. (1996)
    (its first mode about 5.4 Hz from these matrices; El Centro was played 5 times faster
    there): a ground frequency of 5 Hz."""

    pga_m_s2: float = 1.5
    ground_frequency_hz: float = 5.0
    ground_damping: float = 0.6
    rise_s: float = 1.0
    strong_until_s: float = 6.0
    decay_per_s: float = 0.5
    seed: int = 1

    def check(self) -> None:
        for name in ("pga_m_s2", "ground_frequency_hz", "ground_damping", "decay_per_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name}: must be positive, got {getattr(self, name)}")
        if not 0.0 <= self.rise_s <= self.strong_until_s:
            raise ValueError(
                f"rise_s: must be between 0 and strong_until_s ({self.strong_until_s}), "
                f"got {self.rise_s}"
            )


def envelope(t_s: np.ndarray, g: GroundMotion) -> np.ndarray:
    t = np.asarray(t_s, dtype=float)
    rising = (t / g.rise_s) ** 2 if g.rise_s > 0.0 else np.ones_like(t)
    return np.where(
        t < g.rise_s,
        rising,
        np.where(t <= g.strong_until_s, 1.0, np.exp(-g.decay_per_s * (t - g.strong_until_s))),
    )


def ground_acceleration_m_s2(g: GroundMotion, duration_s: float, period_s: float) -> np.ndarray:
    """a_g at t_k = k * period_s, k = 0..K (K = duration / period), max |a_g| = pga."""
    steps = max(1, round(duration_s / period_s))
    w = 2.0 * math.pi * g.ground_frequency_hz
    two_zw = 2.0 * g.ground_damping * w
    a = np.array([[0.0, 1.0], [-w * w, -two_zw]])
    ad, bd = zoh(a, np.array([[0.0], [-1.0]]), period_s)
    noise = np.random.default_rng(g.seed).standard_normal(steps + 1)
    # x_(k+1) = Ad x_k + bd n_k on floats: with a 2-vector in numpy a step cost 7 us, and a
    # building's run (built off the loop, in the control thread, holding the interpreter while
    # the loop answers frames) took 0.2-0.3 s for 20 s of record
    (a00, a01), (a10, a11) = ad.tolist()
    b0, b1 = bd[:, 0].tolist()
    wsq = w * w
    x0 = x1 = 0.0
    out = np.empty(steps + 1)
    for k, n_k in enumerate(noise.tolist()):
        out[k] = -(two_zw * x1 + wsq * x0)
        x0, x1 = a00 * x0 + a01 * x1 + b0 * n_k, a10 * x0 + a11 * x1 + b1 * n_k
    out *= envelope(np.arange(steps + 1) * period_s, g)
    return out * (g.pga_m_s2 / np.max(np.abs(out)))
