"""Error detectors while armed: tracking error, velocity and the damper's temperature.

Pure: told each armed frame's measured and desired force, the estimated velocity and the
damper's latest temperature, it answers which detector crossed its threshold for its hold
time, once per episode (an episode ends when the value is back under the threshold). What
is done about it (`action`) is the daemon's: `warn` an event, `disarm` a fault (SAFE 0 A),
`stop` a fault and the actuator stopped. Limits as a rig controller's error detectors: a
threshold, a time it must be held, an action each.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

Action = Literal["warn", "disarm", "stop"]

# the bounds a config's thresholds are checked against at load
MAX_TRACKING_ERROR_N = 80000.0  # the config's force range limit
MAX_VELOCITY_M_S = 10.0  # twice the actuator's reach: 40 mm at 20 Hz is 5 m/s
MAX_TEMPERATURE_DEGC = 200.0
MAX_HOLD_S = 10.0


@dataclass(frozen=True)
class Detector:
    """One detector: `action` once its value has been above `threshold` for `hold_s`."""

    threshold: float
    action: Action = "warn"
    hold_s: float = 0.0

    def check(self) -> None:
        if not 0.0 <= self.hold_s <= MAX_HOLD_S:
            raise ValueError(f"hold_s: must be in [0, {MAX_HOLD_S:g}] s")


@dataclass(frozen=True)
class DetectorSettings:
    """`[detectors]`: the defaults let the simulator's runs through (a heating run warms the
    damper from 25 to about 70 degC; the characterization matrix moves at most 0.75 m/s) and
    stop what no run of this rig does."""

    # |f_meas - f_des|, N: a model that no longer fits, a damper that leaks; a warning only,
    # as a step of the reference is a large error for a few periods
    tracking_error: Detector = field(default_factory=lambda: Detector(1000.0, "warn", 0.5))
    # |xd| of the estimate, m/s: more than the matrix's motion; held 10 ms (5 frames) so
    # that a single noisy sample does not trip it
    velocity: Detector = field(default_factory=lambda: Detector(2.0, "disarm", 0.01))
    # DamperTemperature of RigStatus, degC: the MR fluid's upper working range
    temperature: Detector = field(default_factory=lambda: Detector(100.0, "disarm", 0.0))

    def check(self) -> None:
        bounds = (
            ("tracking_error", MAX_TRACKING_ERROR_N, "N"),
            ("velocity", MAX_VELOCITY_M_S, "m/s"),
            ("temperature", MAX_TEMPERATURE_DEGC, "degC"),
        )
        for name, top, unit in bounds:
            if not 0.0 < getattr(self, name).threshold <= top:
                raise ValueError(f"{name}.threshold: must be in (0, {top:g}] {unit}")


@dataclass(frozen=True)
class Detection:
    """A detector that crossed its threshold for its hold time: `text` names it and the value."""

    name: str
    action: Action
    value: float
    text: str


_WHAT = {
    "tracking_error": ("tracking error |f_meas - f_des|", "N", "{:.1f}"),
    "velocity": ("velocity |xd|", "m/s", "{:.3f}"),
    "temperature": ("damper temperature", "degC", "{:.1f}"),
}


class Detectors:
    """The detectors' episodes: since when each is above its threshold, and whether it was
    reported. `reset()` at arming: an episode does not outlive the run it was in."""

    def __init__(self, settings: DetectorSettings) -> None:
        self.settings = settings
        self._since: dict[str, float] = {}
        self._reported: set[str] = set()

    def reset(self) -> None:
        self._since.clear()
        self._reported.clear()

    def check(
        self, t_s: float, f_meas_n: float, f_des_n: float, xd_m_s: float, temp_degc: float
    ) -> list[Detection]:
        """An armed frame's values (a NaN temperature: none received yet, not above)."""
        values = {
            "tracking_error": abs(f_meas_n - f_des_n),
            "velocity": abs(xd_m_s),
            "temperature": temp_degc,
        }
        out = []
        for name, value in values.items():
            d: Detector = getattr(self.settings, name)
            if not (math.isfinite(value) and value > d.threshold):
                self._since.pop(name, None)
                self._reported.discard(name)
                continue
            since = self._since.setdefault(name, t_s)
            if name in self._reported or t_s - since < d.hold_s:
                continue
            self._reported.add(name)
            what, unit, fmt = _WHAT[name]
            held = f" for {(t_s - since) * 1e3:.0f} ms" if d.hold_s else ""
            text = (
                f"detector {name}: {what} {fmt.format(value)} {unit} above "
                f"{d.threshold:g} {unit}{held} (action {d.action})"
            )
            out.append(Detection(name, d.action, value, text))
        return out
