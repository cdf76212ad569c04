"""The servo-hydraulic actuator: the piston follows a position setpoint, not ideally.

Pure numerics, no CAN: `ServoActuator.step(setpoint_m, velocity_ff_m_s, dt_s)` takes the
setpoint of one period (the servo's setpoint at the period's end, joined to the previous one by
a straight line) and returns the piston's position and velocity at its end. The firmware feeds
it the motion generator's waveform (`[actuator.servo] waveforms`) or a STREAM's
ActuatorSetpoint frames; a caller that hands the piston over from the motion generator starts
it where that left it (`reset(x_m)`).

The model (`spec/hil.md`, "Actuator delay"; the RTHS benchmark of Silva, Dyke et al. 2020):
a servo-valve of first-order lag 1/b1 driving an actuator (an integrator) in a proportional
position loop, with a velocity feedforward into the valve, and a transport delay D:

    x'' + b1 x' + b2 x = g b2 r(t - D) + k_ff b1 w(t - D)

x the piston position, r the setpoint, w the velocity feedforward, g = a1 b0 / b2 the loop's
static gain, k_ff the fraction of the feedforward the servo controller applies (1: the valve
passes exactly the flow the feedforward asks). With w = r' its transfer function is

    X/R = (g b2 + k_ff b1 s) / (s^2 + b1 s + b2) e^(-s D)                  (`transfer`)

The benchmark's b1 ~ 425 1/s, b2 ~ 1.0e5 1/s^2 give a 50 Hz, 0.67-damped pair: about 4.3 ms of
phase delay at 2 Hz before the transport delay. Between the periods' samples the setpoint is
interpolated linearly (the servo controller runs faster than the CAN loop); each period is
integrated in sub-steps by the exact discretisation of the linear part for a linear input
(a first-order hold, from one matrix exponential), so the response is the transfer function's
up to the limits: the setpoint clamped to the stroke and rate-limited to the velocity limit
(each counted), the piston's velocity saturated at the valve's flow limit and its position
held at the stroke's ends.
"""

from __future__ import annotations

import bisect
import cmath
import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import expm

# Sub-steps of at most this long: the velocity limit acts between them.
MAX_SUBSTEP_S = 5e-4
_COEF_CACHE = 64  # discretisations kept (a steady period needs at most three)
_MIN_SUBSTEP_S = 1e-9  # a setpoint sample closer than this to a sub-step's end moves to it


@dataclass(frozen=True)
class ServoParams:
    """The servo loop's parameters (defaults: the RTHS benchmark's actuator, `spec/hil.md`)."""

    b1_per_s: float = 425.0  # valve pole: the valve's time constant is 1 / b1
    b2_per_s2: float = 1.0e5  # loop stiffness: natural frequency sqrt(b2) (50 Hz)
    static_gain: float = 1.0  # g = a1 b0 / b2: position per setpoint at rest
    velocity_ff_gain: float = 0.0  # k_ff: the benchmark's servo has no feedforward
    transport_delay_s: float = 0.002  # D: one 2 ms period from setpoint to valve
    velocity_limit_m_s: float = 1.0  # the valve's flow limit, as piston velocity

    def check(self) -> None:
        if not 0.0 < self.b1_per_s <= 1.0e4:
            raise ValueError("b1_per_s: must be in (0, 1e4]")
        if not 0.0 < self.b2_per_s2 <= 1.0e7:
            raise ValueError("b2_per_s2: must be in (0, 1e7]")
        if not 0.5 <= self.static_gain <= 1.5:
            raise ValueError("static_gain: must be in [0.5, 1.5]")
        if not 0.0 <= self.velocity_ff_gain <= 1.0:
            raise ValueError("velocity_ff_gain: must be in [0, 1]")
        if not 0.0 <= self.transport_delay_s <= 0.05:
            raise ValueError("transport_delay_s: must be in [0, 0.05]")
        if not 0.0 < self.velocity_limit_m_s <= 10.0:
            raise ValueError("velocity_limit_m_s: must be in (0, 10]")

    def transfer(self, frequency_hz: float) -> complex:
        """X/R at `frequency_hz` with the feedforward w = r' (the model's equation above)."""
        s = 2j * math.pi * frequency_hz
        b1, b2 = self.b1_per_s, self.b2_per_s2
        servo = (self.static_gain * b2 + self.velocity_ff_gain * b1 * s) / (s * s + b1 * s + b2)
        return servo * cmath.exp(-s * self.transport_delay_s)

    def with_spread(self, fraction: float, seed: int) -> ServoParams:
        """These parameters with b1, b2 and the transport delay each scaled by a factor drawn
        uniformly from [1 - fraction, 1 + fraction] (seeded): the rig's actuator as it is, not
        as its data sheet says."""
        if fraction == 0.0:
            return self
        f = 1.0 + fraction * np.random.default_rng(seed).uniform(-1.0, 1.0, 3)
        return replace(
            self,
            b1_per_s=self.b1_per_s * float(f[0]),
            b2_per_s2=self.b2_per_s2 * float(f[1]),
            transport_delay_s=self.transport_delay_s * float(f[2]),
        )


