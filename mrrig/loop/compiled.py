"""The frame's numerics compiled (numba `njit`, cached on disk): the Kalman step, the network's
force and its exact scalar current solve (network inversion), and the reference damper's
Bouc-Wen step. Each is the Python path's arithmetic in the same order, so the two agree to
rounding (tests/test_compiled_path.py: to 1e-12 over the frames of a recorded run); the
Python classes stay the reference and the fallback.

Why numba: the wheels carry LLVM (llvmlite), so a fresh clone gets the compiler from PyPI with
the project's dependencies and needs no C compiler; `cache=True` keeps the machine code in
`__pycache__`, which `scripts/bootstrap.sh` fills (`warm()`), so a daemon loads it in a few
hundred ms instead of compiling for seconds. Without numba the daemon runs the Python path and
says so once.

What runs compiled (`kalman`, `compile_controller`, `compile_reference`): `RealtimeKalman`
(the daemon's estimate); the exact method of `NetworkInversion` on a model without history
inputs (`ScalarInverter`'s solve, solve ahead and force: `compiled_inversion`); and
`BoucWenReference`'s damper (the `bouc_wen` and `paper_case` references). Everything else runs
on the Python path: the flow and gradient methods, models with history inputs, twin and GRU
inversion, the supervised and recurrent inverses, the constant, Heaviside and continuous-state
laws, the other references, the clamp and the slew limit (a few float operations each: a call
into compiled code costs more than they do), the detectors, and the packing (cantools' codec).
The hybrid loop's frame (the substructure, its law and delay compensation) is compiled in
`mrrig.loop.compiled_hil`.
"""

from __future__ import annotations

import functools
import logging
import math

import numpy as np

from damper.plant import _MAX_SUBSTEPS, BoucWenDamper, BoucWenParams
from mrrig.loop.compiled_inversion import CompiledScalarInverter
from mrrig.loop.compiled_kernels import AVAILABLE, njit
from mrrig.loop.controllers import FORWARD_INPUTS, Controller, NetworkInversion
from mrrig.loop.estimation import RealtimeKalman
from mrrig.loop.inversion import ScalarInverter
from mrrig.loop.mlp import MLP
from mrrig.loop.reference import BoucWenReference, ForceReference

log = logging.getLogger(__name__)

try:
    from numba import njit

    AVAILABLE = True
except ImportError:  # the Python path; `use_compiled` says so
    AVAILABLE = False

    def njit(*_args, **_kwargs):
        return lambda f: f


# ---- the Kalman step (estimation.RealtimeKalman) ---------------------------------------------
# one state array: x 0:3, P 3:12, Q 12:21, prior 21:24, P prior 24:33, gain 33:36,
# P posterior 36:45, prepared flag 45
_KF_SIZE = 46


@njit
def _kf_prepare(st, T, r0):  # noqa: ANN001, ANN202 - numba types it
    if st[45] != 0.0:
        return
    h = 0.5 * T * T
    x0, x1, x2 = st[0], st[1], st[2]
    st[21] = x0 + T * x1 + h * x2  # eq. 25
    st[22] = x1 + T * x2
    st[23] = x2
    # eq. 26: P = A P A^T + Q, as RealtimeKalman.prepare, term by term
    for i in range(3):
        if i == 0:
            a0 = st[3 + 0] + T * st[3 + 3] + h * st[3 + 6]
            a1 = st[3 + 1] + T * st[3 + 4] + h * st[3 + 7]
            a2 = st[3 + 2] + T * st[3 + 5] + h * st[3 + 8]
        elif i == 1:
            a0 = st[3 + 3] + T * st[3 + 6]
            a1 = st[3 + 4] + T * st[3 + 7]
            a2 = st[3 + 5] + T * st[3 + 8]
        else:
            a0, a1, a2 = st[3 + 6], st[3 + 7], st[3 + 8]
        st[24 + 3 * i] = a0 + T * a1 + h * a2 + st[12 + 3 * i]
        st[24 + 3 * i + 1] = a1 + T * a2 + st[12 + 3 * i + 1]
        st[24 + 3 * i + 2] = a2 + st[12 + 3 * i + 2]
    r = r0 / (1.0 + abs(st[22]))  # eq. 24 with the predicted x'
    s = st[24] + r
    for i in range(3):
        st[33 + i] = st[24 + 3 * i] / s  # eq. 27
    for i in range(3):
        for j in range(3):
            st[36 + 3 * i + j] = st[24 + 3 * i + j] - st[33 + i] * st[24 + j]  # eq. 29
    st[45] = 1.0


