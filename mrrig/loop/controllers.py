"""Damper controllers behind one interface (mrrig/loop/controller_base.py): given the estimate
and the desired force, a current. The registry (`make_controller`, by name), the open-loop and
the paper's controllers, and network inversion (its stateful forward models' solves:
mrrig/loop/state_inversion.py).
"""

from __future__ import annotations

import math

import numpy as np

from mrrig.loop.adaptation import AdaptationSettings, GainOffsetRLS
from mrrig.loop.controller_base import (
    FORWARD_INPUTS,
    INVERSION_METHODS,
    SUPERVISED_INPUTS,
    ControlInput,
    Controller,
    ControllerSettings,
    ModelInputs,
)
from mrrig.loop.gru import GRUModel
from mrrig.loop.inversion import (
    DEFAULT_CONTINUITY,
    ScalarInverter,
    exact_inversion,
    flow_inversion,
    gradient_inversion,
)
from mrrig.loop.mlp import MLP
from mrrig.loop.state_inversion import GruInversion, TwinInversion
from mrrig.loop.twin_model import TwinModel

CONTROLLERS: dict[str, type[Controller]] = {}


def register(cls: type[Controller]) -> type[Controller]:
    """Class decorator: the controller is known by its `name` to the daemon's config, the
    `set_controller` request and `mrrig bench paper`."""
    CONTROLLERS[cls.name] = cls
    return cls


def make_controller(name: str, settings: ControllerSettings) -> Controller:
    """The registered controller `name` built from `settings`; ValueError (one line) for an
    unknown name or settings that do not fit it."""
    cls = CONTROLLERS.get(name)
    if cls is None:
        raise ValueError(f"unknown controller {name!r} (known: {', '.join(CONTROLLERS)})")
    if cls.needs_model and settings.model is None:
        raise ValueError(f"controller {name} needs a model")
    return cls.build(settings)


@register
class ConstantCurrent(Controller):
    """Open loop: the same current all the time."""

    name = "constant"
    controller_id = 6

    @classmethod
    def build(cls, s: ControllerSettings) -> Controller:
        return cls(s.i_max, s.current_a)

    def __init__(self, i_max: float, current: float) -> None:
        super().__init__(i_max)
        if not 0.0 <= current <= i_max:
            raise ValueError(f"current {current} A outside [0, {i_max}] A")
        self.current = float(current)

    def command(self, s: ControlInput) -> np.ndarray:
        return np.full(np.shape(s.f_des), self.current)


@register
class ReferenceCurrent(Controller):
    """The ideal controller of a reference damper: its own current, open loop (the floor)."""

    # The current a `bouc_wen` or `paper_case` reference damper is driven with over the
    # period the command acts on (`ForceReference.current_at`, given by the daemon's frame
    # before each command: `follow`): the plant then makes the desired force but for the
    # measurement chain (the estimate's motion, the load cell, the bus and the coil). Its Et
    # is the floor a plan prints beside another controller's (a step's `floor_of`). A
    # reference without a current of its own gives NaN: the daemon refuses to arm on one.
    name = "reference_current"
    controller_id = 6  # an open-loop current: the DBC's CONSTANT_CURRENT
    follows_reference = True

    def reset(self, batch: int = 1) -> None:
        super().reset(batch)
        self._current = math.nan

    def follow(self, current_a: float) -> None:
        """The reference damper's current over the coming period."""
        self._current = current_a

    def command(self, s: ControlInput) -> np.ndarray:
        return np.full(np.shape(s.f_des), min(max(self._current, 0.0), self.i_max))


