"""The grey-box forward model: the identified Bouc-Wen twin (`twin_model.TwinModel`) plus a
small network on its residual, and its inversion frame by frame.

The force is eq. 30 of the twin's state plus the offset, plus r(z, x - y, u, x, xd): a tanh
MLP (`mlp.MLP`, inputs `RESIDUAL_INPUTS`) of the twin's own states (the hysteresis z, the
internal displacement as x - y, the filtered command u) and the measured motion. The twin is
carried frame to frame as `TwinTracker` carries it (its integrator at the model's sub-step,
`substep_s`, the one it was trained with), so the network sees the states it was fitted on.

Inversion (`GreyBoxTracker.solve`): as the twin's, the state is stepped one period on (the
previous command held) and the u reachable one period on is found, now for eq. 30 plus the
network: the force is smooth in u (eq. 30 a ratio of a quadratic to a linear function, the
network's tanh layer), evaluated on a grid over the reachable u, the bracket of a sign change
nearest the present u refined by safeguarded Newton steps with the exact derivative in u
(eq. 30's and the network's, `force_and_du`); without a sign change, the grid's u whose force
is nearest. The command is then eq. 36 inverted, as the twin's. Pure numerics.

File format `mrrig-greybox/1`: a JSON object with the twin's plant file (`plant`), the
residual network as an `mrrig-mlp/1` object (`residual`), the sub-step and the training
report (`identified`).
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import astuple, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from damper.plant import BoucWenDamper, bouc_wen_force
from damper.plant_file import parse_plant
from mrrig.loop.mlp import MLP, ModelError
from mrrig.loop.twin_model import SUBSTEP_S, TwinModel, TwinTracker

FORMAT = "mrrig-greybox/1"
RESIDUAL_INPUTS = ("z", "x_minus_y", "u", "x", "xd")
GRID = 9  # points of the bracketing grid over the reachable u
NEWTON_STEPS = 8  # at most, in the bracket
TOL_U = 1e-9  # relative to the bracket: the solve's step at which it stops
MAX_SUBSTEP_S = 0.01  # a sub-step above it would not follow eq. 36's lag


def is_greybox_doc(doc: Any) -> bool:
    return isinstance(doc, dict) and doc.get("format") == FORMAT


@dataclass(frozen=True)
class GreyBoxModel(TwinModel):
    """The twin's plant plus the residual network (module docstring). A `TwinModel`, so that
    the daemon's checks of a twin (units, plausible parameters) and its inversion apply; its
    `tracker` carries the residual too."""

    residual: MLP | None = None
    substep_s: float = SUBSTEP_S
    identified: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.residual is None or tuple(self.residual.input_names) != RESIDUAL_INPUTS:
            got = None if self.residual is None else self.residual.input_names
            raise ModelError(f"residual: inputs must be {list(RESIDUAL_INPUTS)}, got {got}")
        if not 0.0 < self.substep_s <= MAX_SUBSTEP_S:
            raise ModelError(
                f"substep_s: must lie in (0, {MAX_SUBSTEP_S:g}] s, got {self.substep_s}"
            )

    @property
    def meta(self) -> dict[str, Any]:
        return {**super().meta, "kind": "bouc-wen-greybox"}

    def tracker(self, dt_s: float, i_max: float, continuity: float = 0.0) -> GreyBoxTracker:
        return GreyBoxTracker(self, dt_s, i_max, continuity)

    def to_doc(self) -> dict[str, Any]:
        assert self.residual is not None
        return {
            "format": FORMAT,
            "plant": self.plant.to_json(),
            "residual": self.residual.to_dict(),
            "substep_s": self.substep_s,
            "identified": self.identified,
        }

    def save(self, path: str | Path) -> None:
        Path(path).write_text(
            json.dumps(self.to_doc(), indent=1, allow_nan=False) + "\n", encoding="utf-8"
        )

    @classmethod
    def from_doc(cls, doc: dict[str, Any], path: str | Path) -> GreyBoxModel:
        """One-line ModelError naming the part of the file that is wrong."""
        for key in ("plant", "residual"):
            if not isinstance(doc.get(key), dict):
                raise ModelError(f"{path}: {key}: missing or not an object")
        try:
            plant = parse_plant(doc["plant"], Path(path))
        except ValueError as exc:
            raise ModelError(str(exc)) from None
        net = MLP.from_text(json.dumps(doc["residual"]), f"{path}: residual")
        sub = doc.get("substep_s", SUBSTEP_S)
        if not isinstance(sub, int | float) or isinstance(sub, bool):
            raise ModelError(f"{path}: substep_s: expected a number, got {sub!r}")
        try:
            return cls(plant, str(path), net, float(sub), dict(doc.get("identified") or {}))
        except ModelError as exc:
            raise ModelError(f"{path}: {exc}") from None


@functools.lru_cache(maxsize=8)
def _k(params: Any) -> tuple:
    return astuple(params)


def twin_force_du(k: tuple, z: Any, y: Any, u: Any, x: Any, xd: Any) -> Any:
    """d(eq. 30)/du at the state (z, y) and the motion (x, xd): eqs 32-35 are affine in u, so
    eq. 30 is (c1a + c1b u)(p + q u) / (d0 + d1 u) plus a term free of u."""
    c0a, c0b, k0, c1a, c1b, _k1, _x0, aa, ab = k[:9]
    p = aa * z + c0a * xd + k0 * (x - y)
    q = ab * z + c0b * xd
    d0, d1 = c0a + c1a, c0b + c1b
    c1, n, d = c1a + c1b * u, p + q * u, d0 + d1 * u
    return ((c1b * n + c1 * q) * d - c1 * n * d1) / (d * d)


def residual_and_du(net: MLP, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The residual network's output for rows X (N x 5, `RESIDUAL_INPUTS`) and its derivative
    in u (column 2)."""
    zs = (X - net.in_mean) / net.in_std
    o = np.tanh(zs @ net.W1.T + net.b1)
    r = net.out_mean + net.out_std * (o @ net.W2 + net.b2)
    j = RESIDUAL_INPUTS.index("u")
    dr = net.out_std * ((1.0 - o * o) @ (net.W2 * net.W1[:, j])) / net.in_std[j]
    return r, dr


