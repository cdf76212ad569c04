"""The plant: modified Bouc-Wen MR damper (Spencer et al. 1997; paper eqs 30-36).

State (z, y, u): the evolutionary variable z, the internal displacement y and u, the lagged
effect of the command v (volts or amperes, depending on the preset). The integrator is
fixed-step RK4 with sub-steps of at most `substep_s` (the system is stiff: its fastest
eigenvalue is about -4e3 1/s, so 1-2 ms steps are unstable). That eigenvalue, d(z')/dz at the
saturated z, grows with the speed: a step faster than its sub-steps are stable for (0.35 m/s
for 0.25 ms sub-steps, paper parameters) takes more sub-steps, so that a velocity spike of the
estimate (after a bus stall) gives a finite force. The displacement inside a step is the
cubic Hermite interpolant of the step's end points and velocities.

The same code runs on Python floats (one damper, the 0.5 kHz simulator: operators and abs()
only, so no numpy overhead) and on numpy arrays of equal shape (a batch of independent dampers).
"""

from __future__ import annotations

import math
from dataclasses import astuple, dataclass, replace
from typing import Any, ClassVar

import numpy as np

# A float, or a numpy array of equal shape for a batch of dampers.
Num = Any

# Up to this many dampers, one Python-float run per damper beats one numpy batch run (the
# batch step's per-operation overhead; docs/measurements.md).
_SCALAR_BATCH_MAX = 32

# RK4 is stable for h * lambda down to -2.785 on the real axis; keep h * lambda >= -2.
_RK4_STABLE_H_LAMBDA = 2.0
# At most this many sub-steps per step, whatever the speed (17 m/s in a 2 ms step, paper
# parameters): past it, a speed no damper reaches gives a non-finite force, which the caller
# checks, instead of holding up a real-time loop.
_MAX_SUBSTEPS = 400

_PAPER_TABLE_3 = dict(
    c0a=784.0,
    c0b=1803.0,
    k0=3610.0,
    c1a=14649.0,
    c1b=34622.0,
    k1=840.0,
    x0=0.0245,
    alpha_a=12441.0,
    alpha_b=38430.0,
    gamma=136320.0,
    beta=2059020.0,
    A=58.0,
    n=2.0,
    eta=190.0,
)


@dataclass(frozen=True)
class BoucWenParams:
    """Modified Bouc-Wen parameters, SI units; the `*b` terms are per unit of command."""

    c0a: float  # N s/m
    c0b: float  # N s/m per unit command
    k0: float  # N/m
    c1a: float  # N s/m
    c1b: float  # N s/m per unit command
    k1: float  # N/m
    x0: float  # m, accumulator offset
    alpha_a: float  # N/m
    alpha_b: float  # N/m per unit command
    gamma: float  # 1/m^2, multiplies |x'-y'|
    beta: float  # 1/m^2, multiplies (x'-y')
    A: float  # dimensionless
    n: float  # dimensionless
    eta: float  # 1/s, command lag

    PRESETS: ClassVar[tuple[str, ...]] = ("paper-volt", "rig-current")

    @classmethod
    def preset(cls, name: str) -> BoucWenParams:
        """A named parameter set.

        - ``"paper-volt"``: paper Table 3 (Lai & Liao 2002, Lord RD-1005-1), command in volts.
        - ``"rig-current"``: the same numbers per ampere, for a current-driven rig over 0-2 A.
          This is an assumption of the simulator, not an identified current model.
        """
        if name not in cls.PRESETS:
            raise ValueError(f"unknown Bouc-Wen preset {name!r}; known: {', '.join(cls.PRESETS)}")
        return cls(**_PAPER_TABLE_3)


# the force parameters that a temperature scales: viscous (eqs 34-35), yield (eq. 33), stiffness
VISCOUS_PARAMS = ("c0a", "c0b", "c1a", "c1b")
YIELD_PARAMS = ("alpha_a", "alpha_b")
STIFFNESS_PARAMS = ("k0", "k1")


