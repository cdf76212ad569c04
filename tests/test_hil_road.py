"""ISO 8608 road profiles (spec/hil.md, substructure 1): the generated profile's displacement PSD
against Gd(n), the bump event, and the road under the wheel at a speed."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import welch

from mrrig.hil.road import (
    N_MAX_CYCLE_PER_M,
    N_MIN_CYCLE_PER_M,
    Bump,
    gd_m3,
    gd_n0_m3,
    road_input_m,
    spatial_profile_m,
)

# The stated tolerance: Welch's PSD (segments of 2^16 samples, Hann), averaged over each
# third-octave band of 0.011-2.83 cycle/m, within 20 % (0.8 dB) of Gd(n) averaged over it.
BAND_TOLERANCE = 0.20


def _third_octave_ratios(n: np.ndarray, psd: np.ndarray, gd: np.ndarray) -> np.ndarray:
    edges = N_MIN_CYCLE_PER_M * 2.0 ** (np.arange(0, 30) / 3.0)
    edges = edges[edges <= N_MAX_CYCLE_PER_M]
    ratios = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        inside = (n >= lo) & (n < hi)
        ratios.append(psd[inside].mean() / gd[inside].mean())
    return np.array(ratios)


@pytest.mark.parametrize("iso_class", "ABCD")
def test_the_profile_psd_is_gd_of_its_class_within_the_stated_tolerance(iso_class: str) -> None:
    dx_m = 0.05
    _, z = spatial_profile_m(iso_class, 20_000.0, dx_m, seed=7)
    n, psd = welch(z, fs=1.0 / dx_m, nperseg=2**16)
    ratios = _third_octave_ratios(n, psd, gd_m3(np.maximum(n, 1e-9), iso_class))
    assert ratios.size == 24
    assert np.all(np.abs(ratios - 1.0) < BAND_TOLERANCE), ratios


def test_the_class_geometric_means_are_the_spec_s() -> None:
    assert [gd_n0_m3(c) * 1e6 for c in "ABCD"] == [16.0, 64.0, 256.0, 1024.0]
    assert gd_n0_m3("H") == pytest.approx(16e-6 * 4**7)
    with pytest.raises(ValueError, match="unknown ISO 8608 class 'Z'"):
        gd_n0_m3("Z")


def test_the_road_under_the_wheel_has_the_temporal_psd_at_its_speed() -> None:
    """At speed V, n = f / V and G(f) = Gd(f / V) / V."""
    speed, period = 20.0, 0.002
    z = road_input_m("C", speed, 600.0, period, seed=3)
    assert z.size == 300_001
    f, psd = welch(z, fs=1.0 / period, nperseg=2**15)
    n = f / speed
    ratios = _third_octave_ratios(n, psd * speed, gd_m3(np.maximum(n, 1e-9), "C"))
    assert np.all(np.abs(ratios - 1.0) < BAND_TOLERANCE), ratios


def test_a_seed_gives_one_road_and_another_seed_another() -> None:
    a = road_input_m("B", 10.0, 20.0, 0.002, seed=1)
    assert np.array_equal(a, road_input_m("B", 10.0, 20.0, 0.002, seed=1))
    assert not np.allclose(a, road_input_m("B", 10.0, 20.0, 0.002, seed=2))


def test_a_bump_is_a_half_sine_of_its_height_and_length_where_it_is() -> None:
    bump = Bump(height_m=0.05, length_m=2.0, at_m=100.0)
    x = np.array([99.9, 100.0, 100.5, 101.0, 102.0, 102.1])
    assert bump.profile_m(x) == pytest.approx([0.0, 0.0, 0.05 * np.sqrt(0.5), 0.05, 0.0, 0.0])
    pothole = Bump(height_m=-0.03, length_m=1.0, at_m=10.0)
    flat = road_input_m("A", 10.0, 2.0, 0.002, seed=1)
    holed = road_input_m("A", 10.0, 2.0, 0.002, seed=1, bumps=(pothole,))
    # the wheel is at 10.5 m at t = 1.05 s: the pothole's bottom
    assert holed[525] - flat[525] == pytest.approx(-0.03)
    assert np.array_equal(holed[:500], flat[:500])