class ServoActuator:
    """The piston following setpoints through `ServoParams`' dynamics within the stroke."""

    def __init__(self, params: ServoParams, stroke_m: float, x0_m: float = 0.0) -> None:
        self.params = params
        self.stroke_m = stroke_m
        b1, b2 = params.b1_per_s, params.b2_per_s2
        self._a = np.array([[0.0, 1.0], [-b2, -b1]])
        self._b = np.array([[0.0, 0.0], [params.static_gain * b2, params.velocity_ff_gain * b1]])
        self._coef: dict[float, tuple[float, ...]] = {}
        self.clamped_setpoints = 0  # setpoints beyond the stroke, clamped to it
        self.rate_limited_setpoints = 0  # setpoint steps beyond the velocity limit
        self.reset(x0_m)

    def reset(self, x_m: float = 0.0) -> None:
        """At rest at x_m with the setpoint there (a clock restarting at 0)."""
        x_m = min(max(x_m, -self.stroke_m), self.stroke_m)
        self.x_m, self.xd_m_s = x_m, 0.0
        self.setpoint_m = x_m  # the latest setpoint applied (after the limits)
        self._t_s = 0.0
        # the setpoint's samples (time, position, feedforward): the delay line
        self._times = [0.0]
        self._inputs = [(x_m, 0.0)]

    def _coefficients(self, h_s: float) -> tuple[float, ...]:
        """The exact discretisation over h_s for an input linear in time: with
        M = [[A, B, 0], [0, 0, I], [0, 0, 0]], exp(M h) = [[Phi, G0, G1], ...] and
        x(h) = Phi x(0) + G0 u(0) + G1 (u(h) - u(0)) / h. Cached per sub-step length."""
        key = round(h_s, 12)
        coef = self._coef.get(key)
        if coef is None:
            if len(self._coef) >= _COEF_CACHE:  # periods of ever new lengths (stalls)
                self._coef.clear()
            m = np.zeros((6, 6))
            m[:2, :2] = self._a
            m[:2, 2:4] = self._b
            m[2:4, 4:6] = np.eye(2)
            coef = self._coef[key] = tuple(float(v) for v in expm(m * h_s)[:2, :].ravel())
        return coef

    def _input_at(self, t_s: float) -> tuple[float, float]:
        """The setpoint and feedforward the valve sees at t_s: the samples interpolated
        linearly, held before the first and after the last."""
        times, inputs = self._times, self._inputs
        i = bisect.bisect_right(times, t_s)
        if i == 0:
            return inputs[0]
        if i == len(times):
            return inputs[-1]
        t0, t1 = times[i - 1], times[i]
        (r0, w0), (r1, w1) = inputs[i - 1], inputs[i]
        a = (t_s - t0) / (t1 - t0)
        return r0 + a * (r1 - r0), w0 + a * (w1 - w0)

    def step(self, setpoint_m: float, velocity_ff_m_s: float, dt_s: float) -> tuple[float, float]:
        """The setpoint (and its velocity feedforward) at the end of a period of dt_s; returns
        the piston's (position m, velocity m/s) at the end of it."""
        if dt_s <= 0.0:
            return self.x_m, self.xd_m_s
        p = self.params
        v_max = p.velocity_limit_m_s
        r = min(max(setpoint_m, -self.stroke_m), self.stroke_m)
        if r != setpoint_m:
            self.clamped_setpoints += 1
        step_max = v_max * dt_s
        if abs(r - self.setpoint_m) > step_max:
            r = self.setpoint_m + math.copysign(step_max, r - self.setpoint_m)
            self.rate_limited_setpoints += 1
        w = min(max(velocity_ff_m_s, -v_max), v_max)
        self.setpoint_m = r
        t0 = self._t_s
        t1 = t0 + dt_s
        self._times.append(t1)
        self._inputs.append((r, w))
        x, v = self.x_m, self.xd_m_s
        stroke = self.stroke_m
        delay = p.transport_delay_s
        # sub-steps in the valve's (delayed) time, cut at the setpoint's samples, where the
        # input is linear: the discretisation is exact between the limits
        start, end = t0 - delay, t1 - delay
        n = max(1, math.ceil(dt_s / MAX_SUBSTEP_S - 1e-9))
        times = self._times
        inner = times[bisect.bisect_right(times, start) : bisect.bisect_left(times, end)]
        cuts = sorted([start + k * dt_s / n for k in range(1, n)] + inner)
        ta = start
        ra, wa = self._input_at(ta)
        for tb in (*cuts, end):
            if tb != end and (tb - ta < _MIN_SUBSTEP_S or end - tb < _MIN_SUBSTEP_S):
                continue
            h = tb - ta
            p00, p01, g00, g01, h00, h01, p10, p11, g10, g11, h10, h11 = self._coefficients(h)
            rb, wb = self._input_at(tb)
            dr, dw = (rb - ra) / h, (wb - wa) / h
            x_next = p00 * x + p01 * v + g00 * ra + g01 * wa + h00 * dr + h01 * dw
            v = p10 * x + p11 * v + g10 * ra + g11 * wa + h10 * dr + h11 * dw
            # the valve's flow limit: neither the velocity nor the mean one over the sub-step
            v = min(max(v, -v_max), v_max)
            x += min(max(x_next - x, -v_max * h), v_max * h)
            if abs(x) >= stroke:
                x = math.copysign(stroke, x)
                if v * x > 0.0:
                    v = 0.0
            ta, ra, wa = tb, rb, wb
        self._t_s = t1
        # keep the samples the delay line still needs (one before t1 - delay - dt)
        keep = bisect.bisect_right(self._times, t1 - delay - dt_s) - 1
        if keep > 0:
            del self._times[:keep], self._inputs[:keep]
        self.x_m, self.xd_m_s = x, v
        return x, v