def params_at_temperature(
    params: BoucWenParams,
    rise_k: float,
    viscous_per_k: float,
    yield_per_k: float,
    stiffness_per_k: float,
) -> BoucWenParams:
    """The parameters of a damper `rise_k` warmer than the one `params` describe: each group
    of force parameters times (1 + coefficient * rise), at least 0.05. With one coefficient
    for all three groups, the force at any current and motion is scaled by that factor
    exactly: y' (eq. 32) is a ratio of the scaled parameters, and z (eq. 31) holds none."""
    factors = {}
    for names, per_k in (
        (VISCOUS_PARAMS, viscous_per_k),
        (YIELD_PARAMS, yield_per_k),
        (STIFFNESS_PARAMS, stiffness_per_k),
    ):
        f = max(0.05, 1.0 + per_k * rise_k)
        factors.update({n: getattr(params, n) * f for n in names})
    return replace(params, **factors)


def bouc_wen_rates(
    z: Num, y: Num, u: Num, x: Num, xd: Num, v: Num, k: tuple
) -> tuple[Num, Num, Num]:
    """(z', y', u') for the state (z, y, u), displacement x, velocity xd and command v; the
    parameters `k` (`astuple(BoucWenParams)`) may be arrays too (a batch of parameter sets:
    `mrrig identify`'s Jacobian)."""
    c0a, c0b, k0, c1a, c1b, _k1, _x0, aa, ab, gamma, beta, a_, n, eta = k
    alpha = aa + ab * u  # eq. 33
    c1 = c1a + c1b * u  # eq. 34
    c0 = c0a + c0b * u  # eq. 35
    yd = (alpha * z + c0 * xd + k0 * (x - y)) / (c0 + c1)  # eq. 32, denominator (c0 + c1)
    r = xd - yd
    az = abs(z)
    azn1 = az ** (n - 1.0)
    zd = -gamma * abs(r) * z * azn1 - beta * r * azn1 * az + a_ * r  # eq. 31
    ud = -eta * (u - v)  # eq. 36
    return zd, yd, ud


def bouc_wen_force(z: Num, y: Num, u: Num, x: Num, xd: Num, k: tuple) -> Num:
    """Damper force for the state and the kinematics (eq. 30)."""
    c0a, c0b, k0, c1a, c1b, k1, x0, aa, ab, _gamma, _beta, _a, _n, _eta = k
    c1 = c1a + c1b * u  # eq. 34
    c0 = c0a + c0b * u  # eq. 35
    yd = ((aa + ab * u) * z + c0 * xd + k0 * (x - y)) / (c0 + c1)  # eqs 32-33
    return c1 * yd + k1 * (x - x0)  # eq. 30


def state_derivative(state: np.ndarray, x: Num, xd: Num, command: Num, params: BoucWenParams):
    """d(z, y, u)/dt as an array, for `scipy.integrate.solve_ivp` (state = [z, y, u])."""
    z, y, u = state
    return np.array(bouc_wen_rates(z, y, u, x, xd, command, astuple(params)))


def damper_force(state: np.ndarray, x: Num, xd: Num, params: BoucWenParams) -> Num:
    """Force (eq. 30) for state = [z, y, u] and the current displacement and velocity."""
    z, y, u = state
    return bouc_wen_force(z, y, u, x, xd, astuple(params))


def _speed_bound(x0: Num, v0: Num, x1: Num, v1: Num, dt_s: float) -> float:
    """The largest of the end speeds and the mean speed of a step (of all dampers of a batch)."""
    if isinstance(x1, float) and isinstance(x0, float):
        return max(abs(v0), abs(v1), abs(x1 - x0) / dt_s)
    return float(np.max(np.maximum(np.maximum(np.abs(v0), np.abs(v1)), np.abs(x1 - x0) / dt_s)))


def _hermite_nodes(dt_s: float, m: int) -> tuple[tuple[float, ...], ...]:
    """Weights (a0..a3, b0..b3) per node s = j/(2m), j = 0..2m, of the cubic Hermite
    interpolant: x(s) = a0*x0 + a1*v0 + a2*x1 + a3*v1, x'(s) = b0*x0 + ... (dt folded in)."""
    nodes = []
    for j in range(2 * m + 1):
        s = j / (2 * m)
        s2, s3 = s * s, s * s * s
        nodes.append(
            (
                2 * s3 - 3 * s2 + 1,
                dt_s * (s3 - 2 * s2 + s),
                -2 * s3 + 3 * s2,
                dt_s * (s3 - s2),
                (6 * s2 - 6 * s) / dt_s,
                3 * s2 - 4 * s + 1,
                (-6 * s2 + 6 * s) / dt_s,
                3 * s2 - 2 * s,
            )
        )
    return tuple(nodes)


