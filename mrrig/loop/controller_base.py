"""What every damper controller shares: the control instant's input (`ControlInput`), the
settings a controller is built from (`ControllerSettings`), the interface (`Controller`) and a
model's input rows with their history (`ModelInputs`). The controllers themselves and their
registry: mrrig/loop/controllers.py.

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

from mrrig.loop.adaptation import AdaptationSettings
from mrrig.loop.inversion import DEFAULT_CONTINUITY
from mrrig.loop.mlp import MLP

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
