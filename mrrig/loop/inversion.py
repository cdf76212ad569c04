"""Network inversion (paper eqs 2-14): the current that makes the forward MLP give a force.

With the weights frozen, the force is a function of the current alone for each sample:

    f(i) = f0 + sum_h v_h tanh(k_h + w_h i),   k = feature part of the pre-activation (eq. 5)

Three methods:
- `gradient_inversion`: the paper's reference, gradient descent on E = 1/2 (f_d - f_net)^2
  (eqs 2-3) with the analytic gradient of eq. 14, from a random start.
- `flow_inversion`: the same descent's end point taken as its continuous flow over the same
  descent time, in a few exponential-Euler steps instead of 1000 iterations.
- `exact_inversion` (the default): bracket the roots of f(i) - f_d on a grid over [0, i_max],
  take the root nearest the previous command, refine it by safeguarded Newton with the same
  analytic derivative; saturate at the nearest bound when the force is out of reach.
  With a continuity weight mu > 0 it solves, just as exactly, the regularised problem

      min over i in [0, i_max] of  (f(i) - f_d)^2 / s_f^2 + mu (i - i_prev)^2 / s_i^2

  (s_f, s_i: the model's force and current scalers). Where df/di is large the answer is the
  root; where the force hardly depends on the current (velocity reversals) it stays near the
  previous command instead of jumping across the range. mu = 1 matches the smoothing of the
  paper's on-line gradient method (rate 0.001 x 1000 iterations = unit descent time in the
  same standardised units): linearised, that method ends (i_prev - i*) exp(-g^2) from the
  root, the regularised solve (i_prev - i*) / (1 + g^2 / mu), g = the standardised df/di.
  The smoothing is per sample, so its time scale depends on the sample period: mu = 1 helps
  the paper's 1 ms study and hurts the rig's 2 ms loop. The daemon's default is the model's
  own mu, chosen on its training rows by `mrrig train` (`training.choose_continuity`), and
  the root (mu = 0) for a model without one.
`ScalarInverter` is the one-sample path of both for the real-time loop.

Features are the model's inputs without the current, in the model's order, physical units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mrrig.loop.mlp import MLP

DEFAULT_CONTINUITY = 0.0  # mu of the exact solve without another choice: the root itself
PAPER_CONTINUITY = 1.0  # mu equivalent to the paper's on-line gradient method (module docstring)
# flow_inversion: steps per unit of descent time; within 2 mV rms of the paper's 1000
# iterations (bench paper), the root to 1e-9 A at descent time 100 (tests)
FLOW_STEPS = 4
GRID_BLOCK_ROWS = 128  # rows of the exact solve's grid evaluated at a time (`_on_grid`)


def flow_steps(duration: float) -> int:
    """The flow's exponential-Euler steps for a descent time: `FLOW_STEPS` per unit of it."""
    return FLOW_STEPS * max(1, math.ceil(duration))


@dataclass(frozen=True)
class _Split:
    """The model's pre-activation split into a feature part and a current part.

    Physical units: pre = features @ A.T + a0 + w * current_a; force = f0 + v . tanh(pre).
    Standardised units (as trained): pre = z_features @ W1f.T + b1 + W1c * current_std.
    """

    A: np.ndarray  # H x (n-1), per physical feature unit
    a0: np.ndarray  # H
    w: np.ndarray  # H, per ampere
    v: np.ndarray  # H, N per unit of hidden output
    vw: np.ndarray  # H, v * w
    f0: float
    c: int
    c_mean: float
    c_std: float

    @classmethod
    def of(cls, model: MLP) -> _Split:
        c = model.current_index
        if c is None:
            raise ValueError("network inversion needs a model with an input named 'current'")
        others = [j for j in range(model.n_in) if j != c]
        A = model.W1[:, others] / model.in_std[others]
        c_mean, c_std = float(model.in_mean[c]), float(model.in_std[c])
        w = model.W1[:, c] / c_std
        a0 = model.b1 - A @ model.in_mean[others] - w * c_mean
        v = model.out_std * model.W2
        return cls(
            A=A,
            a0=a0,
            w=w,
            v=v,
            vw=v * w,
            f0=model.out_mean + model.out_std * model.b2,
            c=c,
            c_mean=c_mean,
            c_std=c_std,
        )

    def features_part(self, features: np.ndarray) -> np.ndarray:
        """k (N x H): the pre-activation without the current term."""
        return features @ self.A.T + self.a0