@register
class Heaviside(Controller):
    """Dyke et al. (1996): full or no current by the sign of (f_d - f_a) f_a (eqs 37-38)."""

    name = "heaviside"
    controller_id = 2

    @classmethod
    def build(cls, s: ControllerSettings) -> Controller:
        return cls(s.i_max, s.on_current_a)

    def __init__(self, i_max: float, on_current_a: float | None = None) -> None:
        super().__init__(i_max)
        on = self.i_max if on_current_a is None else float(on_current_a)
        if not 0 < on <= self.i_max:
            raise ValueError(f"on_current_a: {on:g} A is outside (0, {self.i_max:g}] A")
        self.on_current_a = on

    def reset(self, batch: int = 1) -> None:
        super().reset(batch)
        self._held = np.zeros(batch)

    def command(self, s: ControlInput) -> np.ndarray:
        prod = (s.f_des - s.f_meas) * s.f_meas
        # eq. 37-38; held at its previous value when the product is exactly 0
        self._held = np.where(prod > 0, self.on_current_a, np.where(prod < 0, 0.0, self._held))
        return self._held.copy()


@register
class ContinuousState(Controller):
    """Sims et al. (1999): v = clip(G (f_d - B f_a) sgn(f_a), 0, Vmax) (eq. 39)."""

    name = "continuous_state"
    controller_id = 3

    @classmethod
    def build(cls, s: ControllerSettings) -> Controller:
        return cls(s.i_max, s.gain, s.b)

    def __init__(self, i_max: float, gain: float = 0.021, b: float = 1.0) -> None:
        super().__init__(i_max)
        if not (math.isfinite(gain) and gain > 0):
            raise ValueError(f"gain: {gain!r} must be a positive number (A/N)")
        if not (math.isfinite(b) and b > 0):
            raise ValueError(f"b: {b!r} must be a positive number")
        self.gain = gain
        self.b = b

    def command(self, s: ControlInput) -> np.ndarray:
        v = self.gain * (s.f_des - self.b * s.f_meas) * np.sign(s.f_meas)  # eq. 39
        return np.clip(v, 0.0, self.i_max)


