"""Damper controllers behind one interface: given the estimate and the desired force, a current.

Every controller works on a batch: the fields of `ControlInput` are arrays of shape (B,) (B = 1
in the rig daemon, B = 7 in `mrrig bench paper`, which runs the seven validation cases at once),
and `command` returns the current (or, in the paper's simulation, the voltage) of shape (B,),
already clamped to [0, i_max]. Controllers are pure numerics: they know nothing of CAN or Zenoh.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mrrig.loop.adaptation import AdaptationSettings, GainOffsetRLS
from mrrig.loop.gru import GRUModel, GruTracker
from mrrig.loop.inversion import (
    DEFAULT_CONTINUITY,
    ScalarInverter,
    exact_inversion,
    flow_inversion,
    gradient_inversion,
)
from mrrig.loop.mlp import MLP
from mrrig.loop.twin_model import TwinModel

FORWARD_INPUTS = ("x", "xd", "xdd", "current")
INVERSION_METHODS = ("exact", "gradient", "flow")  # NetworkInversion's (mrrig/loop/inversion.py)
SUPERVISED_INPUTS = ("x", "xd", "xdd", "f_des")
HISTORY_SIGNALS = ("x", "xd", "xdd", "current")  # what a history input may be a past sample of


def history_input_names(samples: int, signals: Sequence[str]) -> tuple[str, ...]:
    """History input names, `SIGNAL_K` = SIGNAL K samples back, newest first: 2 samples of
    (x, xd) are (x_1, xd_1, x_2, xd_2). Units are those of the signal."""
    return tuple(f"{sig}_{k}" for k in range(1, samples + 1) for sig in signals)


def parse_history_input(name: str) -> tuple[str, int]:
    """(signal, samples back) of a history input name; a one-line ValueError for anything else."""
    sig, sep, k = name.rpartition("_")
    if sep and sig in HISTORY_SIGNALS and k.isascii() and k.isdigit() and not k.startswith("0"):
        return sig, int(k)
    raise ValueError(
        f"input {name!r} is not a history input SIGNAL_K "
        f"(SIGNAL one of {', '.join(HISTORY_SIGNALS)}, K >= 1 samples back)"
    )


@dataclass
class ControlInput:
    """One control instant: the state estimate, the load cell and the target (arrays (B,))."""

    x: np.ndarray  # displacement, m
    xd: np.ndarray  # velocity, m/s
    xdd: np.ndarray  # acceleration, m/s^2
    f_meas: np.ndarray  # measured (load-cell) force, N
    f_des: np.ndarray  # desired force, N
    # the desired force one period ahead, where the reference is known ahead (None: it is not)
    f_des_next: np.ndarray | None = None


@dataclass(frozen=True)
class ControllerSettings:
    """Everything a controller of the registry may be built from; each takes what it needs
    (`Controller.build`). The daemon makes it from its config's [controller] section,
    `mrrig bench paper` directly."""

    i_max: float
    dt_s: float = 0.002
    model: MLP | None = None
    method: str = "exact"  # network inversion's solve: INVERSION_METHODS
    feedback_tau_s: float | None = None
    continuity: float = DEFAULT_CONTINUITY
    ahead: bool = False  # network inversion for the instant the command acts on
    adaptation: AdaptationSettings | None = (
        None  # on-line gain and offset (mrrig/loop/adaptation.py)
    )
    current_a: float = 0.0  # the constant controller's
    gain: float = 0.021  # continuous state's G, A/N (eq. 39)
    b: float = 1.0  # continuous state's B (eq. 39)
    on_current_a: float | None = None  # Heaviside's current when on (eq. 37); None: i_max
    gradient_iterations: int = 1000
    seed: int = 0


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


class Controller(abc.ABC):
    """A damper controller: `reset()` before a run, then `command()` once per sample."""

    name: str = ""
    controller_id: int = 0  # DamperCommand.ControllerId (spec/can-protocol.md)
    needs_model = False
    # whether `command_one` uses the desired force one period ahead (`f_des_next`)
    wants_next_target = False
    # whether it commands the force reference's own current (`follow`, before each command)
    follows_reference = False

    @classmethod
    def build(cls, s: ControllerSettings) -> Controller:
        """From the registry's settings (`make_controller`); most need the limit alone."""
        return cls(s.i_max)

    def __init__(self, i_max: float) -> None:
        if not i_max > 0:
            raise ValueError(f"i_max must be positive, got {i_max}")
        self.i_max = float(i_max)
        self.batch = 1

    def reset(self, batch: int = 1) -> None:
        """Forget all history; the next `command` is the first of a run of `batch` lanes."""
        self.batch = batch

    @abc.abstractmethod
    def command(self, s: ControlInput) -> np.ndarray:
        """The command for this instant, clamped to [0, i_max]."""

    def command_one(
        self,
        x: float,
        xd: float,
        xdd: float,
        f_meas: float,
        f_des: float,
        f_des_next: float | None = None,
    ) -> float:
        """`command` for a batch of one lane, in plain floats (the daemon's loop). The same
        result and state; controllers override it where a float path is cheaper."""
        s = ControlInput(
            np.array([x]),
            np.array([xd]),
            np.array([xdd]),
            np.array([f_meas]),
            np.array([f_des]),
            None if f_des_next is None else np.array([f_des_next]),
        )
        return float(self.command(s)[0])

    def after_send(self) -> None:  # noqa: B027 - most controllers learn nothing on-line
        """Learn from the instant just commanded (on-line adaptation), once its command has
        gone out: off the latency path. The daemon calls it only while armed and without a
        fault in that frame."""

    def adaptation_state(self) -> dict | None:
        """The on-line adaptation's state (None: the controller has none)."""
        return None

    def command_sent(self, current_a: float) -> None:  # noqa: B027 - most carry no command
        """The command sent for this instant was `current_a`, not the one `command_one`
        returned (the loop's slew limit moved it): a controller that carries the command
        held (the coil's lag, a twin's or a GRU's state) carries this one."""

    def follow_motion(self, x: float, xd: float) -> None:  # noqa: B027 - most keep no state
        """A disarmed frame's estimated motion (the rig holds the coil at 0 A): a controller
        whose model carries the damper's state (a twin's) moves it on, to arm on it."""

    def prepare_one(  # noqa: B027
        self, x: float, xd: float, xdd: float, f_des: float, f_des_next: float | None = None
    ) -> None:
        """Work ahead for the next `command_one`, from a predicted state and target (the
        daemon calls it after it has answered a frame, while it waits for the next one). It
        changes no result beyond the solver's tolerance; most controllers have nothing to do."""

    def solved_ahead(self) -> tuple[int, int]:
        """(commands whose work `prepare_one` saved, prepared commands that needed it all)."""
        return 0, 0

    def model_force(self, s: ControlInput, current: np.ndarray) -> np.ndarray:
        """The forward model's force for `current` (NaN for controllers without one)."""
        return np.full_like(np.asarray(current, dtype=float), np.nan)

    def model_force_one(
        self, x: float, xd: float, xdd: float, f_meas: float, f_des: float, current_a: float
    ) -> float:
        """`model_force` for one lane in plain floats (the daemon's sample of each frame); the
        controllers with a model override it."""
        return math.nan

    def _model_force_arrays(
        self, x: float, xd: float, xdd: float, f_meas: float, f_des: float, current_a: float
    ) -> float:
        """`model_force_one` through `model_force` (arrays of one lane)."""
        s = ControlInput(
            np.array([x]), np.array([xd]), np.array([xdd]), np.array([f_meas]), np.array([f_des])
        )
        return float(self.model_force(s, np.array([current_a]))[0])