class BoucWenDamper:
    """One damper (float state) or a batch of independent dampers (numpy array state)."""

    def __init__(self, params: BoucWenParams, substep_s: float = 1e-4) -> None:
        if not substep_s > 0.0:
            raise ValueError(f"substep_s must be positive, got {substep_s}")
        self.params = params
        self.substep_s = substep_s
        self._k = astuple(params)
        # |d(z')/dz| per m/s of relative velocity at the saturated |z| = (A / (gamma + beta))^(1/n)
        # (eq. 31): a sub-step may cover this much travel and stay stable
        g = params.gamma + params.beta
        stiffness_per_m = g * params.n * (params.A / g) ** ((params.n - 1.0) / params.n)
        self._max_substep_travel_m = _RK4_STABLE_H_LAMBDA / stiffness_per_m
        self._dt_s = -1.0
        self._m = 0
        self._nodes: tuple[tuple[float, ...], ...] = ()
        # the last fast step's nodes (more sub-steps, same dt) and their number: one table, so
        # that a run's memory does not grow with every new speed its stalls bring
        self._fast_m = 0
        self._fast_nodes: tuple[tuple[float, ...], ...] = ()
        self.reset(0.0)

    def set_params(self, params: BoucWenParams) -> None:
        """New force parameters from the next step on (a damper whose fluid warms), the state
        kept; the hysteresis shape (gamma, beta, A, n) must stay, for the sub-step bound."""
        same = ("gamma", "beta", "A", "n")
        if any(getattr(params, k) != getattr(self.params, k) for k in same):
            raise ValueError("set_params: gamma, beta, A and n must stay as they are")
        self.params = params
        self._k = astuple(params)

    @property
    def state(self) -> tuple[Num, Num, Num]:
        """(z, y, u) now."""
        return self._z, self._y, self._u

    def reset(self, x_m: Num, xd_m_s: Num = 0.0, command: Num = 0.0) -> Num:
        """Rest state at displacement x_m: z = 0, y = x, u = command. Returns the force."""
        self._z = x_m * 0.0
        self._y = x_m + 0.0  # a copy for arrays
        self._u = command + x_m * 0.0  # broadcast to the batch shape
        self._x = x_m + 0.0
        self._xd = xd_m_s + x_m * 0.0
        return bouc_wen_force(self._z, self._y, self._u, self._x, self._xd, self._k)

    def set_state(self, state: tuple[Num, Num, Num], x_m: Num, xd_m_s: Num) -> None:
        """Put the damper back in the state (z, y, u) at displacement x_m and velocity xd_m_s
        (a forward model steps ahead from its state and returns to it: mrrig.loop.twin_model)."""
        self._z, self._y, self._u = state
        self._x, self._xd = x_m, xd_m_s

    def step(self, x_m: Num, xd_m_s: Num, command: Num, dt_s: float) -> Num:
        """Advance dt_s to the displacement x_m and velocity xd_m_s, the command held.

        Returns the force (eq. 30) at the end of the interval.
        """
        # Sample-time jitter at rounding level (np.diff of a time base) keeps the cached nodes.
        if abs(dt_s - self._dt_s) > 1e-9 * dt_s:
            if not dt_s > 0.0:
                raise ValueError(f"dt_s must be positive, got {dt_s}")
            self._m = max(1, math.ceil(dt_s / self.substep_s - 1e-9))
            self._nodes = _hermite_nodes(dt_s, self._m)
            self._fast_m, self._fast_nodes = 0, ()
            self._dt_s = dt_s
        k = self._k
        x0, v0, x1, v1 = self._x, self._xd, x_m, xd_m_s
        m, nodes = self._m, self._nodes
        travel_m = _speed_bound(x0, v0, x1, v1, dt_s) * dt_s
        if travel_m > m * self._max_substep_travel_m and math.isfinite(travel_m):
            m = min(math.ceil(travel_m / self._max_substep_travel_m), _MAX_SUBSTEPS)
            if m != self._fast_m:  # a sustained fast motion reuses them
                self._fast_m, self._fast_nodes = m, _hermite_nodes(dt_s, m)
            nodes = self._fast_nodes
        h = dt_s / m
        h2, h6 = 0.5 * h, h / 6.0
        z, y, u = self._z, self._y, self._u
        for j in range(m):
            a = nodes[2 * j]
            xa = a[0] * x0 + a[1] * v0 + a[2] * x1 + a[3] * v1
            va = a[4] * x0 + a[5] * v0 + a[6] * x1 + a[7] * v1
            b = nodes[2 * j + 1]
            xb = b[0] * x0 + b[1] * v0 + b[2] * x1 + b[3] * v1
            vb = b[4] * x0 + b[5] * v0 + b[6] * x1 + b[7] * v1
            c = nodes[2 * j + 2]
            xc = c[0] * x0 + c[1] * v0 + c[2] * x1 + c[3] * v1
            vc = c[4] * x0 + c[5] * v0 + c[6] * x1 + c[7] * v1
            z1, y1, u1 = bouc_wen_rates(z, y, u, xa, va, command, k)
            z2, y2, u2 = bouc_wen_rates(z + h2 * z1, y + h2 * y1, u + h2 * u1, xb, vb, command, k)
            z3, y3, u3 = bouc_wen_rates(z + h2 * z2, y + h2 * y2, u + h2 * u2, xb, vb, command, k)
            z4, y4, u4 = bouc_wen_rates(z + h * z3, y + h * y3, u + h * u3, xc, vc, command, k)
            z = z + h6 * (z1 + 2.0 * (z2 + z3) + z4)
            y = y + h6 * (y1 + 2.0 * (y2 + y3) + y4)
            u = u + h6 * (u1 + 2.0 * (u2 + u3) + u4)
        self._z, self._y, self._u = z, y, u
        self._x, self._xd = x1, v1
        return bouc_wen_force(z, y, u, x1, v1, k)


