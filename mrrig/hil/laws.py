"""Semi-active control laws (spec/hil.md, Semi-active laws): each gives a desired damper force for
the inverse model, or a fixed current (the passive laws, clipped-optimal's on-off form).

A passive damper cannot push: it can only give a force F with F s' > 0 (tension positive, s'
the stroke velocity: the force resists the motion). A law's force of the other sign becomes 0
(the least the damper gives: 0 A); its size is clipped by the inverse model's current range.
A law sees only what a real controller would: the numerical model's states and the measured
damper force.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.linalg import solve_continuous_are

LawName = Literal[
    "skyhook", "groundhook", "hybrid", "clipped-optimal", "passive-soft", "passive-hard"
]
LAWS: tuple[str, ...] = (
    "skyhook",
    "groundhook",
    "hybrid",
    "clipped-optimal",
    "passive-soft",
    "passive-hard",
)
# the laws that need the quarter car's body and wheel
VEHICLE_LAWS = ("skyhook", "groundhook", "hybrid")


@dataclass(frozen=True)
class Demand:
    """What a law asks for one frame: a desired force (N, tension positive) for the inverse
    model, or a current (A) to send as it is."""

    force_n: float | None = None
    current_a: float | None = None

    def current(self, controller_a: float, range_a: float | None, i_max_a: float) -> float:
        """The frame's current: the law's own where it asks one (passive-soft/hard), else the
        controller's `controller_a` (its inverse of `force_n`); within the scenario's damper
        range 0-`range_a` while a run streams (None: no run), and always within [0, `i_max_a`]
        (the loop's). The daemon's frame (`HilLoop.command`) and the reference both call it."""
        i_a = controller_a if self.current_a is None else self.current_a
        if range_a is not None:
            i_a = min(i_a, range_a)
        return min(max(i_a, 0.0), i_max_a)


@dataclass(frozen=True)
class LawParams:
    """The laws' gains; the LQR weights are on the substructure's performance outputs
    (quarter car: body acceleration, suspension travel, tyre deflection; building: storey
    drifts, relative floor accelerations) and on the damper force."""

    skyhook_c_n_s_per_m: float = 2500.0
    groundhook_c_n_s_per_m: float = 2500.0
    hybrid_alpha: float = 0.5  # 1 = skyhook alone, 0 = groundhook alone
    # empty: the substructure's own (`default_lqr_weights`)
    lqr_output_weights: tuple[float, ...] = ()
    lqr_force_weight: float = 1.0e-7
    clipped_on_off: bool = False  # Dyke (1996): i_max when (f_c - F) F > 0, else 0 A

    def check(self) -> None:
        for name in ("skyhook_c_n_s_per_m", "groundhook_c_n_s_per_m", "lqr_force_weight"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name}: must be positive, got {getattr(self, name)}")
        if not 0.0 <= self.hybrid_alpha <= 1.0:
            raise ValueError(f"hybrid_alpha: must be in [0, 1], got {self.hybrid_alpha}")
        if self.lqr_output_weights and min(self.lqr_output_weights) < 0.0:
            raise ValueError("lqr_output_weights: non-negative weights, one per output")


def dissipative(force_n: float, stroke_velocity_m_s: float) -> float:
    """The force a passive damper can give of the one asked: itself if F s' > 0, else 0."""
    return force_n if force_n * stroke_velocity_m_s > 0.0 else 0.0


def lqr_gain(
    a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray, w: np.ndarray, r: float
) -> np.ndarray:
    """K of u = -K x minimising the integral of y' W y + r u^2, y = C x + D u:
    Q = C' W C, N = C' W D, R = D' W D + r; A' P + P A - (P B + N) R^-1 (B' P + N') + Q = 0."""
    wm = np.diag(w)
    q, n, rr = c.T @ wm @ c, c.T @ wm @ d, d.T @ wm @ d + r
    p = solve_continuous_are(a, b, q, rr, s=n)
    return np.linalg.solve(rr, b.T @ p + n.T)


class Law:
    """One law, chosen by name, for one substructure (`QuarterCar` or `ShearBuilding`)."""

    def __init__(self, name: str, params: LawParams, substructure, i_max_a: float) -> None:
        if name not in LAWS:
            raise ValueError(f"unknown law {name!r}; known: {', '.join(LAWS)}")
        if name in VEHICLE_LAWS and not hasattr(substructure, "body_velocity_m_s"):
            raise ValueError(f"law {name!r} needs a quarter car (a body and a wheel)")
        self.name, self.params, self.i_max_a = name, params, i_max_a
        self._sub = substructure
        self._gain = None
        if name == "clipped-optimal":
            a, b, c, d = substructure.control_model()
            w = np.asarray(
                params.lqr_output_weights or substructure.default_lqr_weights(), dtype=float
            )
            if w.size != c.shape[0]:
                raise ValueError(
                    f"lqr_output_weights: {c.shape[0]} weights for this substructure, got {w.size}"
                )
            self._gain = lqr_gain(a, b, c, d, w, params.lqr_force_weight)

    def optimal_force_n(self) -> float:
        """The LQR's force f_c = -K x on the model's state (clipped-optimal's ideal force)."""
        return float(-(self._gain @ self._sub.control_state())[0])

    def demand(self, measured_force_n: float) -> Demand:
        p, sub, name = self.params, self._sub, self.name
        if name == "passive-soft":
            return Demand(current_a=0.0)
        if name == "passive-hard":
            return Demand(current_a=self.i_max_a)
        sv = sub.stroke_velocity_m_s
        if name == "clipped-optimal":
            f_c = self.optimal_force_n()
            if p.clipped_on_off:
                # Dyke et al. (1996), the clipped-optimal command: v = V_max H{(f_c - f) f}
                on = (f_c - measured_force_n) * measured_force_n > 0.0
                return Demand(current_a=self.i_max_a if on else 0.0)
            return Demand(force_n=dissipative(f_c, sv))
        # the force on the body is -F, on the wheel +F (spec/hil.md, Conventions)
        sky = dissipative(p.skyhook_c_n_s_per_m * sub.body_velocity_m_s, sv)  # Karnopp (1974)
        ground = dissipative(-p.groundhook_c_n_s_per_m * sub.wheel_velocity_m_s, sv)
        if name == "skyhook":
            return Demand(force_n=sky)
        if name == "groundhook":
            return Demand(force_n=ground)
        return Demand(force_n=p.hybrid_alpha * sky + (1.0 - p.hybrid_alpha) * ground)
