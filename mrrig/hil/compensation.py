"""Actuator delay compensation (spec/hil.md, Actuator delay and its compensation).

Timing, per frame k: the model gives `target_m`, the stroke it wants measured at frame k + 1;
the frame's measured stroke `measured_m` is the answer to what was sent before. A perfect
actuator would show the setpoint sent at frame k at frame k + 1: one frame of lag is the
loop's own, and the compensators lead the target by the delay beyond it.

- `PolynomialCompensator` (Horiuchi et al. 1996): the last `order + 1` targets are extrapolated
  by a Lagrange polynomial over the lead, the delay estimated on line by `DelayEstimator`
  (weighted least squares of the measured stroke's increments on the sent setpoint's, delayed
  by a whole and a fractional number of frames).
- `AdaptiveCompensator` (in the spirit of Chen & Ricles' adaptive inverse compensation, 2010):
  the same extrapolation, its lead adapted by a normalised gradient law on the measured
  tracking error e = x_c - x_m ~ tau_r x_c' (tau_r the delay left): the lead grows while the
  measured stroke lags and shrinks while it leads, whatever the actuator.

- `ModelCompensator` (model-based, after Carrion & Spencer 2007's use of the known
  substructure): the numerical model's own prediction of its stroke over the estimated delay,
  the measured force held and the excitation ahead known. It leads without a polynomial's
  gain at high frequency: behind a 50 Hz servo, the extrapolation's gain near the servo's
  band closes a loop through the damper's stiffness and the wheel's mass (the body
  acceleration's error against the reference lies at 40-100 Hz), the model does not.

All give the setpoint's velocity as the feedforward.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

# The least setpoint excitation the delay estimate is updated on: the weighted sum of squared
# second differences of the sent setpoint, per frame of the window, (0.1 um)^2. A setpoint at
# rest (or one that moves by rounding) says nothing of the delay; noise would move it.
_MIN_EXCITATION_M2 = 1e-14
# the adaptive lead: the least power of the target's per-frame step it normalises by, (1 um)^2
# (0.5 mm/s at 500 Hz), and the most it moves in a frame (a 100th of a frame)
_MIN_STEP_POWER_M2 = 1e-12
_MAX_LEAD_CHANGE = 0.01


def extrapolation_weights(order: int, lead_frames: float) -> tuple[np.ndarray, np.ndarray]:
    """Lagrange weights on x_k, x_(k-1), ..., x_(k-order) (nodes t_j = -j frames) for the value
    and the derivative (per frame) at t = lead_frames:
        L_j(a) = prod_(m != j) (a + m) / (m - j)              (Horiuchi et al. 1996, eq. 3's
        L_j'(a) = sum_(i != j) 1/(i - j) prod_(m != j, i) (a + m) / (m - j)   general form)"""
    nodes = range(order + 1)
    value = np.ones(order + 1)
    slope = np.zeros(order + 1)
    for j in nodes:
        for m in nodes:
            if m != j:
                value[j] *= (lead_frames + m) / (m - j)
        for i in nodes:
            if i == j:
                continue
            term = 1.0 / (i - j)
            for m in nodes:
                if m not in (i, j):
                    term *= (lead_frames + m) / (m - j)
            slope[j] += term
    return value, slope


class DelayEstimator:
    """The delay d (frames) of the measured stroke behind the sent setpoint, by exponentially
    weighted least squares on increments (offsets drop out): for each whole lag L, the
    increment measured now dm_k is fitted by the sent increment du_(k-L) interpolated towards
    du_(k-L-1) by a fraction f in [0, 1]:
        r_L(f) = dm_k - du_(k-L) + f (du_(k-L) - du_(k-L-1))
    f = -S(a D) / S(D D) minimises the weighted sum of r^2 (a = dm - du_(k-L), D the
    difference), and d = L + f for the L of the least residual. Unlike the peak of a
    cross-correlation (flat for a narrow-band stroke, its top moved by the window's ripple),
    the residual's minimum is sharp. The estimate stays `initial_frames` for the first
    quarter of the window: from a few frames of a starting stroke, the sensor's noise chose a
    lag of 13-20 frames where the rig's was 3, and the compensator leading by that much made
    the hybrid loop unstable within 30 frames (test_hil_sim on the simulator)."""

    def __init__(self, max_lag: int, window_frames: float, initial_frames: float) -> None:
        self.max_lag = max_lag
        self._forget = 1.0 - 1.0 / window_frames
        self._min_s_dd = _MIN_EXCITATION_M2 * window_frames
        self._warmup = int(window_frames / 4)  # updates before the first estimate
        # _sent[j]: the setpoint sent j + 1 frames before the frame being measured
        self._sent = deque([0.0] * (max_lag + 2), maxlen=max_lag + 2)
        self._s_aa = np.zeros(max_lag)
        self._s_ad = np.zeros(max_lag)
        self._s_dd = np.zeros(max_lag)
        self._last_measured: float | None = None
        self.delay_frames = initial_frames

    def update(self, sent_m: float, measured_m: float) -> float:
        """One frame: the setpoint sent at the frame before and the stroke measured now."""
        self._sent.appendleft(sent_m)
        if self._last_measured is not None:
            sent = np.asarray(self._sent)
            du = sent[:-1] - sent[1:]  # du[l - 1]: the increment sent l frames ago
            dm = measured_m - self._last_measured
            a = dm - du[:-1]  # lags L = 1..max_lag
            d = du[:-1] - du[1:]
            lam = self._forget
            self._s_aa = lam * self._s_aa + a * a
            self._s_ad = lam * self._s_ad + a * d
            self._s_dd = lam * self._s_dd + d * d
            self._warmup -= 1
            if self._warmup <= 0:
                self._refine()
        self._last_measured = measured_m
        return self.delay_frames

    def _refine(self) -> None:
        s_dd = np.maximum(self._s_dd, 1e-30)
        f = np.clip(-self._s_ad / s_dd, 0.0, 1.0)
        residual = self._s_aa + 2.0 * f * self._s_ad + f * f * self._s_dd
        best = int(np.argmin(residual))
        if self._s_dd[best] > self._min_s_dd:
            self.delay_frames = best + 1 + float(f[best])


class NoCompensation:
    """The model's stroke as it is; its velocity by the backward difference."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.reset()

    def reset(self) -> None:
        self._last: float | None = None

    @property
    def delay_s(self) -> float:
        return 0.0

    def update(self, target_m: float, measured_m: float) -> tuple[float, float]:
        velocity = 0.0 if self._last is None else (target_m - self._last) / self.period_s
        self._last = target_m
        return target_m, velocity


class _Extrapolating:
    """The last `order + 1` targets and their extrapolation over a lead."""

    def __init__(self, order: int, period_s: float, max_delay_s: float) -> None:
        self.order, self.period_s = order, period_s
        self.max_lead_frames = max_delay_s / period_s
        self._targets: deque[float] = deque(maxlen=order + 1)
        self._lead = -1.0
        self._w = self._dw = np.zeros(0)

    def _extrapolate(self, target_m: float, lead_frames: float) -> tuple[float, float]:
        if not self._targets:
            self._targets.extend([target_m] * (self.order + 1))
        self._targets.appendleft(target_m)
        lead = min(max(lead_frames, 0.0), self.max_lead_frames)
        if abs(lead - self._lead) > 1e-3:  # weights recomputed only when the lead moves
            self._w, self._dw = extrapolation_weights(self.order, lead)
            self._lead = lead
        x = np.fromiter(self._targets, float, self.order + 1)
        return float(self._w @ x), float(self._dw @ x) / self.period_s


class _EstimatedDelay:
    """The delay a compensator leads by, estimated on line from what it sent and what was
    measured (`DelayEstimator`, a 2 s window), for the polynomial and the model compensators."""

    def __init__(self, period_s: float, initial_delay_s: float, max_lead_frames: float) -> None:
        self.period_s = period_s
        self._max_lag = math.ceil(max_lead_frames) + 1
        self._initial_frames = 1.0 + initial_delay_s / period_s
        self.reset()

    def reset(self) -> None:
        self.estimator = DelayEstimator(
            max_lag=self._max_lag,
            window_frames=2.0 / self.period_s,
            initial_frames=self._initial_frames,
        )
        self._sent: float | None = None

    @property
    def lead_frames(self) -> float:
        """The estimated delay beyond the loop's own frame, in frames (>= 0)."""
        return max(self.estimator.delay_frames - 1.0, 0.0)

    def measured(self, measured_m: float) -> None:
        """The measured stroke, against the last setpoint sent (before choosing the next)."""
        if self._sent is not None:
            self.estimator.update(self._sent, measured_m)

    def remember(self, setpoint_m: float) -> None:
        """The setpoint sent this frame."""
        self._sent = setpoint_m


class PolynomialCompensator(_Extrapolating):
    """Extrapolation over the delay estimated on line (Horiuchi et al. 1996)."""

    def __init__(
        self, order: int, period_s: float, initial_delay_s: float, max_delay_s: float
    ) -> None:
        super().__init__(order, period_s, max_delay_s)
        self.delay = _EstimatedDelay(period_s, initial_delay_s, self.max_lead_frames)

    def reset(self) -> None:
        self._targets.clear()
        self.delay.reset()

    @property
    def delay_s(self) -> float:
        """The estimated delay beyond the loop's own frame (what the setpoint is led by)."""
        return self.delay.lead_frames * self.period_s

    def update(self, target_m: float, measured_m: float) -> tuple[float, float]:
        self.delay.measured(measured_m)
        setpoint, velocity = self._extrapolate(target_m, self.delay.lead_frames)
        self.delay.remember(setpoint)
        return setpoint, velocity


class AdaptiveCompensator(_Extrapolating):
    """Extrapolation whose lead adapts to the measured tracking error (normalised gradient):
        e_k = x_c(k) - x_m(k),   lead += gain * e_k x_c'(k) dt / (P_v dt^2 + eps)
    with P_v the exponentially weighted mean of x_c'^2; at rest (P_v ~ 0) the lead holds."""

    def __init__(
        self,
        order: int,
        period_s: float,
        initial_delay_s: float,
        max_delay_s: float,
        gain: float = 0.01,
    ) -> None:
        super().__init__(order, period_s, max_delay_s)
        self._initial_lead = initial_delay_s / period_s
        self.gain = gain
        self.reset()

    def reset(self) -> None:
        self._targets.clear()
        self.lead_frames = self._initial_lead
        self._previous_target: float | None = None
        self._power = 0.0

    @property
    def delay_s(self) -> float:
        return self.lead_frames * self.period_s

    def update(self, target_m: float, measured_m: float) -> tuple[float, float]:
        if self._previous_target is not None:
            # the last frame's target is what this frame should measure; x_c' dt by the
            # difference of the last two targets
            step = self._previous_target - self._targets[1]
            self._power += 0.001 * (step * step - self._power)
            error = self._previous_target - measured_m
            # a floor on the power: a stroke that barely moves (the run's start, a rest)
            # would make the least error a large correction
            change = self.gain * error * step / max(self._power, _MIN_STEP_POWER_M2)
            change = min(max(change, -_MAX_LEAD_CHANGE), _MAX_LEAD_CHANGE)
            self.lead_frames = min(max(self.lead_frames + change, 0.0), self.max_lead_frames)
        self._previous_target = target_m
        return self._extrapolate(target_m, self.lead_frames)


class ModelCompensator:
    """The model's prediction over the delay estimated on line (`DelayEstimator`)."""

    def __init__(self, substructure, period_s: float, initial_delay_s: float, max_delay_s: float):
        self.substructure = substructure
        self.period_s = period_s
        self.max_lead_frames = max_delay_s / period_s
        self.delay = _EstimatedDelay(period_s, initial_delay_s, self.max_lead_frames)

    def reset(self) -> None:
        self.delay.reset()

    @property
    def delay_s(self) -> float:
        return self.delay.lead_frames * self.period_s

    def update(self, target_m: float, measured_m: float) -> tuple[float, float]:
        """`target_m` is the model's stroke now (its state is what is predicted from)."""
        self.delay.measured(measured_m)
        lead = min(self.delay.lead_frames, self.max_lead_frames)
        setpoint, velocity = self.substructure.predicted_stroke(lead)
        self.delay.remember(setpoint)
        return setpoint, velocity


def make_compensator(
    method: str,
    order: int,
    period_s: float,
    initial_delay_s: float,
    max_delay_s: float,
    substructure=None,
) -> NoCompensation | PolynomialCompensator | AdaptiveCompensator | ModelCompensator:
    """The compensator a scenario's `[compensation]` names (`model` needs the substructure)."""
    if method == "model":
        if substructure is None:
            raise ValueError("compensation 'model' needs the numerical substructure")
        return ModelCompensator(substructure, period_s, initial_delay_s, max_delay_s)
    if method == "none":
        return NoCompensation(period_s)
    if method == "polynomial":
        return PolynomialCompensator(order, period_s, initial_delay_s, max_delay_s)
    if method == "adaptive":
        return AdaptiveCompensator(order, period_s, initial_delay_s, max_delay_s)
    raise ValueError(f"unknown compensation {method!r}; known: none, polynomial, adaptive, model")