@njit
def _kf_update(st, T, r0, x_meas, measured):  # noqa: ANN001, ANN202
    _kf_prepare(st, T, r0)
    st[45] = 0.0
    if not measured:  # the prediction is kept, with its covariance
        for i in range(3):
            st[i] = st[21 + i]
        for i in range(9):
            st[3 + i] = st[24 + i]
        return st[0], st[1], st[2]
    y = x_meas - st[21]
    for i in range(3):
        st[i] = st[21 + i] + st[33 + i] * y  # eq. 28
    for i in range(9):
        st[3 + i] = st[36 + i]
    return st[0], st[1], st[2]


@njit
def _kf_prior(st, T, r0):  # noqa: ANN001, ANN202
    _kf_prepare(st, T, r0)
    return st[21], st[22], st[23]


class CompiledKalman(RealtimeKalman):
    """`RealtimeKalman` with its step compiled; the same numbers (the module's docstring)."""

    def reset(self, x0: float) -> None:
        super().reset(x0)
        st = np.zeros(_KF_SIZE)
        st[0] = float(x0)
        st[3:12] = np.asarray(self._p).ravel()
        st[12:21] = np.asarray(self._q).ravel()
        self._st = st

    def prepare(self) -> None:
        _kf_prepare(self._st, self.dt_s, self.r0)

    @property
    def prior(self) -> tuple[float, float, float]:
        return _kf_prior(self._st, self.dt_s, self.r0)

    @property
    def gain(self) -> tuple[float, float, float]:
        self.prepare()
        return tuple(self._st[33:36].tolist())

    def update(self, x_meas: float | None) -> tuple[float, float, float]:
        if x_meas is None:
            return _kf_update(self._st, self.dt_s, self.r0, 0.0, False)
        return _kf_update(self._st, self.dt_s, self.r0, x_meas, True)


# ---- the reference damper's step (damper.plant.BoucWenDamper, one damper) ---------------------
@njit
def _rates(z, y, u, x, xd, v, k):  # noqa: ANN001, ANN202
    """`damper.plant.bouc_wen_rates`."""
    alpha = k[7] + k[8] * u  # eq. 33
    c1 = k[3] + k[4] * u  # eq. 34
    c0 = k[0] + k[1] * u  # eq. 35
    yd = (alpha * z + c0 * xd + k[2] * (x - y)) / (c0 + c1)  # eq. 32
    r = xd - yd
    az = abs(z)
    azn1 = az ** (k[12] - 1.0)
    zd = -k[9] * abs(r) * z * azn1 - k[10] * r * azn1 * az + k[11] * r  # eq. 31
    ud = -k[13] * (u - v)  # eq. 36
    return zd, yd, ud


@njit
def _node(j, m, dt, x0, v0, x1, v1):  # noqa: ANN001, ANN202
    """The cubic Hermite interpolant at node j of 2m (`damper.plant._hermite_nodes`)."""
    s = j / (2 * m)
    s2, s3 = s * s, s * s * s
    x = (
        (2 * s3 - 3 * s2 + 1) * x0
        + dt * (s3 - 2 * s2 + s) * v0
        + (-2 * s3 + 3 * s2) * x1
        + dt * (s3 - s2) * v1
    )
    v = (
        (6 * s2 - 6 * s) / dt * x0
        + (3 * s2 - 4 * s + 1) * v0
        + (-6 * s2 + 6 * s) / dt * x1
        + (3 * s2 - 2 * s) * v1
    )
    return x, v


@njit
def _bw_step(k, z, y, u, x0, v0, x1, v1, command, dt, m, max_travel):  # noqa: ANN001, ANN202
    """`BoucWenDamper.step` on floats: (z, y, u, force)."""
    speed = abs(v0)
    if abs(v1) > speed:
        speed = abs(v1)
    if abs(x1 - x0) / dt > speed:
        speed = abs(x1 - x0) / dt
    travel = speed * dt
    if travel > m * max_travel and math.isfinite(travel):
        m = min(math.ceil(travel / max_travel), _MAX_SUBSTEPS)
    h = dt / m
    h2, h6 = 0.5 * h, h / 6.0
    for j in range(m):
        xa, va = _node(2 * j, m, dt, x0, v0, x1, v1)
        xb, vb = _node(2 * j + 1, m, dt, x0, v0, x1, v1)
        xc, vc = _node(2 * j + 2, m, dt, x0, v0, x1, v1)
        z1, y1, u1 = _rates(z, y, u, xa, va, command, k)
        z2, y2, u2 = _rates(z + h2 * z1, y + h2 * y1, u + h2 * u1, xb, vb, command, k)
        z3, y3, u3 = _rates(z + h2 * z2, y + h2 * y2, u + h2 * u2, xb, vb, command, k)
        z4, y4, u4 = _rates(z + h * z3, y + h * y3, u + h * u3, xc, vc, command, k)
        z = z + h6 * (z1 + 2.0 * (z2 + z3) + z4)
        y = y + h6 * (y1 + 2.0 * (y2 + y3) + y4)
        u = u + h6 * (u1 + 2.0 * (u2 + u3) + u4)
    c1 = k[3] + k[4] * u  # eq. 34
    c0 = k[0] + k[1] * u  # eq. 35
    yd = ((k[7] + k[8] * u) * z + c0 * v1 + k[2] * (x1 - y)) / (c0 + c1)  # eqs 32-33
    return z, y, u, c1 * yd + k[5] * (x1 - k[6])  # eq. 30