def residual_rows(z: Any, y: Any, u: Any, x: Any, xd: Any) -> np.ndarray:
    """The residual network's input rows (`RESIDUAL_INPUTS`) of states and motion."""
    return np.column_stack(np.broadcast_arrays(z, x - y, u, x, xd)).astype(np.float64)


def force_and_du(
    model: GreyBoxModel, z: Any, y: Any, u: Any, x: Any, xd: Any
) -> tuple[np.ndarray, np.ndarray]:
    """The grey-box force (eq. 30, the offset and the residual) at states (z, y), the filtered
    command u and the motion (x, xd), and its derivative in u (arrays broadcast)."""
    assert model.residual is not None
    k = _k(model.plant.params)
    X = residual_rows(z, y, u, x, xd)
    r, dr = residual_and_du(model.residual, X)
    zz, yy, uu, xx, vv = X[:, 0], X[:, 3] - X[:, 1], X[:, 2], X[:, 3], X[:, 4]
    f = bouc_wen_force(zz, yy, uu, xx, vv, k) + model.plant.offset_n + r
    return f, twin_force_du(k, zz, yy, uu, xx, vv) + dr


class GreyBoxTracker(TwinTracker):
    """One damper's grey-box model, carried frame to frame and inverted (module docstring)."""

    def __init__(
        self, model: GreyBoxModel, dt_s: float, i_max: float, continuity: float = 0.0
    ) -> None:
        super().__init__(model, dt_s, i_max, continuity)
        self.model = model
        self.damper = BoucWenDamper(model.plant.params, model.substep_s)

    def _force(self, z: float, y: float, u: float, x: float, xd: float) -> float:
        f, _ = force_and_du(self.model, z, y, u, x, xd)
        return float(f[0])

    def advance(self, x: float, xd: float) -> float:
        """Advance the twin to this frame's motion (the command held since the last one); the
        grey-box force now."""
        super().advance(x, xd)
        z, y, u = self.damper.state
        return self._force(z, y, u, x, xd)

    def force(self, x: float, xd: float, u: float) -> float:
        z, y, _ = self.damper.state
        return self._force(z, y, u, x, xd)

    def solve(self, target_n: float, x1: float | None = None, xd1: float | None = None) -> float:
        """The command for the force `target_n` one period on, clamped to [0, i_max] (as
        `TwinTracker.solve`, the residual included). Becomes the command held."""
        d = self.damper
        z, y, u = d.state
        x, xd = self.x, self.xd
        if x1 is not None and xd1 is not None:
            d.step(x1, xd1, self.command, self.dt_s)
            z1, y1, _ = d.state
            d.set_state((z, y, u), self.x, self.xd)
            z, y, x, xd = z1, y1, x1, xd1
        lag = self.lag
        lo, hi = u - lag * u, u + lag * (self.i_max - u)
        u1 = solve_u(self.model, z, y, x, xd, target_n, lo, hi, u)
        if self._pull > 0.0:  # the continuity, as `TwinTracker.solve`'s
            g = float(force_and_du(self.model, z, y, u1, x, xd)[1][0])
            u1 += (u - u1) / (1.0 + g * g / self._pull)
        v = u + (u1 - u) / lag  # eq. 36 inverted: u reaches u1 one period on
        self.command = min(max(v, 0.0), self.i_max)
        return self.command


def solve_u(
    model: GreyBoxModel,
    z: float,
    y: float,
    x: float,
    xd: float,
    target_n: float,
    lo: float,
    hi: float,
    near: float,
) -> float:
    """The u in [lo, hi] whose grey-box force at the state (z, y) and motion (x, xd) is
    `target_n`: the sign change of a grid nearest `near`, refined by safeguarded Newton steps;
    without one, the grid's u whose force is nearest the target."""
    grid = np.linspace(lo, hi, GRID)
    f, _ = force_and_du(model, z, y, grid, x, xd)
    g = f - target_n
    brackets = np.flatnonzero(np.sign(g[:-1]) * np.sign(g[1:]) <= 0.0)
    if brackets.size == 0 or not np.all(np.isfinite(g)):
        return float(grid[int(np.nanargmin(np.abs(g)))])
    mids = 0.5 * (grid[brackets] + grid[brackets + 1])
    b = int(brackets[int(np.argmin(np.abs(mids - near)))])
    a, c = float(grid[b]), float(grid[b + 1])
    ga = float(g[b])
    if ga == 0.0:
        return a
    t = 0.5 * (a + c)
    for _ in range(NEWTON_STEPS):
        ft, dt = force_and_du(model, z, y, t, x, xd)
        gt = float(ft[0]) - target_n
        if gt == 0.0:
            return t
        if (gt < 0.0) == (ga < 0.0):
            a, ga = t, gt
        else:
            c = t
        step = gt / float(dt[0]) if dt[0] != 0.0 else math.inf
        nxt = t - step
        if not a < nxt < c:
            nxt = 0.5 * (a + c)  # Newton left the bracket: bisect
        if abs(nxt - t) <= TOL_U * max(abs(hi - lo), 1e-12):
            return nxt
        t = nxt
    return t