class ModelInputs:
    """A model's input rows at each control instant, history inputs included.

    The model's inputs must be `present` (this instant's values, in that order) followed by
    history inputs `SIGNAL_K` (`history_input_names`, any order). Per lane it keeps the last
    K instants that the history inputs need. `advance(s, prev_command)` once per instant,
    before that instant's rows: it files the previous instant, with `prev_command` (the
    command made for it) as its current, and makes `s` the present one. Until K instants
    have been seen after `reset()`, the missing past ones are the first instant (at the first
    instant, the present one itself), with the past command 0 A (the command before a run).
    """

    def __init__(self, names: Sequence[str], present: tuple[str, ...], what: str) -> None:
        names = tuple(names)
        n = len(present)
        if names[:n] != present:
            raise ValueError(
                f"{what} needs a model whose inputs start with {', '.join(present)} (then "
                f"history inputs such as x_1, xd_1), got {', '.join(names)}"
            )
        history = []
        for name in names[n:]:
            try:
                history.append(parse_history_input(name))
            except ValueError as exc:
                raise ValueError(f"{what}: {exc}") from None
        self.signals = tuple(dict.fromkeys(sig for sig, _ in history))
        self.samples = max((k for _, k in history), default=0)
        self.present = present
        # history column j of a row = ring[lane, k - 1, signal index], flattened
        self._take = np.array(
            [(k - 1) * len(self.signals) + self.signals.index(sig) for sig, k in history],
            dtype=int,
        )
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next instant is the first of a run."""
        self._ring: np.ndarray | None = None  # (lanes, samples, signals), newest first
        self._last: np.ndarray | None = None  # the present instant's signals (lanes, signals)

    def _now(self, s: ControlInput) -> np.ndarray:
        """The history signals of instant `s` (lanes, signals); its current, not known yet, is
        0 A until `advance` files the instant with the command made for it."""
        values = {"x": s.x, "xd": s.xd, "xdd": s.xdd, "current": np.zeros(np.shape(s.x))}
        return np.stack([values[sig] for sig in self.signals], axis=-1)

    def _filled(self, s: ControlInput) -> np.ndarray:
        """A ring whose every past instant is `s` (the start of a run)."""
        return np.repeat(self._now(s)[:, None, :], self.samples, axis=1)

    def advance(self, s: ControlInput, prev_command: np.ndarray) -> None:
        """Make `s` the present instant; `prev_command` was the command for the previous one."""
        if self.samples == 0:
            return
        if self._ring is None or self._last is None:
            self._ring = self._filled(s)
        else:
            self._ring[:, 1:] = self._ring[:, :-1]
            self._ring[:, 0] = self._last
            if "current" in self.signals:
                self._ring[:, 0, self.signals.index("current")] = prev_command
        self._last = self._now(s)

    def rows(self, s: ControlInput, current: np.ndarray | None = None) -> np.ndarray:
        """Input rows (B, n) in the model's order; without the current column if current is
        None (the inversion's features). Before the first `advance`, the history is `s`."""
        values = {"x": s.x, "xd": s.xd, "xdd": s.xdd, "f_des": s.f_des, "current": current}
        cols = [values[name] for name in self.present if values[name] is not None]
        if self.samples == 0:
            return np.stack(cols, axis=-1)
        ring = self._filled(s) if self._ring is None else self._ring
        past = ring.reshape(ring.shape[0], -1)[:, self._take]
        return np.concatenate([np.stack(cols, axis=-1), past], axis=-1)


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


class TwinInversion(Controller):
    """Network inversion with a Bouc-Wen twin (a plant file of `mrrig identify`) as the
    forward model: the twin's state carried frame to frame on the estimated motion and the
    commands sent, eq. 30 solved for the command through eq. 36's lag
    (mrrig/loop/twin_model.py). The load-cell feedback and the one-step-ahead solve as
    `NetworkInversion`'s; the solve is exact, without adaptation. Built by network_inversion
    for a twin model."""

    name = "network_inversion"
    controller_id = 1
    needs_model = True
    # network inversion's settings, as this solve has them: exact (the continuity: the pull
    # toward the present lagged current, `TwinTracker.solve`)
    method = "exact"

    @classmethod
    def build(cls, s: ControllerSettings) -> Controller:
        if s.method != "exact":
            raise ValueError(f"method {s.method!r}: a twin forward model is solved exactly")
        if s.adaptation is not None:
            raise ValueError("adaptation: not with a twin forward model (its force is eq. 30)")
        assert isinstance(s.model, TwinModel)
        return cls(s.i_max, s.model, s.dt_s, s.feedback_tau_s, s.ahead, s.continuity)

    def __init__(
        self,
        i_max: float,
        model: TwinModel,
        dt_s: float = 0.002,
        feedback_tau_s: float | None = None,
        ahead: bool = False,
        continuity: float = 0.0,
    ) -> None:
        super().__init__(i_max)
        if feedback_tau_s is not None and not feedback_tau_s >= 0:
            raise ValueError(f"feedback_tau_s must be >= 0, got {feedback_tau_s}")
        self.continuity = continuity
        self.model = model
        self.dt_s = dt_s
        self.feedback_tau_s = feedback_tau_s
        self.ahead = ahead
        self.wants_next_target = ahead
        self.reset(1)

    def reset(self, batch: int = 1) -> None:
        """A new run: the load-cell residual starts again; the twins keep the state the motion
        gave them (`follow_motion` while disarmed: the damper is the one that moved), where
        the lanes are as many; a twin not yet moved starts at rest at its first frame."""
        super().reset(batch)
        lanes = getattr(self, "lanes", [])
        if len(lanes) != batch:
            self.lanes = [
                self.model.tracker(self.dt_s, self.i_max, self.continuity) for _ in range(batch)
            ]
        self._residual = [0.0] * batch

    def follow_motion(self, x: float, xd: float) -> None:
        for twin in self.lanes:
            twin.command = 0.0  # the rig's SAFE answers: the coil off
            twin.advance(float(x), float(xd))

    def command_sent(self, current_a: float) -> None:
        self.lanes[0].command = current_a  # the command held until the next frame

    def command_one(
        self,
        x: float,
        xd: float,
        xdd: float,
        f_meas: float,
        f_des: float,
        f_des_next: float | None = None,
    ) -> float:
        # plain floats: the integrator's arithmetic on numpy scalars takes 3-4 times as long
        nxt = None if f_des_next is None else float(f_des_next)
        return self._lane(0, float(x), float(xd), float(xdd), float(f_meas), float(f_des), nxt)

    def _lane(
        self,
        j: int,
        x: float,
        xd: float,
        xdd: float,
        f_meas: float,
        f_des: float,
        f_des_next: float | None,
    ) -> float:
        twin = self.lanes[j]
        first = not twin.started
        f_twin = twin.advance(x, xd)
        ahead = self.ahead and f_des_next is not None
        r = 0.0
        if self.feedback_tau_s is not None:
            a = self.dt_s / (self.feedback_tau_s + self.dt_s)
            last = r = self._residual[j]
            r += a * (f_meas - f_twin - r)
            self._residual[j] = r
            if ahead and not first:
                r = 2.0 * r - last  # at the solved instant, at its last rate of change
        if not ahead or f_des_next is None:
            return twin.solve(f_des - r)
        T = self.dt_s
        # the instant the command first acts on: one period on at constant acceleration (eq. 21)
        return twin.solve(f_des_next - r, x + xd * T + 0.5 * xdd * T * T, xd + xdd * T)

    def command(self, s: ControlInput) -> np.ndarray:
        nxt = s.f_des_next
        return np.array(
            [
                self._lane(
                    j,
                    float(s.x[j]),
                    float(s.xd[j]),
                    float(s.xdd[j]),
                    float(s.f_meas[j]),
                    float(s.f_des[j]),
                    None if nxt is None else float(nxt[j]),
                )
                for j in range(self.batch)
            ]
        )

    def model_force_one(
        self, x: float, xd: float, xdd: float, f_meas: float, f_des: float, current_a: float
    ) -> float:
        return self._model_force_arrays(x, xd, xdd, f_meas, f_des, current_a)

    def model_force(self, s: ControlInput, current: np.ndarray) -> np.ndarray:
        """Eq. 30 at the twin's present state and the motion of `s`, with u = `current`."""
        cur = np.asarray(current, dtype=float)
        return np.array(
            [
                self.lanes[j].force(float(s.x[j]), float(s.xd[j]), float(cur[j]))
                for j in range(cur.size)
            ]
        )


class GruInversion(TwinInversion):
    """Network inversion with a GRU forward model (mrrig/loop/gru.py): its hidden state
    carried frame to frame, advanced with the commands actually sent, and its force one sample
    on solved for the command (a grid bracket and Newton steps through the gates; eq. 36's lag
    inverted for a model of the lagged current). The command of a frame acts on the next
    sample, so the solve is always for it, at the motion predicted there (eq. 21); `ahead`
    with `f_des_next` takes the desired force then as the target, else the present one. The
    load-cell feedback as `NetworkInversion`'s, the residual against the model's force now.
    Exact solve only, without adaptation; `continuity` as network inversion's (the model's
    own, `online_continuity`, chosen on its training rows), in closed form where u is the
    read-out's alone; with u in the cell the root nearest the present u. Built by
    network_inversion for a GRU model."""

    @classmethod
    def build(cls, s: ControllerSettings) -> Controller:
        if s.method != "exact":
            raise ValueError(f"method {s.method!r}: a GRU forward model is solved exactly")
        if s.adaptation is not None:
            raise ValueError("adaptation: not with a GRU forward model")
        assert isinstance(s.model, GRUModel)
        GruTracker(s.model, s.dt_s, s.i_max, s.continuity)  # a setting it refuses, here
        return cls(s.i_max, s.model, s.dt_s, s.feedback_tau_s, s.ahead, s.continuity)

    def __init__(
        self,
        i_max: float,
        model: GRUModel,
        dt_s: float = 0.002,
        feedback_tau_s: float | None = None,
        ahead: bool = False,
        continuity: float = 0.0,
    ) -> None:
        super().__init__(i_max, model, dt_s, feedback_tau_s, ahead, continuity)

    def follow_motion(self, x: float, xd: float) -> None:
        """Nothing: the GRU's hidden state starts at its run's first frame, as it was trained."""

    def reset(self, batch: int = 1) -> None:
        Controller.reset(self, batch)
        self.lanes = [
            GruTracker(self.model, self.dt_s, self.i_max, self.continuity) for _ in range(batch)
        ]
        self._residual = [0.0] * batch

    def _lane(
        self,
        j: int,
        x: float,
        xd: float,
        xdd: float,
        f_meas: float,
        f_des: float,
        f_des_next: float | None,
    ) -> float:
        gru = self.lanes[j]
        first = not gru.started
        f_now = gru.advance(x, xd, xdd)
        ahead = self.ahead and f_des_next is not None
        target = f_des_next if ahead and f_des_next is not None else f_des
        if self.feedback_tau_s is not None:
            a = self.dt_s / (self.feedback_tau_s + self.dt_s)
            last = r = self._residual[j]
            r += a * (f_meas - f_now - r)
            self._residual[j] = r
            if ahead and not first:
                r = 2.0 * r - last  # at the solved instant, at its last rate of change
            target -= r
        T = self.dt_s
        return gru.solve(target, x + xd * T + 0.5 * xdd * T * T, xd + xdd * T, xdd)


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
