"""Whether a model is plausible, checked where it is loaded, before the loop takes it: a model
file can have the right format, names and units and still be no model of a damper (random
weights, a coil lag of 1e-12 s, a twin whose offset is 1e300 N).

Two checks, both one-line `ModelError`s naming the file, the field and the value:

- `check_plausible`: sizes within bounds and every meta field, scaler and twin parameter
  within a physical range (`forward_model_from_text` runs it on every model it reads);
- `self_check`: a short closed loop on the model's own training envelope (the daemon runs it
  at start and for `set_controller` / `set_model`, with a spare of the controller it built):
  `SELF_CHECK_FRAMES` frames of a sine of the motion inside the envelope, twice: with the
  model itself as the damper, asked for the force it makes there with a smooth current, and
  with the reference damper (the simulator's), asked for its own force so. A model whose
  command chatters (moves more than `MAX_CHATTER` of [0, i_max] a frame on average: an
  untrained GRU steps it rail to rail on the reference damper though it tracks itself), that
  cannot track its own force, or whose force does not grow with the current along the motion
  (an MR damper's does, eqs 33-35) is refused. An inverse model (its output a current) has
  no force of its own: its commands on the reference damper alone are checked. About 0.1 s
  of CPU for a network or a GRU, 0.2 s for a twin.

Pure numerics.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from damper.plant import BoucWenDamper, BoucWenParams
from mrrig.loop.controllers import FORWARD_INPUTS, ControlInput, Controller, ModelInputs
from mrrig.loop.coverage import model_envelope
from mrrig.loop.gru import GRUModel, GruTracker
from mrrig.loop.mlp import MLP, ModelError
from mrrig.loop.twin_model import SUBSTEP_S, TwinModel, TwinTracker

# sizes: a network the loop could evaluate but no damper needs (check_cost bounds the time)
MAX_INPUTS = 256
MAX_HIDDEN = {"mlp": 1024, "gru": 256}
# the coil's lag (eq. 36: tau = 1/eta): from 10 us (below it, no lag at the loop's rate) to
# 1 s (above it, the command would have to be hundreds of times the current it wants)
LAG_TAU_S = (1e-5, 1.0)
# network inversion's continuity weight (standardised units: mrrig train chooses in [0, 1])
CONTINUITY = (0.0, 100.0)
SAMPLE_PERIOD_S = (1e-5, 1.0)
# standardisation of a network's inputs and output: means and scales of signals in SI units
MAX_MEAN = 1e9
SCALE = (1e-12, 1e12)
# the twin's (Bouc-Wen) parameters: about a thousand times the paper's (Table 3) either way;
# `damper.plant_file` checks the signs
TWIN_BOUNDS = {
    "c0a": 1e8,  # N s/m (and per unit command for the *b terms)
    "c0b": 1e8,
    "c1a": 1e8,
    "c1b": 1e8,
    "k0": 1e9,  # N/m
    "k1": 1e9,
    "alpha_a": 1e9,
    "alpha_b": 1e9,
    "x0": 1.0,  # m
    "gamma": 1e10,  # 1/m^2
    "beta": 1e10,
    "A": 1e5,
    "n": 10.0,
}
MAX_OFFSET_N = 1e5  # beyond any load cell (config: loop.f_range_n within 8e4 N)
# the envelope's physical bounds per input (x, xd, xdd, command)
ENVELOPE_BOUNDS = (1.0, 100.0, 1e5, 1e3)

# the self-check: frames, of which the first are not scored (the loop settling)
SELF_CHECK_FRAMES = 200
SELF_CHECK_WARMUP = 40
MOTION_HZ, CURRENT_HZ = 2.0, 1.3
# the command's mean step per frame, a share of [0, i_max], at most. With the model itself as
# the damper: trained networks, GRUs and twins measured 0.0025-0.004, untrained GRUs too
# (0.004-0.02: they track themselves). With the reference damper: the trained network and
# GRU 0.005, models of other dampers or fitted briefly up to 0.18 (a history network of the
# Dyke damper 0.136, an 8-unit GRU of 120 epochs 0.184), untrained 78-unit GRUs 0.06-0.59:
# those under this bound but one fail the damping share
MAX_CHATTER = 0.05
MAX_CHATTER_REFERENCE = 0.25
# the reference damper: the simulator's (configs/sim.toml), in A
REFERENCE_PRESET = "rig-current"
# an MR damper's force grows with the current along the motion (eqs 33-35): on the frames
# faster than FAST of the sine's peak velocity, at least this share of them. Trained networks,
# GRUs and twins of the simulator's damper measured 1.0, a history network of the Dyke damper
# 0.66; untrained 78-unit GRUs 0.29-0.86 (7 of 8 refused by one check or another; the eighth,
# 0.68 and 5.5 % a frame on the reference damper, passes: the loop's slew limit bounds it)
FAST = 0.5
MIN_DAMPING_SHARE = 0.6
# its own force: refused where the RMS error is over this share of the force's RMS variation
MAX_TRACKING_ERROR = 0.5


def _bad(path: Any, field: str, value: Any, what: str) -> ModelError:
    return ModelError(f"{path}: {field}: {value!r} {what}")


def _in(path: Any, field: str, value: Any, lo: float, hi: float, unit: str = "") -> float:
    """`value` as a float where it is a number in [lo, hi]; else the one-line error."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and lo <= value <= hi
    if not ok:
        unit = f" {unit}" if unit else ""
        raise ModelError(
            f"{path}: {field}: expected a number in [{lo:g}, {hi:g}]{unit}, got {value!r}"
        )
    return float(value)