@register
class NetworkInversion(Controller):
    """The paper's inverse model: solve the frozen forward network for the current.

    `method="exact"` (default) is the bracketed safeguarded-Newton scalar solve;
    `method="gradient"` is the paper's eq. 2/14 gradient descent, kept as the reference;
    `method="flow"` is that descent's end point in a few steps (`flow_inversion`).
    `continuity` is the exact solve's weight mu toward the previous command
    (mrrig/loop/inversion.py; default 0 = the root itself; 1 = the smoothing of the paper's
    on-line gradient method).
    With `feedback_tau_s` set, the load cell corrects the model online: the residual
    r = f_meas - f_net(state, current now) is low-passed with that time constant and the
    network is solved for f_des - r, so a steady model error does not become tracking error;
    `feedback_tau_s=0` takes the last residual as it is (incremental inversion: the network
    supplies only how the force changes with the current and the motion).

    A model trained on the lagged current (meta `current_input = "lagged"`, `lag_tau_s`:
    mrrig/offline/training/) is solved for the lagged current u at the next instant, and the
    command is the one that takes u there within one period (eq. 36 inverted, below); u is
    tracked from the commands themselves (the current now of the feedback residual; for
    other models the current now is the previous command). `ahead=True` solves for the
    instant the command first acts on: the state one period ahead (the Kalman filter's
    constant-acceleration model, eq. 21), `ControlInput.f_des_next` and the feedback
    residual extrapolated at its last rate of change; without `f_des_next` it solves for the
    present instant. Not with history inputs.

    A forward model with history inputs (`FORWARD_INPUTS` then e.g. x_1, xd_1: `ModelInputs`)
    gets them from the past instants of each lane, past currents being its own commands;
    the unknown is still the present current alone, a scalar solve.

    With `adaptation` (mrrig/loop/adaptation.py), the model's force is gain * f_net + offset,
    estimated from the load cell in `after_send`; the residual is taken against that force and
    the network is solved for (target - offset) / gain. The adaptation survives `reset` (a
    re-arm: the damper is still the one it adapted to); `reset_adaptation` starts it over.
    Without it the arithmetic is that of the controller without adaptation, bit for bit.
    """

    name = "network_inversion"
    controller_id = 1
    needs_model = True

    @classmethod
    def build(cls, s: ControllerSettings) -> Controller:
        if isinstance(s.model, TwinModel):  # a plant file: the Bouc-Wen twin is the model
            return TwinInversion.build(s)
        if isinstance(s.model, GRUModel):  # a recurrent forward model
            return GruInversion.build(s)
        return cls(
            s.i_max,
            s.model,
            method=s.method,
            feedback_tau_s=s.feedback_tau_s,
            dt_s=s.dt_s,
            gradient_iterations=s.gradient_iterations,
            seed=s.seed,
            continuity=s.continuity,
            ahead=s.ahead,
            adaptation=s.adaptation,
        )

    def __init__(
        self,
        i_max: float,
        model: MLP,
        method: str = "exact",
        feedback_tau_s: float | None = None,
        dt_s: float = 0.002,
        gradient_rate: float = 1e-3,
        gradient_iterations: int = 1000,
        seed: int = 0,
        continuity: float = DEFAULT_CONTINUITY,
        ahead: bool = False,
        adaptation: AdaptationSettings | None = None,
    ) -> None:
        super().__init__(i_max)
        self._inputs = self._forward_inputs(model)
        if method not in INVERSION_METHODS:
            raise ValueError(
                f"unknown inversion method {method!r} ({', '.join(INVERSION_METHODS)})"
            )
        if feedback_tau_s is not None and not feedback_tau_s >= 0:
            raise ValueError(f"feedback_tau_s must be >= 0, got {feedback_tau_s}")
        if ahead and self._inputs.samples:
            raise ValueError("the one-step-ahead solve needs a model without history inputs")
        self.ahead = ahead
        self.wants_next_target = ahead
        self.adapt = None if adaptation is None else GainOffsetRLS(adaptation, dt_s)
        self.lag_tau_s = self._lag_tau_s(model)
        # the share of a step of the command that the lagged current makes in one period:
        # u(k+1) = u(k) + lag (v(k) - u(k)), eq. 36 solved exactly for v held over the period
        self._lag = None if self.lag_tau_s is None else -math.expm1(-dt_s / self.lag_tau_s)
        self.model = model
        self.method = method
        self.feedback_tau_s = feedback_tau_s
        self.dt_s = dt_s
        self.gradient_rate = gradient_rate
        self.gradient_iterations = gradient_iterations
        self._rng = np.random.default_rng(seed)
        self.continuity = continuity
        self._scalar = ScalarInverter(model, i_max, continuity=continuity)
        self._feat = np.empty(model.n_in - 1)  # the float path's features, reused
        self._feat_ahead = np.empty(model.n_in - 1)
        self._feat_next = np.empty(model.n_in - 1)  # the solved instant's (one step ahead)
        self._feat_model = np.empty(model.n_in - 1)  # the frame's sample (`model_force_one`)

    @staticmethod
    def _forward_inputs(model: MLP) -> ModelInputs:
        """The model's inputs: `FORWARD_INPUTS`, then any history inputs; ValueError if not."""
        if model.output_name != "force":
            raise ValueError(
                f"network inversion needs a forward model (output force), got output "
                f"{model.output_name!r}"
            )
        return ModelInputs(model.input_names, FORWARD_INPUTS, "network inversion")

    @staticmethod
    def _lag_tau_s(model: MLP) -> float | None:
        """The coil lag the model's current input went through (None: the command itself)."""
        if model.meta.get("current_input", "commanded") != "lagged":
            return None
        tau = model.meta.get("lag_tau_s")
        if not (isinstance(tau, int | float) and tau > 0):
            raise ValueError(f"a model of the lagged current needs lag_tau_s > 0, got {tau!r}")
        return float(tau)

    def reset(self, batch: int = 1) -> None:
        super().reset(batch)
        self._prev = np.zeros(batch)
        self._u = np.zeros(batch)  # the lagged current now (models of the lagged current)
        self._residual = np.zeros(batch)
        self._first = True
        self._inputs.reset()
        self._scalar.discard_prepared()
        # the instant just commanded, for `after_send`: the network's force then, the load cell
        self._f_net_now: np.ndarray | None = None
        self._f_meas_now = np.zeros(batch)
        if self.adapt is not None and self.adapt.theta.shape[0] != batch:
            self.adapt.reset(batch)

    def _features(self, s: ControlInput, current: np.ndarray) -> np.ndarray:
        return self._inputs.rows(s, current)

    def _state(self, s: ControlInput) -> np.ndarray:
        """The model's inputs without the current (history included), in the model's order."""
        return self._inputs.rows(s)

    def model_force(self, s: ControlInput, current: np.ndarray) -> np.ndarray:
        f = self.model.predict(self._features(s, np.asarray(current, dtype=float)))
        return f if self.adapt is None else self.adapt.force(f)

    def model_force_one(
        self, x: float, xd: float, xdd: float, f_meas: float, f_des: float, current_a: float
    ) -> float:
        """The network's one-sample force (`ScalarInverter.force`: no arrays built), adapted;
        a model with history inputs as `model_force`."""
        if self._inputs.samples or self.batch != 1:
            return self._model_force_arrays(x, xd, xdd, f_meas, f_des, current_a)
        feat = self._feat_model
        feat[0], feat[1], feat[2] = x, xd, xdd
        f = self._scalar.force(feat, current_a)
        if self.adapt is None:
            return f
        return float(self.adapt.force(f)[0])

    def after_send(self) -> None:
        if self.adapt is not None and self._f_net_now is not None:
            self.adapt.update(self._f_net_now, self._f_meas_now)
            self._f_net_now = None

    def adaptation_state(self) -> dict | None:
        return None if self.adapt is None else self.adapt.state()

    def command_sent(self, current_a: float) -> None:
        self._prev[0] = current_a

    def _net_target(self, target: np.ndarray) -> np.ndarray:
        """The network's force that makes the adapted force `target`."""
        if self.adapt is None:
            return target
        return (target - self.adapt.offset_n) / self.adapt.gain

    def solved_ahead(self) -> tuple[int, int]:
        return self._scalar.ahead_used, self._scalar.ahead_missed

    def _solved_instant(self, s: ControlInput) -> ControlInput:
        """The instant the command is solved for: with `ahead` and a known next target, one
        period ahead (the state at constant acceleration, eq. 21); else the present one."""
        if not self.ahead or s.f_des_next is None:
            return s
        T = self.dt_s
        return ControlInput(
            x=s.x + s.xd * T + 0.5 * s.xdd * T * T,
            xd=s.xd + s.xdd * T,
            xdd=s.xdd,
            f_meas=s.f_meas,
            f_des=s.f_des_next,
        )

    def command(self, s: ControlInput) -> np.ndarray:
        lag = self._lag
        self._inputs.advance(s, self._prev if lag is None else self._u)
        if lag is not None:
            self._u = self._u + lag * (self._prev - self._u)  # eq. 36, the held command
        now = self._prev if lag is None else self._u  # what the model's current input is now
        residual = 0.0
        if self.adapt is not None:
            f_net = self.model.predict(self._features(s, now))
            # the first instant's force answers no command of this run: nothing to learn
            self._f_net_now = None if self._first else f_net
            self._f_meas_now = np.array(s.f_meas, dtype=float)
        if self.feedback_tau_s is not None:
            a = self.dt_s / (self.feedback_tau_s + self.dt_s)
            last = self._residual.copy()
            f_model = self.model_force(s, now) if self.adapt is None else self.adapt.force(f_net)
            self._residual += a * (s.f_meas - f_model - self._residual)
            residual = self._residual
        solve_at = self._solved_instant(s)
        if solve_at is not s and self.feedback_tau_s is not None and not self._first:
            # the residual at the solved instant, one period on, at its last rate of change
            residual = 2.0 * self._residual - last
        target = self._net_target(solve_at.f_des - residual)
        if self.method == "gradient":
            # the paper's on-line inverse estimation: a random initial current, then each
            # sample's descent starts from the current now
            i = gradient_inversion(
                self.model,
                self._state(solve_at),
                target,
                i_max=self.i_max,
                rate=self.gradient_rate,
                iterations=self.gradient_iterations,
                i0=None if self._first else now,
                rng=self._rng,
            )
        elif self.method == "flow":
            i = flow_inversion(
                self.model,
                self._state(solve_at),
                target,
                i_max=self.i_max,
                duration=self.gradient_rate * self.gradient_iterations,
                i0=None if self._first else now,
                rng=self._rng,
            )
        elif self.batch == 1:
            i = np.array([self._scalar.solve(self._state(solve_at)[0], float(target[0]), now[0])])
        else:
            i = exact_inversion(
                self.model,
                self._state(solve_at),
                target,
                now,
                i_max=self.i_max,
                continuity=self.continuity,
            )
        if lag is not None:
            i = now + (i - now) / lag  # eq. 36 inverted: u reaches i one period on
        self._prev = np.clip(i, 0.0, self.i_max)
        self._first = False
        return self._prev.copy()

    def command_one(
        self,
        x: float,
        xd: float,
        xdd: float,
        f_meas: float,
        f_des: float,
        f_des_next: float | None = None,
    ) -> float:
        """The float path of `command` for one lane (exact or flow method, no history inputs):
        the same arithmetic without building arrays, for the real-time loop."""
        if self.method == "gradient" or self._inputs.samples or self.batch != 1:
            return super().command_one(x, xd, xdd, f_meas, f_des, f_des_next)
        feat = self._feat
        feat[0], feat[1], feat[2] = x, xd, xdd
        lag = self._lag
        now = float(self._prev[0])
        if lag is not None:
            u = float(self._u[0])
            now = u + lag * (now - u)  # eq. 36, the held command
            self._u[0] = now
        ahead = self.ahead and f_des_next is not None
        target = f_des_next if ahead else f_des
        adapt = self.adapt
        if self.feedback_tau_s is not None or adapt is not None:
            f_model = self._scalar.force(feat, now)
            if adapt is not None:
                # the first instant's force answers no command of this run: nothing to learn
                self._f_net_now = None if self._first else np.array([f_model])
                self._f_meas_now = np.array([f_meas])
                f_model = adapt.gain0 * f_model + adapt.offset0_n
        if self.feedback_tau_s is not None:
            a = self.dt_s / (self.feedback_tau_s + self.dt_s)
            last = r = float(self._residual[0])
            r += a * (f_meas - f_model - r)
            self._residual[0] = r
            if ahead and not self._first:
                r = 2.0 * r - last  # at the solved instant, at its last rate of change
            target = target - r
        if adapt is not None:
            target = (target - adapt.offset0_n) / adapt.gain0
        if ahead:
            # the instant the command first acts on: one period on at constant acceleration
            # (eq. 21), as `_solved_instant`
            T = self.dt_s
            feat = self._feat_next
            feat[0], feat[1], feat[2] = x + xd * T + 0.5 * xdd * T * T, xd + xdd * T, xdd
        if self.method == "flow":
            i0 = self._rng.uniform(0.0, self.i_max, 1)[0] if self._first else now
            duration = self.gradient_rate * self.gradient_iterations
            i = self._scalar.flow(feat, target, float(i0), duration)
        else:
            i = self._scalar.solve(feat, target, now)
        if lag is not None:
            i = now + (i - now) / lag  # eq. 36 inverted
        i = min(max(i, 0.0), self.i_max)
        self._prev[0] = i
        self._first = False
        return i

    def prepare_one(
        self, x: float, xd: float, xdd: float, f_des: float, f_des_next: float | None = None
    ) -> None:
        """Solve ahead on the predicted state (`ScalarInverter.prepare`), with the present
        load-cell correction (and adaptation) as the predicted one; the float path's cases
        only. One step ahead, on the state a period after the predicted one, for `f_des_next`."""
        if self.method != "exact" or self._inputs.samples or self.batch != 1:
            return
        feat = self._feat_ahead
        ahead = self.ahead and f_des_next is not None
        if ahead:
            T = self.dt_s
            x, xd = x + xd * T + 0.5 * xdd * T * T, xd + xdd * T
            f_des = f_des_next
        feat[0], feat[1], feat[2] = x, xd, xdd
        now = float(self._prev[0])  # what command_one will solve from
        if self._lag is not None:
            u = float(self._u[0])
            now = u + self._lag * (now - u)  # eq. 36, the held command
        target = f_des
        if self.feedback_tau_s is not None:
            target = f_des - float(self._residual[0])
        if self.adapt is not None:
            target = (target - self.adapt.offset0_n) / self.adapt.gain0
        self._scalar.prepare(feat, target, now)


