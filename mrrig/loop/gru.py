"""The recurrent (GRU) forward model in numpy, and its inversion frame by frame.

A GRU cell (Cho et al. 2014, in torch's `nn.GRU` form) carries a hidden state h over the
samples; the force is a linear read-out of it. Its inputs are those of the static forward
network, (x, xd, xdd, u): u is the coil's lagged current (meta `current_input = "lagged"`,
eq. 36 with `lag_tau_s`) or the command held over the period before the sample
(`"commanded"`): either way the force at a sample depends on commands sent before it, so the
model is causal and the command of a frame acts on the next sample. Weights are stored as
torch keeps them (gates r, z, n stacked), inputs and output standardised; `predict` runs a
whole series in physical units. mrrig/offline/training/gru.py trains and writes it.

File format `mrrig-gru/1`: a JSON object, arrays written with `repr` (a reload is bit-exact),
with the MLP's names, units and meta (command unit, sample period, lag, coverage envelope), so
that the daemon's checks read it as they read a network.

Inversion (`GruTracker`): each frame the state is advanced to this sample with the u the
commands sent made (eq. 36 for a lagged model), which gives the model's force now (the
load-cell residual is taken against it). The command is then solved for the next sample, the
one it acts on, at the motion predicted there (eq. 21): one period on, u is affine in the
command, so the next force is a smooth function of u through the cell's gates. It is evaluated
on a grid over the u the commands [0, i_max] can reach; the bracket of a sign change nearest
the present u is refined by safeguarded Newton steps (the derivative through the gates, exact);
a force out of reach gets the reachable u whose force is nearest. Pure numerics.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mrrig.loop.mlp import ModelError, _has_kind, _plain

FORMAT = "mrrig-gru/1"
GRID = 9  # points of the bracketing grid over the reachable u
NEWTON_STEPS = 6  # at most, in the bracket
TOL_U = 1e-9  # relative to i_max: the solve's step at which it stops
CURRENT_INPUTS = ("lagged", "commanded")


def _sigmoid(a: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * a))  # no overflow for large |a|


@dataclass
class GRUModel:
    """(x, xd, xdd, u) -> force: h' = GRU(z, h) (torch's gates r, z, n) on the standardised
    motion (and u where W_ih has a fourth column), f = out_mean + out_std * (W_out . h' + b_out
    + u_s (V_out . h' + c_out)), u_s the standardised u: the force affine in u at a state, as
    eq. 30 is in the command's coefficients (eqs 32-35)."""

    input_names: list[str]
    input_units: list[str]
    output_name: str
    output_unit: str
    in_mean: np.ndarray
    in_std: np.ndarray
    out_mean: float
    out_std: float
    W_ih: np.ndarray  # (3H, 3 or 4): rows r, z, n; columns x, xd, xdd (and u)
    W_hh: np.ndarray  # (3H, H)
    b_ih: np.ndarray  # (3H,)
    b_hh: np.ndarray  # (3H,)
    W_out: np.ndarray  # (H,)
    b_out: float
    V_out: np.ndarray  # (H,): the read-out's gain on u
    c_out: float
    fingerprint: str = ""
    metrics: dict[str, Any] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in _ARRAYS:
            try:
                setattr(self, name, np.array(getattr(self, name), dtype=np.float64))
            except ValueError:
                raise ModelError(f"model: field '{name}': not a rectangular array") from None
        self.out_mean, self.out_std = float(self.out_mean), float(self.out_std)
        self.b_out, self.c_out = float(self.b_out), float(self.c_out)
        problem = self._problem()
        if problem is not None:
            raise ModelError(f"model: field '{problem[0]}': {problem[1]}")

    @property
    def n_in(self) -> int:
        return len(self.input_names)

    @property
    def hidden(self) -> int:
        return int(self.W_hh.shape[1])

    @property
    def lag_tau_s(self) -> float | None:
        """The coil lag of the model's u (None: u is the command held over the period)."""
        if self.meta.get("current_input") != "lagged":
            return None
        return float(self.meta["lag_tau_s"])

    def _problem(self) -> tuple[str, str] | None:
        if self.input_names != ["x", "xd", "xdd", "current"]:
            return "input_names", f"must be ['x', 'xd', 'xdd', 'current'], got {self.input_names}"
        if len(self.input_units) != 4 or not all(isinstance(u, str) for u in self.input_units):
            return "input_units", "must be 4 strings"
        h = self.W_hh.shape[1] if self.W_hh.ndim == 2 else 0
        if h == 0:
            return "W_hh", f"must be 3H x H with H >= 1, got shape {self.W_hh.shape}"
        shapes = {
            "in_mean": (4,),
            "in_std": (4,),
            "W_ih": (3 * h, 3 if self.W_ih.shape[1:] == (3,) else 4),
            "W_hh": (3 * h, h),
            "b_ih": (3 * h,),
            "b_hh": (3 * h,),
            "W_out": (h,),
            "V_out": (h,),
        }
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                return name, f"must have shape {shape}, got {getattr(self, name).shape}"
        for name in (*_ARRAYS, "out_mean", "out_std", "b_out", "c_out"):
            if not np.all(np.isfinite(getattr(self, name))):
                return name, "must be finite"
        for name in ("in_std", "out_std"):
            if np.any(np.asarray(getattr(self, name)) <= 0.0):
                return name, "must be > 0"
        ci = self.meta.get("current_input")
        if ci not in CURRENT_INPUTS:
            return "meta.current_input", f"must be one of {', '.join(CURRENT_INPUTS)}, got {ci!r}"
        tau = self.meta.get("lag_tau_s")
        if ci == "lagged" and (
            isinstance(tau, bool) or not isinstance(tau, int | float) or not tau > 0
        ):
            return (
                "meta.lag_tau_s",
                f"a model of the lagged current needs a number > 0, got {tau!r}",
            )
        return None

    @property
    def u_in_cell(self) -> bool:
        """Whether u is an input of the cell too (else of the read-out alone)."""
        return self.W_ih.shape[1] == 4

    def cell(self, z: np.ndarray, h: np.ndarray) -> np.ndarray:
        """One step of the GRU on standardised inputs z (..., 4) from h (..., H)."""
        H = self.hidden
        gi = z[..., : self.W_ih.shape[1]] @ self.W_ih.T + self.b_ih
        gh = h @ self.W_hh.T + self.b_hh
        r = _sigmoid(gi[..., :H] + gh[..., :H])
        u = _sigmoid(gi[..., H : 2 * H] + gh[..., H : 2 * H])
        n = np.tanh(gi[..., 2 * H :] + r * gh[..., 2 * H :])
        return (1.0 - u) * n + u * h

    def read_out(self, h: np.ndarray, u_s: np.ndarray | float) -> np.ndarray:
        """The force of the state h (..., H) and the standardised u (...)."""
        return self.out_mean + self.out_std * (
            h @ self.W_out + self.b_out + u_s * (h @ self.V_out + self.c_out)
        )

    def predict(self, X: np.ndarray, h0: np.ndarray | None = None) -> np.ndarray:
        """The force (N,) along one sequence of inputs X (N, 4) in physical units, from h0
        (zeros: the state after `reset`)."""
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != 4:
            raise ValueError(f"predict: X must be (N, 4), got {X.shape}")
        return self.read_out(self.states(X, h0), (X[:, 3] - self.in_mean[3]) / self.in_std[3])

    def states(self, X: np.ndarray, h0: np.ndarray | None = None) -> np.ndarray:
        """The hidden states (N, H) along X (N, 4), physical units, from h0 (zeros)."""
        Z = (np.asarray(X, dtype=np.float64) - self.in_mean) / self.in_std
        h = np.zeros(self.hidden) if h0 is None else np.array(h0, dtype=float)
        out = np.empty((Z.shape[0], self.hidden))
        for k in range(Z.shape[0]):
            h = self.cell(Z[k], h)
            out[k] = h
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "input_names": list(self.input_names),
            "input_units": list(self.input_units),
            "output_name": self.output_name,
            "output_unit": self.output_unit,
            "hidden": self.hidden,
            "fingerprint": self.fingerprint,
            "in_mean": self.in_mean.tolist(),
            "in_std": self.in_std.tolist(),
            "out_mean": self.out_mean,
            "out_std": self.out_std,
            "W_ih": self.W_ih.tolist(),
            "W_hh": self.W_hh.tolist(),
            "b_ih": self.b_ih.tolist(),
            "b_hh": self.b_hh.tolist(),
            "W_out": self.W_out.tolist(),
            "b_out": self.b_out,
            "V_out": self.V_out.tolist(),
            "c_out": self.c_out,
            "metrics": _plain(self.metrics),
            "meta": _plain(self.meta),
        }

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1) + "\n", encoding="utf-8")

    @classmethod
    def from_doc(cls, doc: dict, path: str | Path) -> GRUModel:
        """A decoded `mrrig-gru/1` document; a one-line ModelError naming the field."""
        kwargs: dict[str, Any] = {}
        for name, kind in _FIELDS.items():
            if name not in doc:
                raise ModelError(f"{path}: field '{name}': missing")
            if not _has_kind(doc[name], kind):
                raise ModelError(f"{path}: field '{name}': expected {kind}")
            kwargs[name] = doc[name]
        try:
            return cls(**kwargs)
        except ModelError as exc:
            raise ModelError(f"{path}: {str(exc).removeprefix('model: ')}") from None


