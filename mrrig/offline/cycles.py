"""Per-cycle results of a damper test, the numbers a damper test report gives: per stroke
cycle its amplitude, frequency, peak forces in extension and compression against the peak
velocities, and the energy it dissipated; and the cycles grouped by test condition.

Pure numerics on SAMPLE_DTYPE arrays (`mrrig.loop.samples`): the signs are the CAN contract's
(displacement positive = extension, force positive = tension), so a dissipating damper pulls
while it extends and the energy of a cycle, the loop integral of force over displacement, is
positive (work done on the damper by the actuator).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mrrig.loop.samples import RigState

MIN_CYCLE_FRAMES = 8  # a "cycle" shorter than this is noise around a crossing
MIN_AMPLITUDE_M = 1e-4  # below it the stroke is the sensor's noise, not a cycle


@dataclass(frozen=True)
class Cycle:
    t_start_s: float
    t_end_s: float
    amplitude_m: float  # half the peak-to-peak displacement
    frequency_hz: float  # 1 / the cycle's duration
    v_max_m_s: float  # peak velocity in extension (> 0)
    v_min_m_s: float  # peak velocity in compression (< 0)
    f_max_n: float  # peak force in tension (extension)
    f_min_n: float  # peak force in compression
    energy_j: float  # loop integral of f_meas dx over the cycle, J
    current_a: float  # mean measured coil current
    armed: bool  # every frame of it armed

    def condition(self) -> tuple[float, float, float]:
        """The test condition the cycle belongs to: amplitude (0.5 mm), frequency (0.1 Hz),
        current (0.05 A), rounded so that a matrix's runs fall into their rows."""
        return (
            round(self.amplitude_m * 2e3) / 2e3,
            round(self.frequency_hz * 10) / 10,
            round(self.current_a * 20) / 20,
        )


def cycles(s: np.ndarray) -> list[Cycle]:
    """The complete stroke cycles of the run: from one upward crossing of the displacement's
    mid-stroke to the next (mid-stroke taken over the whole run, a hysteresis of a tenth of
    the stroke against sensor noise). Frames with a non-finite x or force end a cycle."""
    if s.size < 2 * MIN_CYCLE_FRAMES:
        return []
    x = s["x"]
    finite = np.isfinite(x) & np.isfinite(s["f_meas"])
    if not finite.any():
        return []
    lo, hi = np.percentile(x[finite], [1, 99])
    if hi - lo < 2 * MIN_AMPLITUDE_M:
        return []
    mid, band = 0.5 * (lo + hi), 0.05 * (hi - lo)
    starts = _upward_crossings(x, mid, band)
    out = []
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        if b - a < MIN_CYCLE_FRAMES or not finite[a : b + 1].all():
            continue
        out.append(_cycle(s[a : b + 1]))
    return [c for c in out if c.amplitude_m >= MIN_AMPLITUDE_M]


def _upward_crossings(x: np.ndarray, mid: float, band: float) -> np.ndarray:
    """Indices where x rises through `mid`, counted once it has been below mid - band since
    the last one (a Schmitt trigger)."""
    out = []
    below = False
    for k in range(1, x.size):
        v = x[k]
        if v < mid - band:
            below = True
        elif below and x[k - 1] < mid <= v:
            out.append(k)
            below = False
    return np.asarray(out, dtype=np.int64)


def _cycle(c: np.ndarray) -> Cycle:
    t, x, f, xd = c["t"], c["x"], c["f_meas"], c["xd"]
    i = c["i_meas"] if np.isfinite(c["i_meas"]).all() else c["i_cmd"]
    duration = float(t[-1] - t[0])
    return Cycle(
        t_start_s=float(t[0]),
        t_end_s=float(t[-1]),
        amplitude_m=float(0.5 * (x.max() - x.min())),
        frequency_hz=1.0 / duration if duration > 0 else float("nan"),
        v_max_m_s=float(np.nanmax(xd)),
        v_min_m_s=float(np.nanmin(xd)),
        f_max_n=float(f.max()),
        f_min_n=float(f.min()),
        energy_j=float(np.trapezoid(f, x)),
        current_a=float(np.nanmean(i)),
        armed=bool((c["state"] == RigState.ARMED).all()),
    )


@dataclass(frozen=True)
class ConditionRow:
    """The cycles of one test condition: their count and medians."""

    amplitude_m: float
    frequency_hz: float
    current_a: float
    cycles: int
    v_max_m_s: float
    v_min_m_s: float
    f_max_n: float
    f_min_n: float
    energy_j: float


def by_condition(cs: list[Cycle]) -> list[ConditionRow]:
    """The cycles grouped by `Cycle.condition`, in the order the conditions were first run;
    per group the medians (a cycle cut by a fault or a step change does not move them)."""
    groups: dict[tuple[float, float, float], list[Cycle]] = {}
    for c in cs:
        groups.setdefault(c.condition(), []).append(c)
    rows = []
    for (amp, freq, cur), g in groups.items():

        def med(name: str, g: list[Cycle] = g) -> float:
            return float(np.median([getattr(c, name) for c in g]))

        rows.append(
            ConditionRow(
                amp,
                freq,
                cur,
                len(g),
                med("v_max_m_s"),
                med("v_min_m_s"),
                med("f_max_n"),
                med("f_min_n"),
                med("energy_j"),
            )
        )
    return rows
