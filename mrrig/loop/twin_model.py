"""The Bouc-Wen twin as the forward model the daemon inverts: a plant file (`mrrig identify`,
`damper.plant_file`) in place of a network, for network inversion.

Each frame the twin's state, the hysteresis z, the internal displacement y and the filtered
command u (eqs 31, 32, 36), is advanced from the last frame's estimated motion to this one's
with the command actually sent (held over the period, as the rig holds it), by the plant's
own integrator (`damper.plant.BoucWenDamper`, the simulator's sub-step). The command is then
solved for the instant it acts on: the state is stepped one period further on the predicted
motion (a copy of the integration, the previous command held), and at that state eq. 30 is a
ratio of a quadratic to a linear function of u (eqs 32-35 are affine in u), so u is the root
of a quadratic, solved exactly (with a continuity mu > 0, pulled toward the present u as network
inversion's regularised solve is: `TwinTracker.solve`). The command reaches u through eq. 36's
first-order filter:
over one period u moves the share `1 - exp(-eta T)` of the way to the command, so the rig's
range [0, i_max] of commands is a range of u one period on; a force out of it gets the end
of that range closest to it. The command is the one that takes u to the root in one period.

A frame the rig lost is advanced as one period (the controller knows no time); the load-cell
feedback of network inversion corrects what the twin gets wrong. Pure numerics.
"""

from __future__ import annotations

import json
import math
from dataclasses import astuple, dataclass
from pathlib import Path
from typing import Any

from damper.plant import BoucWenDamper, bouc_wen_force
from damper.plant_file import FORMAT as PLANT_FORMAT
from damper.plant_file import Plant, parse_plant
from mrrig.loop.gru import GRUModel, is_gru_doc
from mrrig.loop.mlp import MLP, ModelError

# the simulator's RK4 sub-step (configs/sim.toml damper.substep_s): the twin integrates as the
# plant it was fitted for does
SUBSTEP_S = 1e-4
# The continuity's scales (network inversion's regularised solve, mrrig/loop/inversion.py,
# standardises by the training data's spreads; a twin has none): the command's step in units of
# a uniform command's spread over the rig's range, i_max / sqrt(12), the force's error in 1 kN
# (the order of the simulated matrix's force spread, 949 N)
CONTINUITY_FORCE_N = 1000.0


@dataclass(frozen=True)
class TwinModel:
    """A plant file as a forward model: its force is eq. 30 plus the offset, of x, xd and the
    command (through eq. 36). The fields the daemon's model checks read (`model_fit`: units,
    sample period; `coverage`: no envelope) are those of a model of x, xd and the command."""

    plant: Plant
    source: str = "twin"

    @property
    def input_names(self) -> list[str]:
        return ["x", "xd", "current"]

    @property
    def input_units(self) -> list[str]:
        return ["m", "m/s", self.plant.command_unit]

    output_name = "force"
    output_unit = "N"

    @property
    def meta(self) -> dict[str, Any]:
        """The command's unit (checked against the rig's) and its lag (eq. 36: 1/eta)."""
        return {
            "kind": "bouc-wen-twin",
            "command_unit": self.plant.command_unit,
            "current_input": "lagged",
            "lag_tau_s": 1.0 / self.plant.params.eta,
        }

    def tracker(self, dt_s: float, i_max: float, continuity: float = 0.0) -> TwinTracker:
        """The model carried frame to frame and inverted (`TwinTracker`)."""
        return TwinTracker(self, dt_s, i_max, continuity)


def forward_model_from_text(text: str, path: str | Path) -> MLP | TwinModel | GRUModel:
    """A forward model file's content: a plant file (`format` "mrrig-plant") as a `TwinModel`,
    a `mrrig-greybox/1` file as a `greybox.GreyBoxModel` (a TwinModel),
    a `mrrig-gru/1` file as a `GRUModel`, anything else as `MLP.from_text` reads it. One-line
    ModelError for a bad file, or one outside a physical range
    (`model_plausibility.check_plausible`)."""
    from mrrig.loop.model_plausibility import check_plausible

    model = _forward_model(text, path)
    check_plausible(model, path)
    return model


def _forward_model(text: str, path: str | Path) -> MLP | TwinModel | GRUModel:
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError):
        doc = None  # MLP.from_text says what is wrong with it
    if is_gru_doc(doc):  # a recurrent forward model (mrrig/loop/gru.py)
        return GRUModel.from_doc(doc, path)
    from mrrig.loop.greybox import GreyBoxModel, is_greybox_doc

    if is_greybox_doc(doc):  # the twin and a network on its residual (mrrig/loop/greybox.py)
        return GreyBoxModel.from_doc(doc, path)
    if not isinstance(doc, dict) or doc.get("format") != PLANT_FORMAT:
        return MLP.from_text(text, path)
    try:
        return TwinModel(parse_plant(doc, Path(path)), str(path))
    except ValueError as exc:
        raise ModelError(str(exc)) from None