_ARRAYS = ("in_mean", "in_std", "W_ih", "W_hh", "b_ih", "b_hh", "W_out", "V_out")
_FIELDS: dict[str, str] = {
    "input_names": "list of strings",
    "input_units": "list of strings",
    "output_name": "string",
    "output_unit": "string",
    "fingerprint": "string",
    "in_mean": "list of numbers",
    "in_std": "list of numbers",
    "out_mean": "number",
    "out_std": "number",
    "W_ih": "list of lists of numbers",
    "W_hh": "list of lists of numbers",
    "b_ih": "list of numbers",
    "b_hh": "list of numbers",
    "W_out": "list of numbers",
    "b_out": "number",
    "V_out": "list of numbers",
    "c_out": "number",
    "metrics": "object",
    "meta": "object",
}


def affine_solve(
    f_m: float,
    gain: float,
    u_mean: float,
    target_n: float,
    u_prev: float,
    lo: float,
    hi: float,
    w_force: float,
    w_cont: float,
) -> float:
    """The u in [lo, hi] minimising w_force (f(u) - target)^2 + w_cont (u - u_prev)^2 for the
    affine force f(u) = f_m + gain (u - u_mean): network inversion's exact solve with its
    continuity weight (mrrig/loop/inversion.py), in closed form; the root where w_cont = 0.
    The objective is convex, so the clamp is its minimum on the range (a target out of reach
    gets the nearest end); where no u changes the force, u_prev clamped."""
    den = w_force * gain * gain + w_cont
    if den == 0.0:
        return min(max(u_prev, lo), hi)
    u = (w_force * gain * (target_n - f_m + gain * u_mean) + w_cont * u_prev) / den
    return min(max(u, lo), hi)