def simulate(
    params: BoucWenParams,
    t_s: np.ndarray,
    x_m: np.ndarray,
    xd_m_s: np.ndarray,
    command: np.ndarray,
    substep_s: float = 1e-4,
) -> np.ndarray:
    """Open-loop force series for displacement, velocity and command series.

    Arrays run along the last axis (t_s is 1-D, the time of each sample); leading axes are a
    batch of independent dampers (one numpy batch run, or one float run per damper for small
    batches, which is faster; the results are the same, unless a step is fast enough to need
    more sub-steps: a batch then takes as many as its fastest damper). The damper starts at
    rest at the first sample (z = 0, y = x, u = command) and command[k] is held over
    [t_k, t_k+1] (zero-order hold, as a sampled controller applies it).
    """
    t_s = np.asarray(t_s, dtype=float)
    x_m, xd_m_s, command = np.broadcast_arrays(
        np.asarray(x_m, dtype=float), np.asarray(xd_m_s, dtype=float), np.asarray(command, float)
    )
    if t_s.ndim != 1 or x_m.shape[-1] != t_s.size:
        raise ValueError(f"t_s must be 1-D with the series' length {x_m.shape[-1]}")
    force = np.empty(x_m.shape)
    damper = BoucWenDamper(params, substep_s)
    dts = np.diff(t_s).tolist()
    if x_m[..., 0].size <= _SCALAR_BATCH_MAX:
        for idx in np.ndindex(x_m.shape[:-1]):
            xs, vs, cs = x_m[idx].tolist(), xd_m_s[idx].tolist(), command[idx].tolist()
            out = [damper.reset(xs[0], vs[0], cs[0])]
            step = damper.step
            for i, dt in enumerate(dts, start=1):
                out.append(step(xs[i], vs[i], cs[i - 1], dt))
            force[idx] = out
        return force
    force[..., 0] = damper.reset(x_m[..., 0], xd_m_s[..., 0], command[..., 0])
    for i, dt in enumerate(dts, start=1):
        force[..., i] = damper.step(x_m[..., i], xd_m_s[..., i], command[..., i - 1], dt)
    return force