def load_forward_model(path: str | Path) -> MLP | TwinModel | GRUModel:
    """Read a forward model file: a network (`mrrig-mlp/1`) or a twin (a plant file)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ModelError(f"{path}: cannot read: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ModelError(f"{path}: not a JSON model file: {exc}") from None
    return forward_model_from_text(text, path)


def force_root(
    k: tuple,
    z: float,
    y: float,
    x: float,
    xd: float,
    target_n: float,
    lo: float,
    hi: float,
    near: float,
) -> float:
    """The u in [lo, hi] whose eq. 30 force (no offset) at the state (z, y) and the motion
    (x, xd) is `target_n`: a root of a quadratic (the one nearer `near` where two are in the
    range); without one, the end of the range whose force is nearer the target."""
    c0a, c0b, k0, c1a, c1b, k1, x0, aa, ab = k[:9]
    # eq. 30 with eqs 32-35: (c1a + c1b u) (p + q u) / (d0 + d1 u) + k1 (x - x0)
    p = aa * z + c0a * xd + k0 * (x - y)
    q = ab * z + c0b * xd
    d0, d1 = c0a + c1a, c0b + c1b
    t = target_n - k1 * (x - x0)
    a2 = c1b * q
    a1 = c1a * q + c1b * p - t * d1
    a0 = c1a * p - t * d0
    roots: tuple[float, ...] = ()
    if abs(a2) * max(abs(lo), abs(hi), 1.0) <= 1e-12 * (abs(a1) + abs(a0)):
        if a1 != 0.0:
            roots = (-a0 / a1,)
    else:
        disc = a1 * a1 - 4.0 * a2 * a0
        if disc >= 0.0:
            s = -0.5 * (a1 + math.copysign(math.sqrt(disc), a1))
            roots = (s / a2, a0 / s) if s != 0.0 else (0.0,)
    inside = [r for r in roots if lo <= r <= hi and d0 + d1 * r > 0.0]
    if inside:
        return min(inside, key=lambda r: abs(r - near))
    # no root: the force misses the target on the same side at both ends; the nearer end
    f_lo, f_hi = bouc_wen_force(z, y, lo, x, xd, k), bouc_wen_force(z, y, hi, x, xd, k)
    if f_lo < target_n and f_hi < target_n:
        return lo if f_lo >= f_hi else hi
    return lo if f_lo <= f_hi else hi


def force_slope(k: tuple, z: float, y: float, x: float, xd: float, u: float) -> float:
    """d(eq. 30)/du at the state (z, y), the motion (x, xd) and u (N per command unit)."""
    c0a, c0b, k0, c1a, c1b, _k1, _x0, aa, ab = k[:9]
    p = aa * z + c0a * xd + k0 * (x - y)
    q = ab * z + c0b * xd
    c1, d = c1a + c1b * u, c0a + c1a + (c0b + c1b) * u
    return (c1b * (p + q * u) + c1 * q) / d - c1 * (p + q * u) * (c0b + c1b) / (d * d)


class TwinTracker:
    """One damper's twin, carried frame to frame and inverted (module docstring)."""

    def __init__(
        self, model: TwinModel, dt_s: float, i_max: float, continuity: float = 0.0
    ) -> None:
        if not continuity >= 0:
            raise ValueError(f"continuity must be >= 0, got {continuity}")
        # mu over the squared scales (`CONTINUITY_FORCE_N`, i_max / sqrt(12)): (N/A)^2
        self._pull = continuity * CONTINUITY_FORCE_N**2 * 12.0 / i_max**2
        params = model.plant.params
        self._k = astuple(params)
        self.offset_n = model.plant.offset_n
        self.dt_s = dt_s
        self.i_max = i_max
        self.damper = BoucWenDamper(params, SUBSTEP_S)
        # eq. 36 over one period, the command v held: u(T) = u + lag (v - u)
        self.lag = -math.expm1(-params.eta * dt_s)
        self.x = self.xd = 0.0
        self.command = 0.0  # the command held since the last frame
        self.started = False

    def reset(self) -> None:
        """The next `advance` starts the twin at rest (z = 0, y = x, u = 0: the coil off)."""
        self.started = False
        self.command = 0.0

    def advance(self, x: float, xd: float) -> float:
        """Advance the state to this frame's motion with the command held since the last one;
        the twin's force now (eq. 30 plus the offset)."""
        if self.started:
            f = self.damper.step(x, xd, self.command, self.dt_s)
        else:
            f = self.damper.reset(x, xd, 0.0)
            self.started = True
        self.x, self.xd = x, xd
        return f + self.offset_n

    def force(self, x: float, xd: float, u: float) -> float:
        """Eq. 30 plus the offset at the twin's present (z, y), the motion (x, xd) and u."""
        z, y, _ = self.damper.state
        return bouc_wen_force(z, y, u, x, xd, self._k) + self.offset_n

    def solve(self, target_n: float, x1: float | None = None, xd1: float | None = None) -> float:
        """The command for the force `target_n` one period on, clamped to [0, i_max]: at the
        motion (x1, xd1) then (the state stepped there, the previous command held), or, without
        it, at the present motion and state. Becomes the command held until the next frame."""
        d = self.damper
        z, y, u = d.state
        x, xd = self.x, self.xd
        if x1 is not None and xd1 is not None:
            d.step(x1, xd1, self.command, self.dt_s)
            z1, y1, _ = d.state
            d.set_state((z, y, u), self.x, self.xd)
            z, y, x, xd = z1, y1, x1, xd1
        lag = self.lag
        # eq. 36: the commands 0 and i_max take u to these one period on
        lo, hi = u - lag * u, u + lag * (self.i_max - u)
        u1 = force_root(self._k, z, y, x, xd, target_n - self.offset_n, lo, hi, u)
        if self._pull > 0.0:
            # min (f(u1) - target)^2 + pull (u1 - u)^2: from the root, the step of the
            # linearised problem (inversion.py's closed form), toward u: inside [lo, hi]
            g = force_slope(self._k, z, y, x, xd, u1)
            u1 += (u - u1) / (1.0 + g * g / self._pull)
        v = u + (u1 - u) / lag  # eq. 36 inverted: u reaches u1 one period on
        self.command = min(max(v, 0.0), self.i_max)
        return self.command