@register
class SupervisedInverse(Controller):
    """Direct inverse MLP (x, xd, xdd, f_des) -> current, trained by supervised learning.

    The model may have history inputs of the motion (x_1, xd_1, ...: `ModelInputs`), not of
    the current: its past outputs would feed back into it.
    """

    name = "supervised"
    controller_id = 4
    needs_model = True

    @classmethod
    def build(cls, s: ControllerSettings) -> Controller:
        return cls(s.i_max, s.model)

    def __init__(self, i_max: float, model: MLP) -> None:
        super().__init__(i_max)
        if model.output_name != "current":
            raise ValueError(
                f"the supervised inverse needs a model with output current, got output "
                f"{model.output_name!r}"
            )
        self._inputs = ModelInputs(model.input_names, SUPERVISED_INPUTS, "the supervised inverse")
        if "current" in self._inputs.signals:
            raise ValueError("the supervised inverse takes no past currents as inputs")
        self.model = model

    def reset(self, batch: int = 1) -> None:
        super().reset(batch)
        self._inputs.reset()

    def command(self, s: ControlInput) -> np.ndarray:
        self._inputs.advance(s, np.zeros(np.shape(s.x)))
        return np.clip(self.model.predict(self._inputs.rows(s)), 0.0, self.i_max)


RNN_INPUTS = ("f_des", "f_des_1", "x", "x_1") + tuple(f"v_{k}" for k in range(1, 7))