class CompiledBoucWenDamper(BoucWenDamper):
    """One damper (float state) stepped in compiled code; a batch (arrays) stays Python."""

    def step(self, x_m, xd_m_s, command, dt_s: float):  # noqa: ANN001, ANN201
        if not isinstance(self._z, float):
            return super().step(x_m, xd_m_s, command, dt_s)
        if abs(dt_s - self._dt_s) > 1e-9 * dt_s:
            if not dt_s > 0.0:
                raise ValueError(f"dt_s must be positive, got {dt_s}")
            self._m = max(1, math.ceil(dt_s / self.substep_s - 1e-9))
            self._dt_s = dt_s
        if self._k_array is None:
            self._k_array = np.array(self._k, dtype=float)
        z, y, u, f = _bw_step(
            self._k_array,
            self._z,
            self._y,
            self._u,
            float(self._x),
            float(self._xd),
            float(x_m),
            float(xd_m_s),
            float(command),
            dt_s,
            self._m,
            self._max_substep_travel_m,
        )
        self._z, self._y, self._u = z, y, u
        self._x, self._xd = x_m, xd_m_s
        return f

    _k_array: np.ndarray | None = None

    def set_params(self, params) -> None:  # noqa: ANN001
        super().set_params(params)
        self._k_array = None


# ---- the switch -----------------------------------------------------------------------------
def kalman(period_s: float, q: float, r0: float, compiled: bool) -> RealtimeKalman:
    """The daemon's estimate: compiled where it can be (numba installed)."""
    if compiled:
        warm()  # each kernel loaded (or compiled) now, not at the first frame
    cls = CompiledKalman if compiled and AVAILABLE else RealtimeKalman
    return cls(period_s, q=q, r0=r0)


def compile_controller(controller: Controller) -> Controller:
    """`controller` with its exact scalar solve compiled (network inversion, exact method, no
    history inputs); any other kind as it is (the module's docstring)."""
    if (
        AVAILABLE
        and type(controller) is NetworkInversion
        and controller.method == "exact"
        and not controller._inputs.samples
        and type(controller._scalar) is ScalarInverter
    ):
        controller._scalar = CompiledScalarInverter(
            controller.model, controller.i_max, continuity=controller.continuity
        )
    return controller


def compile_reference(reference: ForceReference) -> ForceReference:
    """A reference damper (`bouc_wen`, `paper_case`) stepped in compiled code, its state kept;
    any other reference as it is."""
    if AVAILABLE and isinstance(reference, BoucWenReference):
        old = reference._damper
        if type(old) is BoucWenDamper:
            new = CompiledBoucWenDamper(old.params, substep_s=old.substep_s)
            new.set_state(old.state, old._x, old._xd)
            reference._damper = new
    return reference


@functools.cache
def warm() -> None:
    """Compile every kernel once (or load it from the cache), once a process: the daemon does
    before its loop; `scripts/bootstrap.sh` does, so that a daemon's start loads the cache
    (about 0.5 s) rather than compiling (about 10 s)."""
    if not AVAILABLE:
        log.warning("numba is not installed: the frame's numerics run on the Python path")
        return
    kf = CompiledKalman(0.002)
    kf.prepare()
    kf.update(0.001)
    kf.update(None)
    kf.prior  # noqa: B018 - compiles _kf_prior
    d = CompiledBoucWenDamper(BoucWenParams.preset("rig-current"), substep_s=2.5e-4)
    d.step(0.001, 0.1, 1.0, 0.002)
    rng = np.random.default_rng(0)
    model = MLP(
        W1=rng.normal(size=(4, 4)),
        b1=np.zeros(4),
        W2=rng.normal(size=4),
        b2=0.0,
        in_mean=np.zeros(4),
        in_std=np.ones(4),
        out_mean=0.0,
        out_std=100.0,
        input_names=list(FORWARD_INPUTS),
        input_units=["m", "m/s", "m/s^2", "A"],
        output_name="force",
        output_unit="N",
    )
    feat = np.zeros(3)
    for mu in (0.0, 1.0):
        inv = CompiledScalarInverter(model, 2.0, continuity=mu)
        inv.prepare(feat, 10.0, 0.5)
        inv.solve(feat, 10.0, 0.5)
        inv.force(feat, 0.5)