def _as_batch(model: MLP, features: np.ndarray, f_des: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    features = np.asarray(features, dtype=np.float64)
    if features.ndim != 2 or features.shape[1] != model.n_in - 1:
        raise ValueError(
            f"features must be (N, {model.n_in - 1}) (inputs without the current), "
            f"got {features.shape}"
        )
    f_des = np.broadcast_to(np.asarray(f_des, dtype=np.float64), (features.shape[0],))
    return features, f_des


def eq14_gradient(
    model: MLP, X: np.ndarray, f_des: np.ndarray, standardised: bool = False
) -> np.ndarray:
    """dE/dcurrent (N,) of E = 1/2 (f_des - f_net(X))^2 at the full inputs X (N x n_in).

    Physical units (N^2/A) by default; `standardised=True` gives the gradient w.r.t. the
    standardised current of E in standardised force units, the quantity the paper's
    normalised MATLAB network descends on.
    """
    c = model.current_index
    if c is None:
        raise ValueError("eq14_gradient needs a model with an input named 'current'")
    X = np.asarray(X, dtype=np.float64)
    z = (X - model.in_mean) / model.in_std
    o = np.tanh(z @ model.W1.T + model.b1)  # eqs 5, 7
    f_net_s = o @ model.W2 + model.b2  # eq. 12: linear output
    f_des_s = (np.asarray(f_des, dtype=np.float64) - model.out_mean) / model.out_std
    # eq. 14 = eq. 11 * sum over hidden of eq. 8 * eq. 9 * eq. 13
    grad_s = (f_net_s - f_des_s) * ((1.0 - o * o) @ (model.W1[:, c] * model.W2))
    if standardised:
        return grad_s
    return grad_s * model.out_std**2 / model.in_std[c]


def _descent_start(
    model: MLP,
    features: np.ndarray,
    f_des: np.ndarray,
    i_max: float,
    i0: np.ndarray | None,
    rng: np.random.Generator | None,
) -> tuple[_Split, np.ndarray, np.ndarray, np.ndarray]:
    """The paper's descent in standardised units, as its MATLAB network (normalised inputs and
    output) ran it: (split, start current i_s, feature part k_s, target f_des_s), so that
    pre = k_s + W1c * i_s and f_s = W2 . o + b2. The start is uniform on [0, i_max] without i0.
    """
    features, f_des = _as_batch(model, features, f_des)
    s = _Split.of(model)
    n = features.shape[0]
    if i0 is None:
        i0 = (rng if rng is not None else np.random.default_rng()).uniform(0.0, i_max, n)
    i_s = (np.broadcast_to(np.asarray(i0, dtype=np.float64), (n,)) - s.c_mean) / s.c_std
    k_s = s.features_part(features) + s.w * s.c_mean
    return s, i_s, k_s, (f_des - model.out_mean) / model.out_std


def gradient_inversion(
    model: MLP,
    features: np.ndarray,
    f_des: np.ndarray,
    *,
    i_max: float,
    rate: float = 1e-3,
    iterations: int = 1000,
    i0: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """The paper's inversion: `iterations` steps of eq. 2 from i0 (default uniform on [0, i_max]).

    The descent runs in standardised current and force units, as the paper's MATLAB network
    (normalised inputs and output) did: rate 0.001 on E in N^2 w.r.t. amperes would diverge.
    The result is clipped to [0, i_max]. Returns currents (N,) in A.
    """
    s, i_s, k_s, f_des_s = _descent_start(model, features, f_des, i_max, i0, rng)
    W1c = model.W1[:, s.c]
    w_sum = W1c * model.W2
    for _ in range(iterations):
        o = np.tanh(k_s + np.multiply.outer(i_s, W1c))  # eqs 5, 7
        grad = (o @ model.W2 + model.b2 - f_des_s) * ((1.0 - o * o) @ w_sum)  # eq. 14
        i_s = i_s - rate * grad  # eq. 2
    return np.clip(i_s * s.c_std + s.c_mean, 0.0, i_max)


def flow_inversion(
    model: MLP,
    features: np.ndarray,
    f_des: np.ndarray,
    *,
    i_max: float,
    duration: float = 1.0,
    steps: int | None = None,
    i0: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """The end point of the paper's descent taken as its continuous flow, fast.

    `gradient_inversion` makes small steps of di/dt = -dE/di (eqs 2, 14) for a descent time
    `duration` = rate x iterations (1 for the paper's 0.001 x 1000) in standardised units.
    Linearised at i, the force error e decays as exp(-g^2 t) (g = the standardised df/di), so
    each of `steps` exponential-Euler steps of h = duration / steps moves i by
    -(e / g) (1 - exp(-g^2 h)): a Newton step where g is large, a gradient step e g h where
    it is small. The result is clipped to [0, i_max], as the paper's; same start as it.
    `steps` defaults to `flow_steps(duration)`.
    """
    steps = flow_steps(duration) if steps is None else steps
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    s, i_s, k_s, f_des_s = _descent_start(model, features, f_des, i_max, i0, rng)
    W1c = model.W1[:, s.c]
    w_sum = W1c * model.W2
    h = duration / steps
    for _ in range(steps):
        o = np.tanh(k_s + np.multiply.outer(i_s, W1c))  # eqs 5, 7
        e = o @ model.W2 + model.b2 - f_des_s  # eq. 11's error, standardised
        g = (1.0 - o * o) @ w_sum  # eq. 14 without the error factor
        g2h = g * g * h
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(g2h > 1e-12, -np.expm1(-g2h) * e / g, e * g * h)
        i_s = i_s - step
    return np.clip(i_s * s.c_std + s.c_mean, 0.0, i_max)


def exact_inversion(
    model: MLP,
    features: np.ndarray,
    f_des: np.ndarray,
    i_prev: np.ndarray | float,
    *,
    i_max: float,
    grid_points: int = 33,
    xtol_a: float = 1e-6,
    max_iter: int = 60,
    continuity: float = 0.0,
) -> np.ndarray:
    """Currents (N,) in [0, i_max] with f_net(features, i) = f_des, vectorised over samples.

    Roots are bracketed on `grid_points` currents; of several, the one nearest `i_prev`
    (judged by the secant estimate in each bracket) is refined by Newton steps, bisecting
    when a step leaves the bracket, until a step is below `xtol_a`. Two roots inside one grid
    cell are not seen. No root: the bound whose force is nearest f_des (tie: nearest i_prev).
    `continuity` > 0: the regularised problem of the module docstring instead (`_regularised`).
    """
    features, f_des = _as_batch(model, features, f_des)
    s = _Split.of(model)
    n = features.shape[0]
    i_prev = np.broadcast_to(np.asarray(i_prev, dtype=np.float64), (n,))
    if continuity < 0:
        raise ValueError(f"continuity must be >= 0, got {continuity}")
    grid = np.linspace(0.0, i_max, grid_points)
    k = s.features_part(features)
    c = s.f0 - f_des
    if continuity > 0:
        return _regularised(s, model, k, c, i_prev, grid, continuity, xtol_a, max_iter)
    g = _on_grid(s, k, grid) + c[:, None]  # N x G
    g_lo, g_hi = g[:, :-1], g[:, 1:]
    bracket = g_lo * g_hi <= 0.0
    denom = g_lo - g_hi
    with np.errstate(divide="ignore", invalid="ignore"):
        r = grid[:-1] + np.where(denom != 0.0, g_lo / denom, 0.0) * (grid[1] - grid[0])
    cell = np.argmin(np.where(bracket, np.abs(r - i_prev[:, None]), np.inf), axis=1)
    found = bracket.any(axis=1)
    rows = np.arange(n)

    out = np.empty(n)
    # Out of reach: saturate at the bound with the nearer force.
    miss = ~found
    e0, e1 = np.abs(g[miss, 0]), np.abs(g[miss, -1])
    upper = (e1 < e0) | ((e1 == e0) & (np.abs(i_max - i_prev[miss]) < np.abs(i_prev[miss])))
    out[miss] = np.where(upper, i_max, 0.0)

    idx = rows[found]
    cf = cell[found]
    lo, hi = grid[cf], grid[cf + 1]
    glo = g_lo[found, cf]
    x = r[found, cf]
    kk, cc = k[found], c[found]
    active = np.ones(idx.size, dtype=bool)
    for _ in range(max_iter):
        if not active.any():
            break
        a = np.flatnonzero(active)
        t = np.tanh(kk[a] + x[a, None] * s.w)  # eqs 5, 7
        gx = t @ s.v + cc[a]
        dg = s.vw.sum() - (t * t) @ s.vw  # df/di: eq. 14 without the error factor
        same = np.sign(gx) == np.sign(glo[a])
        lo[a] = np.where(same, x[a], lo[a])
        glo[a] = np.where(same, gx, glo[a])
        hi[a] = np.where(same, hi[a], x[a])
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = x[a] - gx / dg
        bad = ~((xn > lo[a]) & (xn < hi[a]))
        xn = np.where(bad, 0.5 * (lo[a] + hi[a]), xn)
        done = (gx == 0.0) | (np.abs(xn - x[a]) <= xtol_a)
        x[a] = np.where(gx == 0.0, x[a], xn)
        active[a[done]] = False
    out[idx] = x
    return out


def _on_grid(s: _Split, k: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """f - f0 (N x G) at every grid current of every row (eqs 5, 7, 12), `GRID_BLOCK_ROWS`
    rows at a time, so that the N x G x H hidden outputs (8 kB a row for the paper's 33 x 30)
    never exist at once and each block stays in the cache. The same numbers as one product
    of all rows."""
    n = k.shape[0]
    gw = grid[:, None] * s.w
    out = np.empty((n, grid.size))
    buf = np.empty((min(GRID_BLOCK_ROWS, n), grid.size, s.w.size))
    for a in range(0, n, GRID_BLOCK_ROWS):
        t = buf[: min(GRID_BLOCK_ROWS, n - a)]
        np.add(k[a : a + GRID_BLOCK_ROWS, None, :], gw, out=t)
        np.tanh(t, out=t)  # eqs 5, 7
        np.matmul(t, s.v, out=out[a : a + GRID_BLOCK_ROWS])
    return out


def _objective_weights(s: _Split, model: MLP, continuity: float) -> tuple[float, float]:
    """(a, b) of J(i) = a (f(i) - f_d)^2 + b (i - i_prev)^2, the module docstring's objective."""
    return 1.0 / float(model.out_std) ** 2, continuity / s.c_std**2


def _vertex(J: np.ndarray, j: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Newton's start for each row: the vertex of the parabola through J at the grid's best
    point j and its two neighbours (where that parabola opens upwards; else the point
    itself), so that Newton needs a step fewer. It lies within half a cell of j."""
    inner = (j > 0) & (j < grid.size - 1)
    rows = np.arange(j.size)
    jm = np.where(inner, j - 1, j)
    jn = np.where(inner, j + 1, j)
    left, mid, right = J[rows, jm], J[rows, j], J[rows, jn]
    curv = left - 2.0 * mid + right
    h = grid[1] - grid[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(inner & (curv > 0.0), 0.5 * h * (left - right) / curv, 0.0)
    return grid[j] + shift


def _regularised(
    s: _Split,
    model: MLP,
    k: np.ndarray,
    c: np.ndarray,
    i_prev: np.ndarray,
    grid: np.ndarray,
    continuity: float,
    xtol_a: float,
    max_iter: int,
) -> np.ndarray:
    """Minimise J over [0, i_max] for each row: the grid's best point, then safeguarded Newton
    on J' = 2 (a g f' + b (i - i_prev)) inside its two neighbouring cells (bisecting on the sign
    of J' when a step leaves the bracket or J'' <= 0), until a step is below xtol_a."""
    a, b = _objective_weights(s, model, continuity)
    g = _on_grid(s, k, grid) + c[:, None]
    J = a * g * g + b * (grid - i_prev[:, None]) ** 2
    j = np.argmin(J, axis=1)
    last = grid.size - 1
    lo = grid[np.maximum(j - 1, 0)]
    hi = grid[np.minimum(j + 1, last)]
    x = _vertex(J, j, grid)
    active = np.ones(x.size, dtype=bool)
    for _ in range(max_iter):
        if not active.any():
            break
        r = np.flatnonzero(active)
        th = np.tanh(k[r] + x[r, None] * s.w)  # eqs 5, 7
        gx = th @ s.v + c[r]
        sech2 = 1.0 - th * th
        d1 = sech2 @ s.vw  # df/di: eq. 14 without the error factor
        d2 = -2.0 * (th * sech2) @ (s.vw * s.w)  # d2f/di2
        jp = a * gx * d1 + b * (x[r] - i_prev[r])  # J'/2
        jpp = a * (d1 * d1 + gx * d2) + b  # J''/2
        up = jp > 0.0
        hi[r] = np.where(up, x[r], hi[r])
        lo[r] = np.where(up, lo[r], x[r])
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = np.where(jpp > 0.0, x[r] - jp / jpp, np.nan)
        bad = ~((xn > lo[r]) & (xn < hi[r]))
        xn = np.where(bad, 0.5 * (lo[r] + hi[r]), xn)
        done = (np.abs(xn - x[r]) <= xtol_a) | (hi[r] - lo[r] <= xtol_a)
        x[r] = xn
        active[r[done]] = False
    return x


class ScalarInverter:
    """One sample at a time, for the real-time loop; same results as the batch functions.

    method "exact" (default) or "gradient" (the paper's; random start from `seed`);
    `continuity` is the exact solve's weight mu (0: the root itself).

    Solving ahead: `prepare(features, f_des, i_prev)` runs the whole exact solve on a
    predicted sample (the daemon predicts the next frame's state while it waits for it) and
    keeps the answer and where it lies. The next `solve` with the same `i_prev` then starts
    Newton from that answer on the measured sample and skips the grid: the two samples differ
    by a Kalman innovation, so Newton converges in a step or two. It must converge (a step
    below `xtol_a`) within `AHEAD_ITERATIONS` steps without leaving the answer's cell and
    its two neighbours, and for the regularised problem with J'' > 0 throughout; otherwise
    the full solve runs. A root is followed ahead only when it is alone in those cells and
    nearer to `i_prev` than any other root by a grid cell, so that the small difference of
    the two samples cannot change which root the full solve would pick.
    `ahead_used` / `ahead_missed` count the solves that were and were not saved.
    """

    AHEAD_ITERATIONS = 4

    def __init__(
        self,
        model: MLP,
        i_max: float,
        method: str = "exact",
        *,
        grid_points: int = 33,
        xtol_a: float = 1e-6,
        max_iter: int = 60,
        rate: float = 1e-3,
        iterations: int = 1000,
        seed: int | None = None,
        continuity: float = 0.0,
    ) -> None:
        if method not in ("exact", "gradient"):
            raise ValueError(f"unknown inversion method {method!r} (exact, gradient)")
        if continuity < 0:
            raise ValueError(f"continuity must be >= 0, got {continuity}")
        self.model = model
        self.method = method
        self.i_max = float(i_max)
        self.xtol_a, self.max_iter = xtol_a, max_iter
        self.rate, self.iterations = rate, iterations
        self._rng = np.random.default_rng(seed)
        s = _Split.of(model)
        self._s = s
        self._grid = np.linspace(0.0, self.i_max, grid_points)
        self._h = float(self._grid[1] - self._grid[0])
        self._grid_list = self._grid.tolist()
        # The hidden layer gets one extra unit, so that one product does what took two calls:
        # its pre-activation is 40 on the grid (tanh exactly 1) with output weight f0 - f_d
        # (`_v_c`), so the grid's product is f - f_d; it is 0 (tanh 0) in `_at`.
        # `_kw`: rows k (this sample's feature part, eq. 5) and w, so [1, x] . _kw = k + w x.
        self._grid_w = np.column_stack([self._grid[:, None] * s.w, np.full(grid_points, 40.0)])
        self._buf_g = np.empty_like(self._grid_w)
        self._g = np.empty(grid_points)
        self._d = np.empty(grid_points)
        self._kw = np.zeros((2, model.hidden + 1))
        self._kw[1, :-1] = s.w
        self._k_ext = self._kw[0]
        self._k = self._k_ext[:-1]
        self._one_x = np.array([1.0, 0.0])
        self._v_c = np.append(s.v, 0.0)
        self._buf_h = np.empty(model.hidden)
        self._vw_sum = float(s.vw.sum())
        self.continuity = float(continuity)
        self._a, self._b = _objective_weights(s, model, self.continuity)
        # Newton's f, f' and f'' (`_at`): tanh, tanh^2 and tanh^3 of the hidden units in the
        # rows of one buffer, times [v, vw, vw w] (0 for the extra unit) in one product
        self._powers = np.empty((3, model.hidden + 1))
        self._th, self._th2, self._th3 = self._powers
        self._weights = np.vstack([np.column_stack([s.v, s.vw, s.vw * s.w]), np.zeros(3)])
        # the grid part of J / a: (f - f_d)^2 + (b / a) (i - i_prev)^2 = hypot(g, d)^2 with
        # d = sqrt(b / a) (grid - i_prev); the same argmin and vertex as J
        self._root_ba = math.sqrt(self._b / self._a)
        self._grid_ba = self._grid * self._root_ba
        self._ahead: tuple[float, float, float, float] | None = None  # i_prev, x, lo, hi
        self.ahead_used = 0
        self.ahead_missed = 0
        self._W1c = model.W1[:, s.c]
        self._w_sum = self._W1c * model.W2

    def force(self, features: np.ndarray, current_a: float) -> float:
        """The model's force (N) for one sample at `current_a` (eqs 5, 7, 12)."""
        s, k = self._s, self._buf_h
        np.dot(s.A, features, out=k)
        k += s.a0
        k += s.w * current_a
        np.tanh(k, out=k)
        return float(k @ s.v) + s.f0

    def _features_part(self, features: np.ndarray) -> None:
        """Write the sample's feature part k of the pre-activations (eq. 5) where `_full` and
        `_at` read it."""
        k = self._k
        np.dot(self._s.A, features, out=k)
        k += self._s.a0

    def solve(self, features: np.ndarray, f_des: float, i_prev: float) -> float:
        """Current in A for one sample; features = the model's inputs without the current.
        A non-finite f_des has no current: NaN, for the caller's finiteness check."""
        if not math.isfinite(f_des):
            return math.nan
        if self.method == "gradient":
            return self._gradient(features, f_des)
        self._features_part(features)
        c = self._s.f0 - f_des
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead[0] == i_prev:
            x = self._newton_ahead(c, i_prev, ahead[1], ahead[2], ahead[3])
            if x is not None:
                self.ahead_used += 1
                return x
            self.ahead_missed += 1
        return self._full(c, i_prev)[0]

    def prepare(self, features: np.ndarray, f_des: float, i_prev: float) -> None:
        """Solve ahead on a predicted sample (class docstring); replaces an unused one."""
        self._ahead = None
        if self.method == "gradient":
            return
        self._features_part(features)
        x, lo, hi = self._full(self._s.f0 - f_des, i_prev)
        if lo < hi:
            self._ahead = (i_prev, x, lo, hi)

    def discard_prepared(self) -> None:
        self._ahead = None

    def _full(self, c: float, i_prev: float) -> tuple[float, float, float]:
        """(current, lo, hi): [lo, hi] is where a later Newton may follow this answer to a
        nearby sample; lo == hi when it must not (out of reach: a bound; an ambiguous pick)."""
        buf_g, g = self._buf_g, self._g
        np.add(self._grid_w, self._k_ext, out=buf_g)
        np.tanh(buf_g, out=buf_g)
        self._v_c[-1] = c
        np.dot(buf_g, self._v_c, out=g)  # f - f_d on the grid
        if self.continuity > 0.0:
            return self._regularised(c, g, i_prev)
        g = g.tolist()
        grid, h = self._grid_list, self._h
        best = second = np.inf
        cell = -1
        cells = []
        for j in range(len(g) - 1):
            gl, gh = g[j], g[j + 1]
            if gl * gh <= 0.0:
                cells.append(j)
                rj = grid[j] + (gl / (gl - gh) if gl != gh else 0.0) * h
                d = abs(rj - i_prev)
                if d < best:
                    second, best, cell, x, glo = best, d, j, rj, gl
                elif d < second:
                    second = d
        if cell < 0:
            e0, e1 = abs(g[0]), abs(g[-1])
            if e1 < e0 or (e1 == e0 and abs(self.i_max - i_prev) < abs(i_prev)):
                return self.i_max, self.i_max, self.i_max
            return 0.0, 0.0, 0.0
        cell_lo, cell_hi = grid[cell], grid[cell + 1]
        lo, hi = cell_lo, cell_hi
        for _ in range(self.max_iter):
            fx, dg, _ = self._at(x)
            gx = fx + c
            if gx == 0.0:
                break
            if (gx > 0.0) == (glo > 0.0) and glo != 0.0:
                lo, glo = x, gx
            else:
                hi = x
            xn = x - gx / dg if dg != 0.0 else np.nan
            if not lo < xn < hi:
                xn = 0.5 * (lo + hi)
            step = abs(xn - x)
            x = xn
            if step <= self.xtol_a:
                break
        # to be followed ahead, the root must be alone in its cell and the neighbouring ones,
        # and clearly the nearest: otherwise a small change of the sample may change the pick
        if second - best <= h or any(0 < abs(j - cell) <= 1 for j in cells):
            return x, x, x
        return x, max(cell_lo - h, 0.0), min(cell_hi + h, self.i_max)

    def _at(self, x: float) -> tuple[float, float, float]:
        """(f - f0, df/di, d2f/di2) of the network at the current x, for the sample whose
        feature part `_features_part` last wrote."""
        th, th2 = self._th, self._th2
        self._one_x[1] = x
        np.dot(self._one_x, self._kw, out=th)  # k + w x (k: this sample's, in self._kw)
        np.tanh(th, out=th)  # eqs 5, 7
        np.multiply(th, th, out=th2)
        np.multiply(th2, th, out=self._th3)
        # rows tanh^p, columns v, vw, vww
        (fv, _, fvww), (_, t2vw, _), (_, _, t3vww) = (self._powers @ self._weights).tolist()
        # df/di: eq. 14 without the error factor; d2f/di2 = -2 sum vww (tanh - tanh^3)
        return fv, self._vw_sum - t2vw, -2.0 * (fvww - t3vww)

    def _newton_ahead(
        self, c: float, i_prev: float, x: float, lo: float, hi: float
    ) -> float | None:
        """Newton from a prepared answer inside its cell; None when it does not converge there."""
        regularised = self.continuity > 0.0
        for _ in range(self.AHEAD_ITERATIONS):
            fx, d1, d2 = self._at(x)
            gx = fx + c
            if regularised:
                jpp = self._a * (d1 * d1 + gx * d2) + self._b  # J''/2
                if not jpp > 0.0:
                    return None
                xn = x - (self._a * gx * d1 + self._b * (x - i_prev)) / jpp  # J'/2 / (J''/2)
            else:
                if gx == 0.0:
                    return x
                if d1 == 0.0:
                    return None
                xn = x - gx / d1
            if not lo <= xn <= hi:
                return None
            if abs(xn - x) <= self.xtol_a:
                return xn
            x = xn
        return None

    def _regularised(self, c: float, g: np.ndarray, i_prev: float) -> tuple[float, float, float]:
        """`_regularised` of the batch path for one sample; g = f - f_d on the grid.
        Returns (current, lo, hi), [lo, hi] the four grid cells around the grid's best point
        (on a nearby sample the best point may move by one)."""
        a, b = self._a, self._b
        r = self._d
        np.subtract(self._grid_ba, i_prev * self._root_ba, out=r)
        np.hypot(g, r, out=r)  # sqrt(J / a) on the grid
        j = int(r.argmin())
        grid = self._grid_list
        lo, hi = grid[max(j - 1, 0)], grid[min(j + 1, len(grid) - 1)]
        cell_lo, cell_hi = grid[max(j - 2, 0)], grid[min(j + 2, len(grid) - 1)]
        x = grid[j]
        if 0 < j < len(grid) - 1:  # the parabola's vertex, as `_vertex`
            left, mid, right = (v * v for v in r[j - 1 : j + 2].tolist())
            curv = left - 2.0 * mid + right
            if curv > 0.0:
                x += 0.5 * self._h * (left - right) / curv
        for _ in range(self.max_iter):
            fx, d1, d2 = self._at(x)
            gx = fx + c  # f - f_d
            jp = a * gx * d1 + b * (x - i_prev)  # J'/2
            jpp = a * (d1 * d1 + gx * d2) + b  # J''/2
            if jp > 0.0:
                hi = x
            else:
                lo = x
            xn = x - jp / jpp if jpp > 0.0 else np.nan
            if not lo < xn < hi:
                xn = 0.5 * (lo + hi)
            step = abs(xn - x)
            x = xn
            if step <= self.xtol_a or hi - lo <= self.xtol_a:
                break
        return x, cell_lo, cell_hi

    def flow(self, features: np.ndarray, f_des: float, i0: float, duration: float = 1.0) -> float:
        """`flow_inversion` for one sample from i0, in plain floats."""
        m, s = self.model, self._s
        k_s = s.A @ features + s.a0 + s.w * s.c_mean
        f_des_s = (f_des - m.out_mean) / m.out_std
        W1c, w_sum, W2, b2 = self._W1c, self._w_sum, m.W2, float(m.b2)
        i_s = (i0 - s.c_mean) / s.c_std
        steps = flow_steps(duration)
        h = duration / steps
        for _ in range(steps):
            o = np.tanh(k_s + i_s * W1c)  # eqs 5, 7
            e = float(o @ W2) + b2 - f_des_s
            g = float((1.0 - o * o) @ w_sum)  # eq. 14 without the error factor
            g2h = g * g * h
            i_s -= -math.expm1(-g2h) * e / g if g2h > 1e-12 else e * g * h
        return min(max(i_s * s.c_std + s.c_mean, 0.0), self.i_max)

    def _gradient(self, features: np.ndarray, f_des: float) -> float:
        m, s = self.model, self._s
        W1c = m.W1[:, s.c]
        k_s = s.A @ features + s.a0 + s.w * s.c_mean
        f_des_s = (f_des - m.out_mean) / m.out_std
        w_sum = W1c * m.W2
        i_s = (self._rng.uniform(0.0, self.i_max) - s.c_mean) / s.c_std
        for _ in range(self.iterations):
            o = np.tanh(k_s + i_s * W1c)  # eqs 5, 7
            grad = (float(o @ m.W2) + m.b2 - f_des_s) * float((1.0 - o * o) @ w_sum)  # eq. 14
            i_s = i_s - self.rate * grad  # eq. 2
        return min(max(i_s * s.c_std + s.c_mean, 0.0), self.i_max)
