"""On-line adaptation of the forward network's force to the damper on the rig.

A damper is not the damper its model was trained on for long: MR fluid heats as the damper
dissipates energy and its force at a given current falls. The model's force is corrected by a
gain and an offset, f = gain * f_net + offset, estimated from the load cell by recursive
least squares with exponential forgetting, one update per frame after the command has gone
out (off the latency path). Pure numerics, vectorised over lanes (the daemon has one lane,
`mrrig bench paper` seven).

Safeguards: each update moves the gain and the offset by at most `max_gain_step` and
`max_offset_step_n`, and keeps them inside `gain_range` and `offset_range_n`; an update whose
prediction error exceeds `residual_limit_n` (a load-cell spike, a sensor fault) is skipped and
counted. The caller freezes it (no update) while not armed and on any fault; `frozen` freezes
it on request. The model file is never touched: the adapted state lives here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FORCE_SCALE_N = 1000.0  # the offset is estimated in kN, so both parameters are of order 1


@dataclass(frozen=True)
class AdaptationSettings:
    memory_s: float = 2.0  # forgetting: data this old weighs 1/e (lambda = exp(-dt/memory))
    gain_range: tuple[float, float] = (0.5, 1.5)
    offset_range_n: tuple[float, float] = (-1000.0, 1000.0)
    max_gain_step: float = 0.002  # per update
    max_offset_step_n: float = 2.0  # per update
    residual_limit_n: float = 1000.0  # |load cell - adapted model| above this: not used
    initial_variance: float = 1e-2  # of the gain (and of the offset in kN) at a reset

    def check(self) -> None:
        lo, hi = self.gain_range
        if not 0 < lo <= 1.0 <= hi:
            raise ValueError("gain_range: must hold 1 and be positive (lo <= 1 <= hi)")
        lo, hi = self.offset_range_n
        if not lo <= 0.0 <= hi:
            raise ValueError("offset_range_n: must hold 0 (lo <= 0 <= hi)")
        for name in ("memory_s", "max_gain_step", "max_offset_step_n", "residual_limit_n"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: must be positive")
        if not self.initial_variance > 0:
            raise ValueError("initial_variance: must be positive")


class GainOffsetRLS:
    """RLS with forgetting on theta = (gain, offset / FORCE_SCALE_N) per lane, regressor
    (f_net, 1) * (1 / FORCE_SCALE_N), measurement f_meas / FORCE_SCALE_N."""

    def __init__(self, settings: AdaptationSettings, dt_s: float) -> None:
        settings.check()
        self.settings = settings
        self.lam = math.exp(-dt_s / settings.memory_s)
        self.frozen = False
        self.reset(1)

    def reset(self, batch: int = 1) -> None:
        """Back to the model as trained: gain 1, offset 0, the initial variance."""
        self.theta = np.zeros((batch, 2))
        self.theta[:, 0] = 1.0
        self.P = np.zeros((batch, 2, 2))
        self.P[:, 0, 0] = self.P[:, 1, 1] = self.settings.initial_variance
        self.updates = 0
        self.skipped = 0
        self._floats()

    def _floats(self) -> None:
        # lane 0's gain and offset as floats, for the daemon's float path before send()
        self.gain0 = float(self.theta[0, 0])
        self.offset0_n = float(self.theta[0, 1] * FORCE_SCALE_N)

    @property
    def gain(self) -> np.ndarray:
        return self.theta[:, 0]

    @property
    def offset_n(self) -> np.ndarray:
        return self.theta[:, 1] * FORCE_SCALE_N

    def force(self, f_net: np.ndarray | float) -> np.ndarray:
        """The adapted force for the network's force."""
        return self.theta[:, 0] * f_net + self.theta[:, 1] * FORCE_SCALE_N

    def update(self, f_net: np.ndarray, f_meas: np.ndarray) -> None:
        """One RLS step per lane from the network's force and the load cell at one instant.
        Lanes whose prediction error is implausible, or not finite, are left as they are."""
        if self.frozen:
            return
        s = self.settings
        phi = np.stack([np.asarray(f_net, float), np.ones(np.shape(f_net))], axis=-1)
        phi /= FORCE_SCALE_N
        y = np.asarray(f_meas, float) / FORCE_SCALE_N
        err = y - np.einsum("bi,bi->b", phi, self.theta)
        ok = np.isfinite(err) & (np.abs(err) * FORCE_SCALE_N <= s.residual_limit_n)
        self.skipped += int(np.sum(~ok))
        if not ok.any():
            return
        Pphi = np.einsum("bij,bj->bi", self.P, phi)
        k = Pphi / (self.lam + np.einsum("bi,bi->b", phi, Pphi))[:, None]
        step = k * np.where(ok, err, 0.0)[:, None]
        step[:, 0] = np.clip(step[:, 0], -s.max_gain_step, s.max_gain_step)
        max_off = s.max_offset_step_n / FORCE_SCALE_N
        step[:, 1] = np.clip(step[:, 1], -max_off, max_off)
        theta = self.theta + step
        theta[:, 0] = np.clip(theta[:, 0], *s.gain_range)
        theta[:, 1] = np.clip(theta[:, 1], *(b / FORCE_SCALE_N for b in s.offset_range_n))
        P = (self.P - np.einsum("bi,bj->bij", k, Pphi)) / self.lam
        # the covariance grows while the motion does not excite both parameters: capped at
        # its initial size so that the first informative frame cannot make a large step
        cap = s.initial_variance
        tr = np.trace(P, axis1=1, axis2=2)
        P *= np.minimum(1.0, 2.0 * cap / np.maximum(tr, 1e-300))[:, None, None]
        self.theta = np.where(ok[:, None], theta, self.theta)
        self.P = np.where(ok[:, None, None], P, self.P)
        self.updates += int(np.sum(ok))
        self._floats()

    def state(self) -> dict[str, float | int | bool]:
        """The adapted state of lane 0, for status, telemetry and the summary."""
        return {
            "gain": float(self.theta[0, 0]),
            "offset_n": float(self.theta[0, 1] * FORCE_SCALE_N),
            "updates": self.updates,
            "skipped": self.skipped,
            "frozen": self.frozen,
        }