def check_plausible(model: MLP | GRUModel | TwinModel, path: Path | str | None) -> None:
    """ModelError naming the first field of the model outside its physical range."""
    if isinstance(model, TwinModel):
        _check_twin(model, path)
        return
    kind = "gru" if isinstance(model, GRUModel) else "mlp"
    if model.n_in > MAX_INPUTS:
        raise _bad(path, "input_names", model.n_in, f"inputs: at most {MAX_INPUTS}")
    if model.hidden > MAX_HIDDEN[kind]:
        raise _bad(path, "hidden", model.hidden, f"units: at most {MAX_HIDDEN[kind]}")
    for name in ("in_mean", "out_mean"):
        values = np.atleast_1d(getattr(model, name))
        k = int(np.argmax(np.abs(values)))
        field = f"{name}[{k}]" if values.size > 1 else name
        _in(path, field, float(values[k]), -MAX_MEAN, MAX_MEAN)
    for name in ("in_std", "out_std"):
        values = np.atleast_1d(getattr(model, name))
        for k, v in enumerate(values):
            _in(path, f"{name}[{k}]" if values.size > 1 else name, float(v), *SCALE)
    meta = model.meta
    if meta.get("lag_tau_s") is not None:
        _in(path, "meta.lag_tau_s", meta["lag_tau_s"], *LAG_TAU_S, "s")
    if meta.get("online_continuity") is not None:
        _in(path, "meta.online_continuity", meta["online_continuity"], *CONTINUITY)
    if meta.get("sample_period_s") is not None:
        _in(path, "meta.sample_period_s", meta["sample_period_s"], *SAMPLE_PERIOD_S, "s")
    if meta.get("i_max_a") is not None:
        _in(path, "meta.i_max_a", meta["i_max_a"], 0.0, ENVELOPE_BOUNDS[3], "A")
    env = model_envelope(meta, str(path))
    if env is not None:
        names = ("x", "xd", "xdd", "command")
        for k, (lo, hi, bound) in enumerate(zip(env.lo, env.hi, ENVELOPE_BOUNDS, strict=True)):
            for side, v in (("lo", lo), ("hi", hi)):
                _in(path, f"meta.envelope.{side}[{k}] ({names[k]})", v, -bound, bound)


def _check_twin(model: TwinModel, path: Path | str | None) -> None:
    p = model.plant.params
    for name, bound in TWIN_BOUNDS.items():
        _in(path, f"params.{name}", getattr(p, name), -bound, bound)
    _in(path, "params.eta", p.eta, 1.0 / LAG_TAU_S[1], 1.0 / LAG_TAU_S[0], "1/s (eq. 36's lag)")
    _in(path, "offset_n", model.plant.offset_n, -MAX_OFFSET_N, MAX_OFFSET_N, "N")


@dataclass(frozen=True)
class SelfCheck:
    """What `self_check` measured: the command's mean step per frame (a share of [0, i_max])
    with the model itself as the damper and with the reference damper, the RMS error of
    tracking the model's own force over that force's RMS variation, the share of fast frames
    where more current makes more force along the motion (NaN for an inverse model), and
    the seconds it took."""

    chatter_own: float
    chatter_reference: float
    tracking_error: float
    damping_share: float
    seconds: float


