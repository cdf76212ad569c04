"""The fit: the modified Bouc-Wen model (`damper.plant`, eqs 30-36) and a force offset fitted
to measured force by `scipy.optimize.least_squares`. Pure numerics: arrays in, parameters out.

The model is simulated open loop from the measured displacement, velocity and command (never
the measured force), so its error is the twin's error. The objective's simulation runs the
data cut into windows, all windows and all the Jacobian's parameter sets in one numpy batch:
each window starts at rest (z = 0, y = x, u = command) `burn_in_s` before the rows it scores,
so that the state it starts with is forgotten (the hysteresis saturates within millimetres,
the command's filter within a few 1/eta). The integrator is RK4, each sample interval cut
into as many sub-steps as the stiff hysteresis needs for the largest speed of the batch (the
`damper.plant` bound) and the command's filter (h eta <= 2). The Et that is reported comes
from `damper.plant.simulate`, the integrator the simulator runs, over whole runs.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import astuple, dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from damper.plant import BoucWenParams, bouc_wen_force, bouc_wen_rates, simulate
from damper.plant_file import PARAM_NAMES

log = logging.getLogger(__name__)

# Fitted in log space (each stays > 0); n is fixed (the exponent's fit is ill-conditioned with
# gamma and beta), and so are x0 (its force k1 x0 is the offset's) and A (z's scale: alpha and
# A trade one for the other at n = 2, so one of them is free).
FREE = ("c0a", "c0b", "k0", "c1a", "c1b", "k1", "alpha_a", "alpha_b", "gamma", "beta", "eta")
_RK4_STABLE_H_LAMBDA = 2.0
JAC_STEP = 1e-4  # forward difference in log space (and in the offset's scaled unit)
MAX_SUBSTEPS = 400  # damper.plant's bound per step
# the command's filter at most this fast (1/s): the simulator's RK4 sub-steps (1e-4 s) hold
# h eta <= 2; a constant-command test cannot tell eta, and the fit would take it anywhere
ETA_MAX = 2e4
# The physical range of each fitted parameter, SI units, "cmd" the command's unit (V or A): a
# damper of the paper's class (Table 3; Spencer et al. 1997: kN forces, strokes of cm, a coil
# commanded with a few V or A). The lower bounds are where the term's force is negligible (about
# 0.1 N or less at the tests' mm and cm/s: the term as good as absent, which the fit may choose);
# the upper ones about 100 times Table 3's value or more (beyond, tens of kN at those scales, or
# a hysteresis loop thinner than the sensors' noise). Without them a fit to one test bought its
# last per mille with parameters no damper has (issue 43: Et 0.36 on another test of the Dyke
# damper, where a plain Bouc-Wen fit reaches about 0.21).
BOUNDS: dict[str, tuple[float, float]] = {
    "c0a": (1.0, 1e5),  # N s/m: the viscous damping at speed (Table 3: 784)
    "c0b": (1.0, 1e5),  # N s/(m cmd): its growth with the command (1803)
    "k0": (1.0, 1e5),  # N/m: the stiffness in series with c0 (3610)
    "c1a": (10.0, 1e7),  # N s/m: the damping that rolls the force off at low speed (14649)
    "c1b": (1.0, 1e7),  # N s/(m cmd): its growth with the command (34622)
    "k1": (1.0, 1e5),  # N/m: the accumulator's stiffness (840)
    "alpha_a": (10.0, 1e7),  # N/m: the hysteresis' force per metre of z (12441)
    "alpha_b": (10.0, 1e7),  # N/(m cmd): its growth with the command (38430)
    "gamma": (1e2, 1e9),  # 1/m^2: the loop's shape, with beta (136320)
    "beta": (1e2, 1e9),  # 1/m^2: (2059020); gamma + beta set z's saturation, sqrt(A/(g+b))
    "eta": (1.0, ETA_MAX),  # 1/s: the command's first-order lag, eq. 36 (190)
}
# Several starts: the objective (an open-loop simulation) is not convex, and from one start the
# trust region stopped where it began to crawl. The given start and STARTS - 1 drawn around it
# (each free parameter times a factor log-uniform within 1/START_SPREAD..START_SPREAD, seeded,
# within BOUNDS) are each fitted SCREEN_EVALUATIONS evaluations; the best on the fitted rows is
# fitted on. Four: each start costs about as much as 6 evaluations of the continued fit, so
# four of them stay under the continued fit's own cost (about 1 min on the Dyke file here).
STARTS = 4
START_SPREAD = 3.0
SCREEN_EVALUATIONS = 6
# A run scored from rest that starts moving: its first WARMUP_S not scored (the fit's burn-in,
# the hysteresis saturating within millimetres, eq. 36's lag within a few 1/eta); moving: its
# first speed over MOVING of its RMS speed (`warm_rows`)
WARMUP_S = 0.2
MOVING = 0.05
AT_BOUND = math.log(1.01)  # a fitted parameter within 1 % of a bound is reported at it


@dataclass(frozen=True)
class Run:
    """One contiguous run of measured samples in SI units; the command in its own unit."""

    t: np.ndarray
    x: np.ndarray
    xd: np.ndarray
    command: np.ndarray
    force: np.ndarray
    name: str = ""

    @property
    def period_s(self) -> float:
        """The run's sample period: its span over its sample count (times printed with few
        digits differ from sample to sample by the rounding)."""
        return float((self.t[-1] - self.t[0]) / (self.t.size - 1))


@dataclass(frozen=True)
class FitResult:
    """What the fit found: parameters, offset, and how it went."""

    params: BoucWenParams
    offset_n: float
    cost_et: float  # sqrt(2 cost) / sigma: the objective's own Et on the scored rows
    start_et: float
    evaluations: int
    seconds: float
    status: str
    # each start's Et on the fitted rows after its screening (`SCREEN_EVALUATIONS`), the
    # first the given start's; which start was fitted on; the parameters at a bound (1 %)
    start_ets: tuple[float, ...] = ()
    chosen_start: int = 0
    at_bounds: tuple[str, ...] = ()


@dataclass(frozen=True)
class _Windows:
    """Windows of samples (rows of equal length) and which of their samples are scored."""

    x: np.ndarray  # (K, W)
    xd: np.ndarray
    command: np.ndarray
    force: np.ndarray
    dt: np.ndarray  # (K,): each window's sample period
    scored: np.ndarray  # (K, W) bool


def windows(
    runs: list[Run], scored_rows: list[np.ndarray], window_s: float, burn_in_s: float
) -> _Windows:
    """Cut the runs into windows of `burn_in_s + window_s`, each scoring its last `window_s` of
    the `scored_rows` of its run (a bool mask per run) not scored by the window before; one
    length for all (the shortest run's period sets it). A run shorter than one window is
    one window of its own length padded with its last sample, unscored."""
    period = min(r.period_s for r in runs)
    n_score = max(1, round(window_s / period))
    n_burn = round(burn_in_s / period)
    width = n_score + n_burn
    parts: dict[str, list] = {k: [] for k in ("x", "xd", "command", "force", "dt", "scored")}
    for run, rows in zip(runs, scored_rows, strict=True):
        n = run.t.size
        idx_rows = np.flatnonzero(rows)
        if idx_rows.size == 0:
            continue
        first, last = int(idx_rows[0]), int(idx_rows[-1]) + 1
        for a in range(first, last, n_score):
            pos = np.arange(max(0, a - n_burn), max(0, a - n_burn) + width)
            idx = np.minimum(pos, n - 1)
            parts["x"].append(run.x[idx])
            parts["xd"].append(run.xd[idx])
            parts["command"].append(run.command[idx])
            parts["force"].append(run.force[idx])
            parts["dt"].append(run.period_s)
            parts["scored"].append((pos >= a) & (pos < min(a + n_score, last)) & rows[idx])
    if not parts["x"]:
        raise ValueError("no rows to fit")
    return _Windows(*(np.array(parts[k]) for k in ("x", "xd", "command", "force", "dt", "scored")))


def _stable_travel_m(k: tuple) -> np.ndarray:
    """The travel (m) a sub-step may cover and stay stable, per parameter set: 2 over
    |d(z')/dz| per m/s at the saturated |z| (eq. 31), as `damper.plant.BoucWenDamper`."""
    gamma, beta, a_, n = k[9], k[10], k[11], k[12]
    g = gamma + beta
    return _RK4_STABLE_H_LAMBDA / (g * n * (a_ / g) ** ((n - 1.0) / n))


def _hermite(x0, v0, x1, v1, dt, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Displacement and velocity at the fraction s of an interval: the cubic Hermite
    interpolant of its end points and velocities, as `damper.plant.BoucWenDamper` steps."""
    s2, s3 = s * s, s * s * s
    x = (2 * s3 - 3 * s2 + 1) * x0 + dt * (s3 - 2 * s2 + s) * v0
    x = x + (3 * s2 - 2 * s3) * x1 + dt * (s3 - s2) * v1
    v = (6 * s2 - 6 * s) / dt * (x0 - x1) + (3 * s2 - 4 * s + 1) * v0 + (3 * s2 - 2 * s) * v1
    return x, v


def simulate_windows(k: tuple, w: _Windows) -> np.ndarray:
    """Eq. 30's force (no offset) of P parameter sets (each entry of `k` of shape (P, 1)) over
    the K windows at once: (P, K, W). Non-finite where a parameter set blows up."""
    n_steps = w.x.shape[1]
    shape = (k[0].shape[0], w.x.shape[0])
    z = np.zeros(shape)
    y = np.broadcast_to(w.x[:, 0], shape).copy()
    u = np.broadcast_to(w.command[:, 0], shape).copy()
    out = np.empty((*shape, n_steps))
    out[:, :, 0] = bouc_wen_force(z, y, u, w.x[:, 0], w.xd[:, 0], k)
    travel = float(np.min(_stable_travel_m(k)))
    eta_max = float(np.max(k[13]))
    speed = np.maximum(np.abs(w.xd[:, 1:]), np.abs(w.xd[:, :-1])) * w.dt[:, None]
    need = np.maximum(np.max(speed, axis=0) / travel, float(np.max(w.dt)) * eta_max / 2.0)
    # at most the plant's sub-steps: a trial parameter set stiffer than that blows up (a large
    # residual) instead of holding the fit up
    m_steps = np.clip(np.ceil(need), 1, MAX_SUBSTEPS).astype(int)
    dt = w.dt
    with np.errstate(all="ignore"):
        for j in range(1, n_steps):
            x0, x1, v0, v1 = w.x[:, j - 1], w.x[:, j], w.xd[:, j - 1], w.xd[:, j]
            cmd = w.command[:, j - 1]  # held over the interval (zero-order hold)
            m = int(m_steps[j - 1])
            h = dt / m
            h2, h6 = 0.5 * h, h / 6.0
            nodes = [_hermite(x0, v0, x1, v1, dt, q / (2 * m)) for q in range(2 * m + 1)]
            for s in range(m):
                (xa, va), (xb, vb), (xc, vc) = nodes[2 * s : 2 * s + 3]
                z1, y1, u1 = bouc_wen_rates(z, y, u, xa, va, cmd, k)
                z2, y2, u2 = bouc_wen_rates(z + h2 * z1, y + h2 * y1, u + h2 * u1, xb, vb, cmd, k)
                z3, y3, u3 = bouc_wen_rates(z + h2 * z2, y + h2 * y2, u + h2 * u2, xb, vb, cmd, k)
                z4, y4, u4 = bouc_wen_rates(z + h * z3, y + h * y3, u + h * u3, xc, vc, cmd, k)
                z = z + h6 * (z1 + 2.0 * (z2 + z3) + z4)
                y = y + h6 * (y1 + 2.0 * (y2 + y3) + y4)
                u = u + h6 * (u1 + 2.0 * (u2 + u3) + u4)
            out[:, :, j] = bouc_wen_force(z, y, u, x1, v1, k)
    return out


class _Objective:
    """theta (log of the FREE parameters, then the offset over the force's spread) to the
    scored rows' residuals over the force's spread, for one or a batch of theta."""

    def __init__(
        self,
        start: BoucWenParams,
        w: _Windows,
        progress: Callable[[str], None],
        free: tuple[str, ...] = FREE,
    ):
        self.start = start
        self.free = free
        self.w = w
        self.target = w.force[w.scored]
        self.sigma = float(np.std(self.target)) or 1.0
        self.progress = progress
        self.evaluations = 0
        self.best = math.inf
        self.first_et = math.nan
        self.t0 = time.monotonic()

    def theta0(self, offset_n: float) -> np.ndarray:
        return np.append(np.log([getattr(self.start, n) for n in self.free]), offset_n / self.sigma)

    def params(self, theta: np.ndarray) -> tuple[BoucWenParams, float]:
        values = dict(zip(self.free, np.exp(theta[: len(self.free)]).tolist(), strict=True))
        return replace(self.start, **values), float(theta[-1]) * self.sigma

    def batch(self, thetas: np.ndarray) -> np.ndarray:
        """(P, rows) residuals for P parameter vectors."""
        base = np.array(astuple(self.start), dtype=float)
        k = np.tile(base, (thetas.shape[0], 1))
        for c, name in enumerate(self.free):
            k[:, PARAM_NAMES.index(name)] = np.exp(thetas[:, c])
        force = simulate_windows(tuple(k[:, [c]] for c in range(k.shape[1])), self.w)
        r = (force[:, self.w.scored] + thetas[:, [-1]] * self.sigma - self.target) / self.sigma
        # a parameter set that blows up: a large residual, not NaN, so the trust region shrinks
        return np.where(np.isfinite(r), r, 10.0)

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        r = self.batch(theta[None, :])[0]
        self.evaluations += 1
        et = float(np.sqrt(np.mean(r * r)))
        if self.evaluations == 1:
            self.first_et = et
        self.best = min(self.best, et)
        self.progress(
            f"evaluation {self.evaluations}: Et {et:.4f} on the fitted rows (best {self.best:.4f}"
            f", {time.monotonic() - self.t0:.0f} s)"
        )
        return r

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        thetas = np.tile(theta, (theta.size + 1, 1))
        thetas[1:] += np.eye(theta.size) * JAC_STEP
        r = self.batch(thetas)
        return ((r[1:] - r[0]) / JAC_STEP).T


def bounds(free: tuple[str, ...] = FREE) -> tuple[np.ndarray, np.ndarray]:
    """The log of the `free` parameters' `BOUNDS` (lower, upper)."""
    lo, hi = np.log([BOUNDS[n] for n in free]).T
    return lo, hi


def start_points(
    start: BoucWenParams, free: tuple[str, ...], starts: int, seed: int
) -> list[BoucWenParams]:
    """`start` (within `BOUNDS`) and `starts - 1` drawn around it: each free parameter times a
    factor log-uniform within 1/START_SPREAD..START_SPREAD (`seed`), within `BOUNDS`."""
    inside = {n: min(max(getattr(start, n), BOUNDS[n][0]), BOUNDS[n][1]) for n in free}
    lo, hi = bounds(free)
    base = np.log([inside[n] for n in free])
    rng = np.random.default_rng(seed)
    spread = math.log(START_SPREAD)
    drawn = [
        np.clip(base + rng.uniform(-spread, spread, base.size), lo, hi) for _ in range(starts - 1)
    ]
    return [replace(start, **inside)] + [
        replace(start, **dict(zip(free, np.exp(p).tolist(), strict=True))) for p in drawn
    ]


def fit(
    runs: list[Run],
    fit_rows: list[np.ndarray],
    start: BoucWenParams,
    offset_n: float = 0.0,
    window_s: float = 0.5,
    burn_in_s: float = 0.2,
    max_evaluations: int = 60,
    progress: Callable[[str], None] = log.info,
    free: tuple[str, ...] = FREE,
    starts: int = 1,
    seed: int = 0,
) -> FitResult:
    """Least-squares fit of the `free` parameters (of FREE, each within `BOUNDS`) and the
    force offset to the runs' force on `fit_rows` (a bool mask per run), from `start` (moved
    into `BOUNDS`; and `offset_n`); the others stay at `start`'s. With `starts` > 1, from
    `start_points` (`seed`), each fitted `SCREEN_EVALUATIONS` evaluations, the best on the
    fitted rows then fitted on up to `max_evaluations`."""
    t0 = time.monotonic()
    w = windows(runs, fit_rows, window_s, burn_in_s)
    lower, upper = bounds(free)
    lower, upper = np.append(lower, -np.inf), np.append(upper, np.inf)
    points = start_points(start, free, starts, seed)
    moved = [n for n in free if not BOUNDS[n][0] <= getattr(start, n) <= BOUNDS[n][1]]
    if moved:
        log.warning("the start's %s moved into the physical bounds (fit.BOUNDS)", ", ".join(moved))
    evaluations, start_et = 0, math.nan
    screened = []
    for j, point in enumerate(points if starts > 1 else []):
        label = f"start {j + 1} of {starts}: "
        obj = _Objective(point, w, lambda line, p=label: progress(p + line), free)
        sol = _solve(obj, obj.theta0(offset_n), lower, upper, SCREEN_EVALUATIONS)
        evaluations += obj.evaluations
        start_et = obj.first_et if j == 0 else start_et
        screened.append((float(np.sqrt(np.mean(sol.fun**2))), sol.x, obj))
    chosen, first, theta0 = 0, points[0], None
    if screened:
        chosen = min(range(len(screened)), key=lambda j: screened[j][0])
        theta0, first = screened[chosen][1], screened[chosen][2].start
        ets = " ".join(f"{e:.4f}" for e, _, _ in screened)
        progress(
            f"starts after {SCREEN_EVALUATIONS} evaluations each, Et on the fitted rows: {ets};"
            f" fitting on from start {chosen + 1}"
        )
    obj = _Objective(first, w, progress, free)
    if theta0 is None:
        theta0 = obj.theta0(offset_n)
    sol = _solve(obj, theta0, lower, upper, max_evaluations)
    evaluations += obj.evaluations
    start_et = obj.first_et if not screened else start_et
    params, offset = obj.params(sol.x)
    at = [
        n
        for n, v, lo, hi in zip(free, sol.x, lower, upper, strict=False)
        if min(v - lo, hi - v) < AT_BOUND
    ]
    return FitResult(
        params,
        offset,
        cost_et=float(np.sqrt(np.mean(sol.fun**2))),
        start_et=start_et,
        evaluations=evaluations,
        seconds=time.monotonic() - t0,
        status=sol.message,
        start_ets=tuple(e for e, _, _ in screened),
        chosen_start=chosen,
        at_bounds=tuple(at),
    )


def _solve(obj: _Objective, theta0: np.ndarray, lower, upper, max_evaluations: int):
    """`least_squares` (trust region within the bounds) of `obj` from `theta0`."""
    theta0 = np.clip(theta0, lower + 1e-9, upper - 1e-9)
    return least_squares(
        obj.residuals,
        theta0,
        jac=obj.jacobian,
        bounds=(lower, upper),
        method="trf",
        max_nfev=max_evaluations,
        x_scale="jac",
    )


def warm_rows(run: Run, warmup_s: float = WARMUP_S) -> np.ndarray:
    """The rows of a run the twin (run from rest at its first sample, `run_force`) is scored
    on: all of them where the run starts at rest; where it starts moving (its first speed over
    `MOVING` of its RMS speed), all but its first `warmup_s`, the warm-up stretch that takes
    the twin from rest to the state the motion gives it (a bool mask)."""
    rows = np.ones(run.t.size, dtype=bool)
    rms = float(np.sqrt(np.mean(run.xd**2)))
    if abs(float(run.xd[0])) > MOVING * rms:
        rows[: min(run.t.size, round(warmup_s / run.period_s))] = False
    return rows


def run_force(params: BoucWenParams, offset_n: float, run: Run, substep_s: float) -> np.ndarray:
    """The twin's force over a whole run, from rest at its first sample (`damper.plant
    .simulate`, the simulator's integrator), plus the offset."""
    t = run.t[0] + np.arange(run.t.size) * run.period_s
    return simulate(params, t, run.x, run.xd, run.command, substep_s) + offset_n