def rnn_features(f: np.ndarray, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Training rows of the RNN of paper eq. 40 from a series: target v[k] for k >= 6.

    Inputs per row: f(k), f(k-1), x(k), x(k-1), v(k-1) ... v(k-6); the command fed back is the
    network's own previous output in closed loop (the "recurrent" part).
    """
    k = np.arange(6, len(f))
    cols = [f[k], f[k - 1], x[k], x[k - 1]] + [v[k - j] for j in range(1, 7)]
    return np.stack(cols, axis=-1)


@register
class RecurrentInverse(Controller):
    """Wang & Liao (2005) RNN (paper eq. 40): the previous six commands are fed back."""

    name = "rnn"
    controller_id = 5
    needs_model = True

    @classmethod
    def build(cls, s: ControllerSettings) -> Controller:
        return cls(s.i_max, s.model)

    def __init__(self, i_max: float, model: MLP) -> None:
        super().__init__(i_max)
        if tuple(model.input_names) != RNN_INPUTS or model.output_name != "current":
            raise ValueError(f"RNN controller needs inputs {RNN_INPUTS}, got {model.input_names}")
        self.model = model

    def reset(self, batch: int = 1) -> None:
        super().reset(batch)
        self._v = np.zeros((batch, 6))
        self._f_prev: np.ndarray | None = None
        self._x_prev: np.ndarray | None = None

    def command(self, s: ControlInput) -> np.ndarray:
        f_prev = s.f_des if self._f_prev is None else self._f_prev
        x_prev = s.x if self._x_prev is None else self._x_prev
        X = np.column_stack([s.f_des, f_prev, s.x, x_prev, self._v])  # eq. 40
        v = np.clip(self.model.predict(X), 0.0, self.i_max)
        self._v = np.column_stack([v, self._v[:, :-1]])
        self._f_prev, self._x_prev = s.f_des, s.x
        return v


CONTROLLER_NAMES = tuple(CONTROLLERS)