class _ModelDamper:
    """The model itself as the rig's damper: `force` at this sample's motion with the command
    held since the last one (a lagged model's current through eq. 36, as the model has it)."""

    def __init__(self, model: MLP | GRUModel | TwinModel, dt_s: float, i_max: float) -> None:
        self.command = 0.0
        self._model = model
        self._tracker: TwinTracker | GruTracker | None = None
        if isinstance(model, TwinModel):
            self._tracker = model.tracker(dt_s, i_max)  # a grey-box's with its residual
        elif isinstance(model, GRUModel):
            self._tracker = GruTracker(model, dt_s, i_max)
        else:
            self._inputs = ModelInputs(model.input_names, FORWARD_INPUTS, "the self-check")
            self._inputs.reset()
            lagged = model.meta.get("current_input") == "lagged"
            tau = model.meta.get("lag_tau_s") if lagged else None
            self._lag = 1.0 if tau is None else -math.expm1(-dt_s / float(tau))
            self._u = self._prev = 0.0
            self._started = False

    def force(self, x: float, xd: float, xdd: float) -> float:
        if isinstance(self._tracker, TwinTracker):
            self._tracker.command = self.command
            return self._tracker.advance(x, xd)
        if isinstance(self._tracker, GruTracker):
            self._tracker.command = self.command
            return self._tracker.advance(x, xd, xdd)
        s = _input(x, xd, xdd, 0.0)
        if self._started:
            self._u += self._lag * (self.command - self._u)
        self._inputs.advance(s, np.array([self._prev]))
        self._started, self._prev = True, self._u
        return float(self._model.predict(self._inputs.rows(s, np.array([self._u])))[0])


class _ReferenceDamper:
    """The reference damper (the simulator's: Bouc-Wen, preset `REFERENCE_PRESET`, in A)."""

    def __init__(self, dt_s: float) -> None:
        self.command = 0.0
        self._dt_s = dt_s
        self._plant = BoucWenDamper(BoucWenParams.preset(REFERENCE_PRESET), SUBSTEP_S)
        self._started = False

    def force(self, x: float, xd: float, xdd: float) -> float:
        if not self._started:
            self._started = True
            return self._plant.reset(x, xd, 0.0)
        return self._plant.step(x, xd, self.command, self._dt_s)


def _input(x: float, xd: float, xdd: float, f_meas: float, f_des: float = 0.0) -> ControlInput:
    return ControlInput(*(np.array([v]) for v in (x, xd, xdd, f_meas, f_des)))


@dataclass(frozen=True)
class _Motion:
    """The self-check's sine (x, xd, xdd over frames + 2) and the smooth current that makes
    its desired force, inside the model's envelope (half of each range) where it has one,
    else a quarter of the rig's stroke at MOTION_HZ over [0, i_max]."""

    x: np.ndarray
    xd: np.ndarray
    xdd: np.ndarray
    current: np.ndarray
    hz: float

    @classmethod
    def of(cls, model: Any, path: Any, dt_s: float, i_max: float, x_half_m: float) -> _Motion:
        t = np.arange(SELF_CHECK_FRAMES + 2) * dt_s
        w = 2 * math.pi * MOTION_HZ
        env = None if _inverse(model) else model_envelope(model.meta, str(path))
        c, a, lo, hi = 0.0, 0.25 * x_half_m, 0.0, i_max
        if env is not None:
            c, a = 0.5 * (env.lo[0] + env.hi[0]), 0.25 * (env.hi[0] - env.lo[0])
            lo, hi = max(env.lo[3], 0.0), min(env.hi[3], i_max)
            if a > 0:
                w = min(w, 0.25 * (env.hi[1] - env.lo[1]) / a)
                w = min(w, math.sqrt(0.25 * (env.hi[2] - env.lo[2]) / a))
        current = 0.5 * (lo + hi) + 0.4 * (hi - lo) * np.sin(2 * math.pi * CURRENT_HZ * t)
        return cls(
            c + a * np.sin(w * t),
            a * w * np.cos(w * t),
            -a * w * w * np.sin(w * t),
            np.clip(current, 0.0, i_max),
            w / (2 * math.pi),
        )


def _inverse(model: Any) -> bool:
    """Whether the model is an inverse one (its output a current): no force of its own."""
    return getattr(model, "output_name", "force") == "current"


