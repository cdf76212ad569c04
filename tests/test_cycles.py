"""Per-cycle results (mrrig/offline/cycles.py) against a damper whose numbers are known: a
viscous plus Coulomb damper on sine strokes, E = pi c w A^2 + 4 F0 A per cycle."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.offline.cycles import by_condition, cycles

DT = 0.002
C, F0 = 2000.0, 150.0  # N s/m, N


def _stroke(amp_m: float, freq_hz: float, current_a: float, seconds: float, t0: float = 0.0):
    n = int(seconds / DT)
    s = np.zeros(n, dtype=SAMPLE_DTYPE)
    s["t"] = t0 + np.arange(n) * DT
    w = 2 * math.pi * freq_hz
    s["x"] = amp_m * np.sin(w * s["t"])
    s["xd"] = amp_m * w * np.cos(w * s["t"])
    s["f_meas"] = C * s["xd"] + F0 * np.tanh(s["xd"] / 1e-3)
    s["i_meas"] = current_a
    s["i_cmd"] = current_a
    s["state"] = RigState.ARMED
    return s


def test_cycles_give_the_energy_peaks_and_conditions_of_a_known_damper():
    a = _stroke(0.010, 2.0, 0.5, 3.0)
    b = _stroke(0.005, 1.0, 1.0, 4.0, t0=3.0)
    s = np.concatenate([a, b])
    cs = cycles(s)
    rows = by_condition(cs)
    assert [(r.amplitude_m, r.frequency_hz, r.current_a) for r in rows] == [
        (0.010, 2.0, 0.5),
        (0.005, 1.0, 1.0),
    ]
    assert rows[0].cycles >= 4 and rows[1].cycles >= 2
    for r, amp, f in ((rows[0], 0.010, 2.0), (rows[1], 0.005, 1.0)):
        w = 2 * math.pi * f
        energy = math.pi * C * w * amp**2 + 4 * F0 * amp
        assert r.energy_j == pytest.approx(energy, rel=0.01)
        assert r.v_max_m_s == pytest.approx(amp * w, rel=0.01)
        assert r.v_min_m_s == pytest.approx(-amp * w, rel=0.01)
        assert r.f_max_n == pytest.approx(C * amp * w + F0, rel=0.01)
        assert r.f_min_n == pytest.approx(-(C * amp * w + F0), rel=0.01)
    assert all(c.armed for c in cs)


def test_noise_a_hold_and_a_non_finite_stretch_give_no_cycle():
    s = _stroke(0.010, 2.0, 0.5, 2.0)
    still = s.copy()
    still["x"] = np.random.default_rng(0).normal(0, 2e-5, s.size)  # a hold: sensor noise
    assert cycles(still) == []
    s["f_meas"][200:260] = np.nan  # a fault's frames: the cycles across them are dropped
    cs = cycles(s)
    assert cs and all(not (c.t_start_s <= 0.45 <= c.t_end_s) for c in cs)
