"""The hybrid loop's frame compiled (numba, `mrrig.loop.compiled_kernels`): `HybridStep.step`
of a quarter car or a building with its law and its delay compensation (`model` or `none`) in
one kernel call: the law's demand on the model's state, the exact step with the measured force,
the on-line delay estimate (`DelayEstimator.update`) and the model's prediction over it
(`_Predicting.predicted_state`). The Python classes of `mrrig.hil` stay the reference (the
all-numerical reference runs them) and the fallback: the arithmetic is theirs, in their order,
so the two agree to rounding (tests/test_compiled_hil.py: to 1e-12 over whole runs).

Runs on the Python path: a playback (its step is a look-up), the `polynomial` and `adaptive`
compensations. `hybrid_step` chooses.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from mrrig.hil.compensation import ModelCompensator, NoCompensation
from mrrig.hil.laws import Demand
from mrrig.hil.scenario import Scenario
from mrrig.hil.stepper import Frame, HybridStep
from mrrig.hil.substructure import _FRACTIONS, QuarterCar
from mrrig.loop.compiled_kernels import AVAILABLE, njit

# the substructure (`_KIND`), the law (`_LAW`), the compensation (`_COMP`) as numbers
_QUARTER_CAR, _BUILDING = 0, 1
_SKYHOOK, _GROUNDHOOK, _HYBRID, _CLIPPED, _SOFT, _HARD = range(6)
_LAW = {
    "skyhook": _SKYHOOK,
    "groundhook": _GROUNDHOOK,
    "hybrid": _HYBRID,
    "clipped-optimal": _CLIPPED,
    "passive-soft": _SOFT,
    "passive-hard": _HARD,
}
_COMP_NONE, _COMP_MODEL = 0, 1
# p: kind, law, c_sky, c_ground, alpha, i_max, on/off, compensation, period, max lead (frames)
(_P_KIND, _P_LAW, _P_SKY, _P_GROUND, _P_ALPHA, _P_IMAX, _P_ONOFF, _P_COMP, _P_T, _P_MAXLEAD) = (
    range(10)
)
# est: has a last measured stroke, it, updates before the first estimate, the delay (frames),
# forgetting factor, least S(DD), a setpoint sent, it (or the last target for `none`)
_E_HAS_LAST, _E_LAST, _E_WARMUP, _E_DELAY, _E_FORGET, _E_MIN_DD, _E_HAS_SENT, _E_SENT = range(8)
# out: force (NaN: a current), current (NaN: a force), target, its velocity, setpoint, its
# velocity, delay (frames), body acceleration, tyre load
_O_FORCE, _O_CURRENT, _O_TARGET, _O_TARGET_V, _O_SET, _O_SET_V, _O_DELAY, _O_ACC, _O_LOAD = range(9)
_OUT = 9


@njit
def _stroke(kind, x):  # noqa: ANN001, ANN202
    """(s, s') of a state: the quarter car's z_s - z_u, the building's first drift."""
    if kind == _QUARTER_CAR:
        return x[0] - x[2], x[1] - x[3]
    n = x.shape[0] // 2
    return x[0], x[n]


@njit
def _advance(ad, bd, x, force, excitation, y):  # noqa: ANN001, ANN202
    """y = Ad x + Bd [F, e] (`ad @ x + bd @ np.array([F, e])`, each product summed in order)."""
    n = x.shape[0]
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += ad[i, j] * x[j]
        y[i] = acc + (bd[i, 0] * force + bd[i, 1] * excitation)


@njit
def _dissipative(force, velocity):  # noqa: ANN001, ANN202
    return force if force * velocity > 0.0 else 0.0


@njit
def _demand(p, gain, x, exc, k, f_meas, out):  # noqa: ANN001, ANN202
    """`Law.demand` on the model's state at frame k: out's force or current (the other NaN)."""
    law = int(p[_P_LAW])
    out[_O_FORCE] = math.nan
    out[_O_CURRENT] = math.nan
    if law == _SOFT:
        out[_O_CURRENT] = 0.0
        return
    if law == _HARD:
        out[_O_CURRENT] = p[_P_IMAX]
        return
    sv = _stroke(int(p[_P_KIND]), x)[1]
    if law == _CLIPPED:  # clipped-optimal: f_c = -K x_c (`Law.optimal_force_n`)
        acc = 0.0
        if int(p[_P_KIND]) == _QUARTER_CAR:  # [s, z_s', z_u - z_r, z_u']
            acc = gain[0] * (x[0] - x[2]) + gain[1] * x[1]
            acc = acc + gain[2] * (x[2] - exc[k]) + gain[3] * x[3]
        else:
            for j in range(x.shape[0]):
                acc += gain[j] * x[j]
        f_c = -acc
        if p[_P_ONOFF] != 0.0:
            on = (f_c - f_meas) * f_meas > 0.0
            out[_O_CURRENT] = p[_P_IMAX] if on else 0.0
            return
        out[_O_FORCE] = _dissipative(f_c, sv)
        return
    sky = _dissipative(p[_P_SKY] * x[1], sv)
    ground = _dissipative(-p[_P_GROUND] * x[3], sv)
    if law == _SKYHOOK:
        out[_O_FORCE] = sky
    elif law == _GROUNDHOOK:
        out[_O_FORCE] = ground
    else:
        out[_O_FORCE] = p[_P_ALPHA] * sky + (1.0 - p[_P_ALPHA]) * ground


@njit
def _sub_step(p, ad, bd, a, b, x, exc, k, f_meas, y, rec, out):  # noqa: ANN001, ANN202
    """`QuarterCar.step` / `ShearBuilding.step`: frame k's outputs, x advanced to k + 1."""
    e = exc[k]
    if int(p[_P_KIND]) == _QUARTER_CAR:
        # a, b: the quarter car's m_s, k_s, k_t as a[0, 0..2]
        s = x[0] - x[2]
        out[_O_ACC] = (-a[0, 1] * s - f_meas) / a[0, 0]
        out[_O_LOAD] = a[0, 2] * (e - x[2])
    else:
        n = x.shape[0] // 2
        last = 0.0
        for i in range(n):  # drifts: np.diff(q, prepend=0)
            rec[i] = x[i] - last
            last = x[i]
        for i in range(n):  # absolute accelerations: (A x + B u)[n:] + a_g
            acc = 0.0
            for j in range(2 * n):
                acc += a[n + i, j] * x[j]
            rec[n + i] = (acc + (b[n + i, 0] * f_meas + b[n + i, 1] * e)) + e
    _advance(ad, bd, x, f_meas, e, y)
    for i in range(x.shape[0]):
        x[i] = y[i]


@njit
def _estimate(est, sent, sums, sent_m, measured_m):  # noqa: ANN001, ANN202
    """`DelayEstimator.update` (and its `_refine`): sums rows S(aa), S(aD), S(DD)."""
    for j in range(sent.shape[0] - 1, 0, -1):  # the deque's appendleft
        sent[j] = sent[j - 1]
    sent[0] = sent_m
    if est[_E_HAS_LAST] != 0.0:
        dm = measured_m - est[_E_LAST]
        lam = est[_E_FORGET]
        for lag in range(sums.shape[1]):
            du0 = sent[lag] - sent[lag + 1]
            du1 = sent[lag + 1] - sent[lag + 2]
            av = dm - du0
            dv = du0 - du1
            sums[0, lag] = lam * sums[0, lag] + av * av
            sums[1, lag] = lam * sums[1, lag] + av * dv
            sums[2, lag] = lam * sums[2, lag] + dv * dv
        est[_E_WARMUP] -= 1.0
        if est[_E_WARMUP] <= 0.0:
            best = -1
            best_r = math.inf
            best_f = 0.0
            for lag in range(sums.shape[1]):
                dd = sums[2, lag]
                clamped = dd if (dd != dd or dd > 1e-30) else 1e-30  # np.maximum
                f = -sums[1, lag] / clamped
                if f < 0.0:  # np.clip, NaN kept
                    f = 0.0
                elif f > 1.0:
                    f = 1.0
                r = sums[0, lag] + 2.0 * f * sums[1, lag] + f * f * dd
                if r != r:  # numpy's argmin: the first NaN
                    best, best_f = lag, f
                    break
                if best < 0 or r < best_r:
                    best, best_r, best_f = lag, r, f
            if sums[2, best] > est[_E_MIN_DD]:
                est[_E_DELAY] = best + 1 + best_f
    est[_E_HAS_LAST] = 1.0
    est[_E_LAST] = measured_m


@njit
def _predict(p, ad, bd, fad, fbd, x, exc, k, force, lead, y, z):  # noqa: ANN001, ANN202
    """`_Predicting.predicted_stroke(lead)`: (s, s') with the force held, the excitation ahead."""
    whole = int(lead)
    last = exc.shape[0] - 1
    n = x.shape[0]
    for i in range(n):
        y[i] = x[i]
    for j in range(whole):
        _advance(ad, bd, y, force, exc[min(k + j, last)], z)
        for i in range(n):
            y[i] = z[i]
    j = round((lead - whole) * _FRACTIONS)
    if j > 0:
        _advance(fad[j], fbd[j], y, force, exc[min(k + whole, last)], z)
        for i in range(n):
            y[i] = z[i]
    return _stroke(int(p[_P_KIND]), y)


@njit
def _hil_step(  # noqa: ANN202, PLR0913
    p, gain, mats, fad, fbd, exc, x, k, f_meas, x_meas, est, sent, sums, work, rec, out
):  # noqa: ANN001
    """`HybridStep.step` at frame k (x the model's state, advanced in place): `out`."""
    ad, bd, a, b = mats[0], mats[1][:, :2], mats[2], mats[3][:, :2]
    y, z = work[0], work[1]
    _demand(p, gain, x, exc, k, f_meas, out)
    _sub_step(p, ad, bd, a, b, x, exc, k, f_meas, y, rec, out)
    kind = int(p[_P_KIND])
    target, target_v = _stroke(kind, x)
    out[_O_TARGET], out[_O_TARGET_V] = target, target_v
    if int(p[_P_COMP]) == _COMP_NONE:  # `NoCompensation.update`
        velocity = 0.0 if est[_E_HAS_SENT] == 0.0 else (target - est[_E_SENT]) / p[_P_T]
        est[_E_HAS_SENT], est[_E_SENT] = 1.0, target
        out[_O_SET], out[_O_SET_V], out[_O_DELAY] = target, velocity, 1.0
        return
    if est[_E_HAS_SENT] != 0.0:  # `ModelCompensator.update`: the estimate, then the lead
        _estimate(est, sent, sums, est[_E_SENT], x_meas)
    lead = min(max(est[_E_DELAY] - 1.0, 0.0), p[_P_MAXLEAD])
    s, sv = _predict(p, ad, bd, fad, fbd, x, exc, k + 1, f_meas, lead, y, z)
    est[_E_HAS_SENT], est[_E_SENT] = 1.0, s
    out[_O_SET], out[_O_SET_V], out[_O_DELAY] = s, sv, est[_E_DELAY]


def compiles(scenario: Scenario, compensate: bool = True) -> bool:
    """Whether `hybrid_step` runs this scenario's frame compiled (the module's docstring)."""
    method = scenario.compensation.method if compensate else "none"
    return AVAILABLE and scenario.kind != "playback" and method in ("model", "none")


def hybrid_step(scenario: Scenario, law: str | None = None, compensate: bool = True) -> HybridStep:
    """A fresh run of `scenario`: compiled where `compiles`, else the Python `HybridStep`."""
    if compiles(scenario, compensate):
        return CompiledHybridStep(scenario, law, compensate)
    return HybridStep(scenario, law, compensate)


class CompiledHybridStep(HybridStep):
    """`HybridStep` whose `step` is one compiled call; the substructure, law and compensator
    objects are the Python ones (built by `HybridStep`), kept in step with the kernel: the
    model's state array is advanced in place, its frame index, last force and outputs (the
    building's drifts and accelerations: arrays rewritten in place) set after each call, and
    the compensator's delay estimate (what `delay_s` reads)."""

    def __init__(self, scenario: Scenario, law: str | None = None, compensate: bool = True):
        super().__init__(scenario, law, compensate)
        sub, comp = self.substructure, self.compensator
        n = sub.x.size
        self._kind = _QUARTER_CAR if isinstance(sub, QuarterCar) else _BUILDING
        lp = self.law.params
        model = isinstance(comp, ModelCompensator)
        assert model or isinstance(comp, NoCompensation), "hybrid_step: model or none only"
        max_lead = comp.max_lead_frames if model else 0.0
        self._p = np.array(
            [
                self._kind,
                _LAW[self.law.name],
                lp.skyhook_c_n_s_per_m,
                lp.groundhook_c_n_s_per_m,
                lp.hybrid_alpha,
                self.law.i_max_a,
                float(lp.clipped_on_off),
                _COMP_MODEL if model else _COMP_NONE,
                scenario.period_s,
                max_lead,
            ]
        )
        gain = self.law._gain
        self._gain = np.zeros(n) if gain is None else np.ascontiguousarray(gain[0], dtype=float)
        # ad, bd (first 2 columns), then A (or the quarter car's m_s, k_s, k_t), B
        mats = np.zeros((4, n, n))
        mats[0], mats[1][:, :2] = sub._fractions[-1]
        if self._kind == _QUARTER_CAR:
            q = sub.params
            mats[2][0, :3] = q.m_s_kg, q.k_s_n_per_m, q.k_t_n_per_m
        else:
            mats[2], mats[3][:, :2] = sub.a, sub.b
        self._mats = mats
        self._fad = np.ascontiguousarray(np.stack([f[0] for f in sub._fractions]))
        self._fbd = np.ascontiguousarray(np.stack([f[1] for f in sub._fractions]))
        self._exc = np.ascontiguousarray(sub._excitation, dtype=float)
        self._est = np.zeros(8)
        if model:
            e = comp.delay.estimator
            self._est[_E_WARMUP] = e._warmup
            self._est[_E_DELAY] = e.delay_frames
            self._est[_E_FORGET] = e._forget
            self._est[_E_MIN_DD] = e._min_s_dd
            self._sent = np.zeros(e.max_lag + 2)
            self._sums = np.zeros((3, e.max_lag))
        else:
            self._sent = np.zeros(2)
            self._sums = np.zeros((3, 0))
        self._work = np.zeros((2, n))
        self._rec = np.zeros(n)  # the building's drifts, then accelerations
        self._out = np.zeros(_OUT)
        if self._kind == _BUILDING:
            nf = n // 2
            sub.drifts_m, sub.accelerations_m_s2 = self._rec[:nf], self._rec[nf:]

    def step(self, measured_force_n: float, measured_stroke_m: float) -> Frame:
        sub = self.substructure
        o = self._out
        _hil_step(
            self._p, self._gain, self._mats, self._fad, self._fbd, self._exc, sub.x, sub.k,
            float(measured_force_n), float(measured_stroke_m), self._est, self._sent,
            self._sums, self._work, self._rec, o,
        )  # fmt: skip
        sub.k += 1
        sub.force_n = measured_force_n
        if self._kind == _QUARTER_CAR:
            sub.body_acceleration_m_s2, sub.tyre_load_n = float(o[_O_ACC]), float(o[_O_LOAD])
        force, current, target, target_v, setpoint, velocity, delay = o[:_O_ACC].tolist()
        comp = self.compensator
        if isinstance(comp, ModelCompensator):
            comp.delay.estimator.delay_frames = delay
        # a law of a current leaves the force NaN, a law of a force the current
        demand = Demand(force_n=force) if math.isnan(current) else Demand(current_a=current)
        return Frame(demand, target, target_v, setpoint, velocity, comp.delay_s)


@functools.cache
def warm() -> None:
    """Compile the kernel (or load it from the cache) once a process, before the loop: on a
    model of its own (no run's record or matrix exponentials needed), every branch's argument
    types being the same."""
    if not AVAILABLE:
        return
    n = 4  # the quarter car's state; a building of two floors
    mats = np.zeros((4, n, n))
    mats[0] = np.eye(n)
    mats[2][0, :3] = 1.0
    fad, fbd = np.stack([np.eye(n)] * (_FRACTIONS + 1)), np.zeros((_FRACTIONS + 1, n, 2))
    for kind, comp in ((_QUARTER_CAR, _COMP_MODEL), (_BUILDING, _COMP_NONE)):
        p = np.array([kind, 0, 1.0, 1.0, 0.5, 1.0, 0.0, comp, 0.002, 10.0])
        est, x = np.zeros(8), np.zeros(n)
        for k in range(3):
            _hil_step(
                p, np.zeros(n), mats, fad, fbd, np.zeros(4), x, k, 1.0, 0.0, est,
                np.zeros(4), np.zeros((3, 2)), np.zeros((2, n)), np.zeros(n), np.zeros(_OUT),
            )  # fmt: skip
