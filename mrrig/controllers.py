"""Damper controllers behind one interface: given the estimate and the desired force, a current.

Every controller works on a batch: the fields of `ControlInput` are arrays of shape (B,) (B = 1
in the rig daemon, B = 7 in `mrrig bench paper`, which runs the seven validation cases at once),
and `command` returns the current (or, in the paper's simulation, the voltage) of shape (B,),
already clamped to [0, i_max]. Controllers are pure numerics: they know nothing of CAN or Zenoh.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np

from mrrig.inversion import ScalarInverter, exact_inversion, gradient_inversion
from mrrig.model.mlp import MLP

FORWARD_INPUTS = ("x", "xd", "xdd", "current")
SUPERVISED_INPUTS = ("x", "xd", "xdd", "f_des")


@dataclass
class ControlInput:
    """One control instant: the state estimate, the load cell and the target (arrays (B,))."""

    x: np.ndarray  # displacement, m
    xd: np.ndarray  # velocity, m/s
    xdd: np.ndarray  # acceleration, m/s^2
    f_meas: np.ndarray  # measured (load-cell) force, N
    f_des: np.ndarray  # desired force, N


class Controller(abc.ABC):
    """A damper controller: `reset()` before a run, then `command()` once per sample."""

    name: str = ""
    controller_id: int = 0  # DamperCommand.ControllerId (spec/can-protocol.md)

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

    def model_force(self, s: ControlInput, current: np.ndarray) -> np.ndarray:
        """The forward model's force for `current` (NaN for controllers without one)."""
        return np.full_like(np.asarray(current, dtype=float), np.nan)


class ConstantCurrent(Controller):
    """Open loop: the same current all the time."""

    name = "constant"
    controller_id = 6

    def __init__(self, i_max: float, current: float) -> None:
        super().__init__(i_max)
        if not 0.0 <= current <= i_max:
            raise ValueError(f"current {current} A outside [0, {i_max}] A")
        self.current = float(current)

    def command(self, s: ControlInput) -> np.ndarray:
        return np.full(np.shape(s.f_des), self.current)


class Heaviside(Controller):
    """Dyke et al. (1996): full or no current by the sign of (f_d - f_a) f_a (eqs 37-38)."""

    name = "heaviside"
    controller_id = 2

    def reset(self, batch: int = 1) -> None:
        super().reset(batch)
        self._held = np.zeros(batch)

    def command(self, s: ControlInput) -> np.ndarray:
        prod = (s.f_des - s.f_meas) * s.f_meas
        # eq. 37-38; held at its previous value when the product is exactly 0
        self._held = np.where(prod > 0, self.i_max, np.where(prod < 0, 0.0, self._held))
        return self._held.copy()


class ContinuousState(Controller):
    """Sims et al. (1999): v = clip(G (f_d - B f_a) sgn(f_a), 0, Vmax) (eq. 39)."""

    name = "continuous_state"
    controller_id = 3

    def __init__(self, i_max: float, gain: float = 0.021, b: float = 1.0) -> None:
        super().__init__(i_max)
        self.gain = gain
        self.b = b

    def command(self, s: ControlInput) -> np.ndarray:
        v = self.gain * (s.f_des - self.b * s.f_meas) * np.sign(s.f_meas)  # eq. 39
        return np.clip(v, 0.0, self.i_max)