class GruTracker:
    """One damper's GRU state, carried frame to frame and inverted (module docstring)."""

    def __init__(self, model: GRUModel, dt_s: float, i_max: float, continuity: float = 0.0) -> None:
        if continuity and model.u_in_cell:
            raise ValueError(
                "continuity: a GRU with u in its cell is solved for the root alone (continuity 0)"
            )
        self.model = model
        self.dt_s = dt_s
        self.i_max = i_max
        tau = model.lag_tau_s
        # eq. 36 over one period, the command v held: u(T) = u + lag (v - u); 1: u is v
        self.lag = 1.0 if tau is None else -math.expm1(-dt_s / tau)
        H = model.hidden
        m = model
        # the cell's pre-activations are affine in the standardised motion and in u
        self._W_motion = m.W_ih[:, :3] / m.in_std[:3]
        # d pre-activation / d u (none where u is the read-out's alone)
        self._col = m.W_ih[:, 3] / m.in_std[3] if m.u_in_cell else np.zeros(3 * H)
        self._b_motion = m.b_ih - self._W_motion @ m.in_mean[:3] - self._col * m.in_mean[3]
        self._w, self._v = m.out_std * m.W_out, m.out_std * m.V_out
        self._f0, self._cv = m.out_mean + m.out_std * m.b_out, m.out_std * m.c_out
        self._u_mean, self._u_scale = m.in_mean[3], 1.0 / m.in_std[3]
        # the exact solve's objective (mrrig/loop/inversion.py): force and continuity weights
        self._w_force, self._w_cont = 1.0 / m.out_std**2, continuity / m.in_std[3] ** 2
        self._H = H
        self.reset()

    def reset(self) -> None:
        """The next `advance` starts from the zero state, u = 0 (the coil off)."""
        self.h = np.zeros(self._H)
        self.u = 0.0  # u at the last sample advanced to
        self.command = 0.0  # the command held since then
        self.started = False
        self.xdd = 0.0

    def _pre(self, x: float, xd: float, xdd: float) -> tuple[np.ndarray, np.ndarray]:
        """(input pre-activations at u = 0, hidden ones) for the motion, from the state h."""
        gi = self._W_motion @ np.array([x, xd, xdd]) + self._b_motion
        return gi, self.model.W_hh @ self.h + self.model.b_hh

    def _force(self, gi: np.ndarray, gh: np.ndarray, u: float | np.ndarray, grad: bool = False):
        """The force one step on, for u (a float, or an array for a grid), and with `grad` its
        derivative in u: the read-out's gain, and the chain through the gates r, z, n."""
        H = self._H
        a = gi + np.multiply.outer(u, self._col)
        r = _sigmoid(a[..., :H] + gh[:H])
        z = _sigmoid(a[..., H : 2 * H] + gh[H : 2 * H])
        n = np.tanh(a[..., 2 * H :] + r * gh[2 * H :])
        h1 = (1.0 - z) * n + z * self.h
        u_s = (u - self._u_mean) * self._u_scale
        gain = h1 @ self._v + self._cv  # the read-out's d force / d u_s at h1
        f = self._f0 + h1 @ self._w + u_s * gain
        if not grad:
            return f, h1
        c = self._col
        dr = r * (1.0 - r) * c[:H]
        dz = z * (1.0 - z) * c[H : 2 * H]
        dn = (1.0 - n * n) * (c[2 * H :] + dr * gh[2 * H :])
        dh1 = dz * (self.h - n) + (1.0 - z) * dn
        return f, h1, dh1 @ (self._w + u_s * self._v) + gain * self._u_scale

    def advance(self, x: float, xd: float, xdd: float) -> float:
        """Step the state to this sample with the u the held command made; the force now."""
        u = self.u + self.lag * (self.command - self.u) if self.started else 0.0  # eq. 36
        self.started = True
        gi, gh = self._pre(x, xd, xdd)
        f, self.h = self._force(gi, gh, u)
        self.u, self.xdd = u, xdd
        return float(f)

    def force(self, x: float, xd: float, command: float) -> float:
        """`force_next` at the last acceleration."""
        return self.force_next(x, xd, self.xdd, command)

    def force_next(self, x1: float, xd1: float, xdd1: float, command: float) -> float:
        """The force at the next sample, at the motion (x1, xd1, xdd1) there, had `command`
        been held until it (eq. 36 for a lagged model); the state is not changed."""
        gi, gh = self._pre(x1, xd1, xdd1)
        return float(self._force(gi, gh, self.u + self.lag * (command - self.u))[0])

    def solve(self, target_n: float, x1: float, xd1: float, xdd1: float) -> float:
        """The command, clamped to [0, i_max], whose u makes the force `target_n` at the next
        sample, at the motion (x1, xd1, xdd1) there. Becomes the command held."""
        u, lag = self.u, self.lag
        lo, hi = u - lag * u, u + lag * (self.i_max - u)  # eq. 36: commands 0 and i_max
        gi, gh = self._pre(x1, xd1, xdd1)
        if not self.model.u_in_cell:
            u1 = self._exact(gi, gh, target_n, lo, hi)
        else:
            u1 = self._bracketed(gi, gh, target_n, lo, hi)
        v = u + (u1 - u) / lag  # eq. 36 inverted: u reaches u1 one period on
        self.command = min(max(v, 0.0), self.i_max)
        return self.command

    def _exact(self, gi: np.ndarray, gh: np.ndarray, target_n: float, lo: float, hi: float):
        """u in [lo, hi] for the target where u is the read-out's alone: the next state does
        not depend on it and the force is affine in it (`affine_solve`, from the present u)."""
        f_m, h1 = self._force(gi, gh, self._u_mean)
        gain = (float(h1 @ self._v) + self._cv) * self._u_scale  # d force / d u
        return affine_solve(
            float(f_m), gain, self._u_mean, target_n, self.u, lo, hi, self._w_force, self._w_cont
        )

    def _bracketed(self, gi: np.ndarray, gh: np.ndarray, target_n: float, lo: float, hi: float):
        """u in [lo, hi] for the target where u is an input of the cell: the grid's bracket
        nearest the present u, refined by Newton; out of reach, the grid's u nearest it."""
        u = self.u
        grid = np.linspace(lo, hi, GRID)
        e = self._force(gi, gh, grid)[0] - target_n
        flips = np.flatnonzero(np.signbit(e[:-1]) != np.signbit(e[1:]))
        if flips.size == 0:
            return float(grid[int(np.argmin(np.abs(e)))])  # out of reach: the nearest force
        k = int(flips[np.argmin(np.abs(grid[flips] - u))])  # the bracket nearest u
        return self._newton(gi, gh, target_n, float(grid[k]), float(grid[k + 1]), float(e[k]))

    def _newton(self, gi, gh, target_n: float, a: float, b: float, e_a: float) -> float:
        """Newton's root of force(u) = target in [a, b] (a sign change), a step leaving the
        bracket replaced by bisection; the bracket shrinks with each evaluation."""
        tol = TOL_U * self.i_max
        u = 0.5 * (a + b)
        for _ in range(NEWTON_STEPS):
            f, _, df = self._force(gi, gh, u, grad=True)
            e = float(f) - target_n
            if (e < 0.0) == (e_a < 0.0):
                a, e_a = u, e
            else:
                b = u
            step = e / df if df != 0.0 else math.inf
            nxt = u - step
            if not a < nxt < b:
                nxt = 0.5 * (a + b)
            if abs(nxt - u) <= tol:
                return nxt
            u = nxt
        return u


def is_gru_doc(doc: Any) -> bool:
    return isinstance(doc, dict) and doc.get("format") == FORMAT
