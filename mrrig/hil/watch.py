"""The hybrid loop's safety checks (spec/hil.md, Safety), frame by frame, pure numerics.

A hybrid loop can go unstable: the actuator's delay acts as negative damping, and an
extrapolating compensator's gain can close a loop through the damper's stiffness (the stiff
building with `polynomial` compensation diverges within 0.1 s). `HilWatch.check` is called
once per frame with what the loop computed and measured, before the setpoint is sent; it
returns the reason for a fault, or None. The checks, first that fires wins:
- a state, target or setpoint that is not finite;
- a setpoint or target beyond the STREAM envelope;
- a setpoint moving faster than `max_setpoint_velocity_m_s` (a diverging loop's setpoints
  jump by many times what any road asks: the first sign of the building's divergence);
- |x_m - x_c| beyond `tracking_limit_m`;
- energy injected: the damper delivered more than `energy_limit_j` to the model over the
  last `energy_window_s` (the power it delivers is -F s'; a passive device cannot deliver
  energy over a window, so a loop that does is fed by the actuator's lag).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class WatchLimits:
    envelope_m: float
    tracking_limit_m: float = 0.02
    max_setpoint_velocity_m_s: float = 3.0
    energy_limit_j: float = 0.1
    energy_window_s: float = 0.25


class HilWatch:
    """The checks of one run; `reset` when a run starts."""

    def __init__(self, limits: WatchLimits, period_s: float) -> None:
        self.limits = limits
        self.period_s = period_s
        self._window = np.zeros(max(1, round(limits.energy_window_s / period_s)))
        self.reset()

    def reset(self) -> None:
        self._window[:] = 0.0
        self._k = 0
        self._injected_j = 0.0
        self._last_setpoint_m: float | None = None

    def check(
        self,
        commanded_m: float,
        measured_m: float,
        force_n: float,
        stroke_velocity_m_s: float,
        target_m: float,
        setpoint_m: float,
        setpoint_velocity_m_s: float,
        state: np.ndarray,
    ) -> str | None:
        """One frame: x_c (`commanded_m`, what the model asked for this frame's time), x_m,
        the measured force and the model's stroke velocity it acted on, then the model's next
        target and the setpoint about to be sent; `state` the model's state vector."""
        lim = self.limits
        numbers = (target_m, setpoint_m, setpoint_velocity_m_s, stroke_velocity_m_s)
        if not (all(math.isfinite(v) for v in numbers) and np.all(np.isfinite(state))):
            return "the numerical model's state or setpoint is not finite"
        for name, value in (("setpoint", setpoint_m), ("model's stroke", target_m)):
            if abs(value) > lim.envelope_m:
                return (
                    f"{name} {value * 1e3:.2f} mm beyond the STREAM envelope "
                    f"+-{lim.envelope_m * 1e3:g} mm"
                )
        last, self._last_setpoint_m = self._last_setpoint_m, setpoint_m
        if last is not None:
            rate = abs(setpoint_m - last) / self.period_s
            if rate > lim.max_setpoint_velocity_m_s:
                return (
                    f"setpoint moved {abs(setpoint_m - last) * 1e3:.2f} mm in one frame "
                    f"({rate:.2f} m/s, limit {lim.max_setpoint_velocity_m_s:g} m/s): "
                    "the hybrid loop is unstable"
                )
        error = measured_m - commanded_m
        if abs(error) > lim.tracking_limit_m:
            return (
                f"tracking error x_m - x_c {error * 1e3:.2f} mm beyond "
                f"+-{lim.tracking_limit_m * 1e3:g} mm"
            )
        # the damper's delivered energy over the window (-F s' dt), a running sum
        delivered = -force_n * stroke_velocity_m_s * self.period_s
        i = self._k % self._window.size
        self._injected_j += delivered - self._window[i]
        self._window[i] = delivered
        self._k += 1
        if self._injected_j > lim.energy_limit_j:
            return (
                f"the damper delivered {self._injected_j:.3f} J to the model in "
                f"{lim.energy_window_s:g} s (limit {lim.energy_limit_j:g} J): energy injected, "
                "the hybrid loop is unstable"
            )
        return None