def _closed_loop(
    controller: Controller,
    m: _Motion,
    damper: _ModelDamper | _ReferenceDamper,
    make: _ModelDamper | _ReferenceDamper,
    i_max: float,
) -> tuple[float, float, float]:
    """(chatter, tracking error, damping share) of `controller` driving `damper` on the
    motion, its desired force the one `make` gives with the motion's smooth current."""
    n = SELF_CHECK_FRAMES
    f_des = np.empty(n + 2)
    for k in range(n + 2):
        f_des[k] = make.force(m.x[k], m.xd[k], m.xdd[k])
        make.command = float(m.current[k])
    controller.reset(1)
    i, f = np.zeros(n), np.zeros(n)
    damping: list[bool] = []
    fast = FAST * float(np.max(np.abs(m.xd)))
    for k in range(n):
        x, xd, xdd = m.x[k], m.xd[k], m.xdd[k]
        f[k] = damper.force(x, xd, xdd)
        v = controller.command_one(x, xd, xdd, f[k], f_des[k], f_des[k + 1])
        i[k] = min(max(v, 0.0), i_max) if math.isfinite(v) else math.nan
        if abs(xd) > fast and controller.needs_model:
            s = _input(x, xd, xdd, f[k], f_des[k])
            f_lo, f_hi = (float(controller.model_force(s, np.array([c]))[0]) for c in (0, i_max))
            if math.isfinite(f_hi - f_lo):
                damping.append(math.copysign(1.0, xd) * (f_hi - f_lo) > 0.0)
        controller.after_send()
        controller.prepare_one(m.x[k + 1], m.xd[k + 1], m.xdd[k + 1], f_des[k + 1], f_des[k + 2])
        damper.command = i[k]
        time.sleep(0)  # the GIL to the daemon's loop and bus threads between frames
    steps = np.abs(np.diff(i[SELF_CHECK_WARMUP - 1 :]))
    chatter = float(np.mean(steps)) / i_max  # NaN where a command was not finite
    want = f_des[SELF_CHECK_WARMUP:n]
    spread = max(float(np.std(want)), 1e-9)
    err = float(np.sqrt(np.mean((f[SELF_CHECK_WARMUP:] - want) ** 2))) / spread
    return chatter, err, float(np.mean(damping)) if damping else math.nan


def self_check(
    controller: Controller,
    model: MLP | GRUModel | TwinModel,
    path: Path | str | None,
    dt_s: float,
    i_max: float,
    x_half_m: float,
) -> SelfCheck:
    """Run `controller` (a spare: its state is spent) in closed loop on the model's own
    motion (module docstring): with the model itself as the damper (a forward model) and with
    the reference damper. ModelError where its command chatters, it cannot track its own
    force, or the model's force does not grow with the current along the motion."""
    t0 = time.perf_counter()
    m = _Motion.of(model, path, dt_s, i_max, x_half_m)
    chatter_own = err = damps = math.nan
    if not _inverse(model):
        own = _ModelDamper(model, dt_s, i_max), _ModelDamper(model, dt_s, i_max)
        chatter_own, err, damps = _closed_loop(controller, m, *own, i_max)
    ref = _ReferenceDamper(dt_s), _ReferenceDamper(dt_s)
    chatter_ref = _closed_loop(controller, m, *ref, i_max)[0]
    result = SelfCheck(chatter_own, chatter_ref, err, damps, time.perf_counter() - t0)
    what = (
        f"{path}: self-check ({SELF_CHECK_FRAMES} frames of a {m.hz:.2g} Hz sine inside the"
        f" model's envelope)"
    )
    untrained = "not a model of a damper (untrained?)"
    checks = (
        ("the model itself", chatter_own, MAX_CHATTER),
        ("the reference", chatter_ref, MAX_CHATTER_REFERENCE),
    )
    for damper, chatter, most in checks:
        if not chatter <= most and not (math.isnan(chatter) and _inverse(model)):
            raise ModelError(
                f"{what}: with {damper} as the damper, the {controller.name} controller's "
                f"command moved {chatter:.1%} of [0, {i_max:g}] A per frame on average (at most"
                f" {most:.0%}: it jumps between the rails): {untrained}"
            )
    if not _inverse(model) and not err <= MAX_TRACKING_ERROR:
        raise ModelError(
            f"{what}: cannot track the model's own force: RMS error {err:.2f} of its RMS "
            f"variation (at most {MAX_TRACKING_ERROR:g}): {untrained}"
        )
    if not _inverse(model) and not damps >= MIN_DAMPING_SHARE:
        raise ModelError(
            f"{what}: more current makes more force along the motion on {damps:.0%} of the "
            f"fast frames (a damper's does on at least {MIN_DAMPING_SHARE:.0%}): {untrained}"
        )
    return result