class NetworkInversion(Controller):
    """The paper's inverse model: solve the frozen forward network for the current.

    `method="exact"` (default) is the bracketed safeguarded-Newton scalar solve;
    `method="gradient"` is the paper's eq. 2/14 gradient descent, kept as the reference.
    With `feedback_tau_s` set, the load cell corrects the model online: the residual
    r = f_meas - f_net(state, previous command) is low-passed with that time constant and the
    network is solved for f_des - r, so a steady model error does not become tracking error.
    """

    name = "network_inversion"
    controller_id = 1

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
    ) -> None:
        super().__init__(i_max)
        if tuple(model.input_names) != FORWARD_INPUTS or model.output_name != "force":
            raise ValueError(
                f"network inversion needs a forward model {FORWARD_INPUTS} -> force, "
                f"got {tuple(model.input_names)} -> {model.output_name}"
            )
        if method not in ("exact", "gradient"):
            raise ValueError(f"unknown inversion method {method!r} (exact, gradient)")
        self.model = model
        self.method = method
        self.feedback_tau_s = feedback_tau_s
        self.dt_s = dt_s
        self.gradient_rate = gradient_rate
        self.gradient_iterations = gradient_iterations
        self._rng = np.random.default_rng(seed)
        self._scalar = ScalarInverter(model, i_max)

    def reset(self, batch: int = 1) -> None:
        super().reset(batch)
        self._prev = np.zeros(batch)
        self._residual = np.zeros(batch)
        self._first = True

    def _features(self, s: ControlInput, current: np.ndarray) -> np.ndarray:
        return np.stack([s.x, s.xd, s.xdd, current], axis=-1)

    @staticmethod
    def _state(s: ControlInput) -> np.ndarray:
        return np.stack([s.x, s.xd, s.xdd], axis=-1)

    def model_force(self, s: ControlInput, current: np.ndarray) -> np.ndarray:
        return self.model.predict(self._features(s, np.asarray(current, dtype=float)))

    def command(self, s: ControlInput) -> np.ndarray:
        target = s.f_des
        if self.feedback_tau_s is not None:
            residual = s.f_meas - self.model_force(s, self._prev)
            a = self.dt_s / (self.feedback_tau_s + self.dt_s)
            self._residual += a * (residual - self._residual)
            target = s.f_des - self._residual
        if self.method == "gradient":
            # the paper's on-line inverse estimation: a random initial current, then each
            # sample's descent starts from the previous sample's current
            i = gradient_inversion(
                self.model,
                self._state(s),
                target,
                i_max=self.i_max,
                rate=self.gradient_rate,
                iterations=self.gradient_iterations,
                i0=None if self._first else self._prev,
                rng=self._rng,
            )
        elif self.batch == 1:
            i = np.array([self._scalar.solve(self._state(s)[0], float(target[0]), self._prev[0])])
        else:
            i = exact_inversion(self.model, self._state(s), target, self._prev, i_max=self.i_max)
        self._prev = np.clip(i, 0.0, self.i_max)
        self._first = False
        return self._prev.copy()


class SupervisedInverse(Controller):
    """Direct inverse MLP (x, xd, xdd, f_des) -> current, trained by supervised learning."""

    name = "supervised"
    controller_id = 4

    def __init__(self, i_max: float, model: MLP) -> None:
        super().__init__(i_max)
        if tuple(model.input_names) != SUPERVISED_INPUTS or model.output_name != "current":
            raise ValueError(
                f"the supervised inverse needs a model {SUPERVISED_INPUTS} -> current, "
                f"got {tuple(model.input_names)} -> {model.output_name}"
            )
        self.model = model

    def command(self, s: ControlInput) -> np.ndarray:
        X = np.stack([s.x, s.xd, s.xdd, s.f_des], axis=-1)
        return np.clip(self.model.predict(X), 0.0, self.i_max)


RNN_INPUTS = ("f_des", "f_des_1", "x", "x_1") + tuple(f"v_{k}" for k in range(1, 7))


def rnn_features(f: np.ndarray, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Training rows of the RNN of paper eq. 40 from a series: target v[k] for k >= 6.

    Inputs per row: f(k), f(k-1), x(k), x(k-1), v(k-1) ... v(k-6); the command fed back is the
    network's own previous output in closed loop (the "recurrent" part).
    """
    k = np.arange(6, len(f))
    cols = [f[k], f[k - 1], x[k], x[k - 1]] + [v[k - j] for j in range(1, 7)]
    return np.stack(cols, axis=-1)


class RecurrentInverse(Controller):
    """Wang & Liao (2005) RNN (paper eq. 40): the previous six commands are fed back."""

    name = "rnn"
    controller_id = 5

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


CONTROLLER_NAMES = (
    "network_inversion",
    "heaviside",
    "continuous_state",
    "supervised",
    "rnn",
    "constant",
)
