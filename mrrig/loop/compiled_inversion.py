"""The network's force and its exact scalar current solve (network inversion) compiled: the
kernels of `mrrig.loop.compiled` for `ScalarInverter`, in its arithmetic's order (that module's
docstring says what runs compiled and why numba)."""

from __future__ import annotations

import math

import numpy as np

from mrrig.loop.compiled_kernels import njit
from mrrig.loop.inversion import ScalarInverter

# ---- the network and its exact scalar solve (inversion.ScalarInverter) -----------------------
# net rows: a0, w, v, v w, v w w, then A's columns (one row per feature); grid rows: the grid,
# the grid times sqrt(b / a); p: f0, h, xtol, max_iter, i_max, continuity, a, b, sqrt(b / a),
# sum(v w); st: prepared flag, i_prev, x, lo, hi, ahead used, ahead missed; work: k (H), g (G)
_P_F0, _P_H, _P_XTOL, _P_ITER, _P_IMAX, _P_MU, _P_A, _P_B, _P_RBA, _P_VWS = range(10)
_AHEAD_ITERATIONS = ScalarInverter.AHEAD_ITERATIONS


@njit
def _k_part(net, feat, k):  # noqa: ANN001, ANN202
    """k = A features + a0 (eq. 5's feature part)."""
    for h in range(net.shape[1]):
        acc = 0.0
        for j in range(feat.shape[0]):
            acc += net[5 + j, h] * feat[j]
        k[h] = acc + net[0, h]


@njit
def _at(net, k, x, vw_sum):  # noqa: ANN001, ANN202
    """(f - f0, df/di, d2f/di2) at the current x (`ScalarInverter._at`)."""
    fv = t2vw = fvww = t3vww = 0.0
    for h in range(net.shape[1]):
        t = math.tanh(k[h] + x * net[1, h])  # eqs 5, 7
        t2 = t * t
        t3 = t2 * t
        fv += t * net[2, h]
        t2vw += t2 * net[3, h]
        fvww += t * net[4, h]
        t3vww += t3 * net[4, h]
    return fv, vw_sum - t2vw, -2.0 * (fvww - t3vww)


@njit
def _full(net, grid, p, k, g, c, i_prev):  # noqa: ANN001, ANN202, C901, PLR0912, PLR0915
    """`ScalarInverter._full` (and its `_regularised`): (current, lo, hi)."""
    n = grid.shape[1]
    for j in range(n):
        acc = 0.0
        gj = grid[0, j]
        for h in range(net.shape[1]):
            acc += math.tanh(gj * net[1, h] + k[h]) * net[2, h]
        g[j] = acc + c  # f - f_d on the grid
    h = p[_P_H]
    xtol = p[_P_XTOL]
    max_iter = int(p[_P_ITER])
    i_max = p[_P_IMAX]
    vw_sum = p[_P_VWS]
    if p[_P_MU] > 0.0:
        a, b = p[_P_A], p[_P_B]
        for j in range(n):
            g[j] = math.hypot(g[j], grid[1, j] - i_prev * p[_P_RBA])  # sqrt(J / a) on the grid
        jb = 0
        for j in range(n):  # numpy's argmin: the first smallest, or the first NaN
            if math.isnan(g[j]):
                jb = j
                break
            if g[j] < g[jb]:
                jb = j
        j = jb
        lo, hi = grid[0, max(j - 1, 0)], grid[0, min(j + 1, n - 1)]
        cell_lo, cell_hi = grid[0, max(j - 2, 0)], grid[0, min(j + 2, n - 1)]
        x = grid[0, j]
        if 0 < j < n - 1:  # the parabola's vertex
            left, mid, right = g[j - 1] * g[j - 1], g[j] * g[j], g[j + 1] * g[j + 1]
            curv = left - 2.0 * mid + right
            if curv > 0.0:
                x += 0.5 * h * (left - right) / curv
        for _ in range(max_iter):
            fx, d1, d2 = _at(net, k, x, vw_sum)
            gx = fx + c
            jp = a * gx * d1 + b * (x - i_prev)  # J'/2
            jpp = a * (d1 * d1 + gx * d2) + b  # J''/2
            if jp > 0.0:
                hi = x
            else:
                lo = x
            xn = x - jp / jpp if jpp > 0.0 else math.nan
            if not lo < xn < hi:
                xn = 0.5 * (lo + hi)
            step = abs(xn - x)
            x = xn
            if step <= xtol or hi - lo <= xtol:
                break
        return x, cell_lo, cell_hi
    best = second = math.inf
    cell = -1
    x = glo = 0.0
    near = False  # another root in a neighbouring cell of the nearest one
    for j in range(n - 1):
        gl, gh = g[j], g[j + 1]
        if gl * gh <= 0.0:
            rj = grid[0, j] + (gl / (gl - gh) if gl != gh else 0.0) * h
            d = abs(rj - i_prev)
            if d < best:
                second, best, cell, x, glo = best, d, j, rj, gl
            elif d < second:
                second = d
    if cell < 0:
        e0, e1 = abs(g[0]), abs(g[n - 1])
        if e1 < e0 or (e1 == e0 and abs(i_max - i_prev) < abs(i_prev)):
            return i_max, i_max, i_max
        return 0.0, 0.0, 0.0
    for j in range(max(cell - 1, 0), min(cell + 2, n - 1)):
        if j != cell and g[j] * g[j + 1] <= 0.0:
            near = True
    cell_lo, cell_hi = grid[0, cell], grid[0, cell + 1]
    lo, hi = cell_lo, cell_hi
    for _ in range(max_iter):
        fx, dg, _d2 = _at(net, k, x, vw_sum)
        gx = fx + c
        if gx == 0.0:
            break
        if (gx > 0.0) == (glo > 0.0) and glo != 0.0:
            lo, glo = x, gx
        else:
            hi = x
        xn = x - gx / dg if dg != 0.0 else math.nan
        if not lo < xn < hi:
            xn = 0.5 * (lo + hi)
        step = abs(xn - x)
        x = xn
        if step <= xtol:
            break
    if second - best <= h or near:
        return x, x, x
    return x, max(cell_lo - h, 0.0), min(cell_hi + h, i_max)


@njit
def _newton_ahead(net, p, k, c, i_prev, x, lo, hi):  # noqa: ANN001, ANN202
    """`ScalarInverter._newton_ahead`: (converged, current)."""
    a, b = p[_P_A], p[_P_B]
    regularised = p[_P_MU] > 0.0
    for _ in range(_AHEAD_ITERATIONS):
        fx, d1, d2 = _at(net, k, x, p[_P_VWS])
        gx = fx + c
        if regularised:
            jpp = a * (d1 * d1 + gx * d2) + b  # J''/2
            if not jpp > 0.0:
                return False, x
            xn = x - (a * gx * d1 + b * (x - i_prev)) / jpp  # J'/2 / (J''/2)
        else:
            if gx == 0.0:
                return True, x
            if d1 == 0.0:
                return False, x
            xn = x - gx / d1
        if not lo <= xn <= hi:
            return False, x
        if abs(xn - x) <= p[_P_XTOL]:
            return True, xn
        x = xn
    return False, x


@njit
def _solve(net, grid, p, st, work, feat, f_des, i_prev):  # noqa: ANN001, ANN202
    if not math.isfinite(f_des):
        return math.nan
    H = net.shape[1]
    k, g = work[:H], work[H:]
    _k_part(net, feat, k)
    c = p[_P_F0] - f_des
    ahead = st[0] != 0.0
    st[0] = 0.0
    if ahead and st[1] == i_prev:
        ok, x = _newton_ahead(net, p, k, c, i_prev, st[2], st[3], st[4])
        if ok:
            st[5] += 1.0
            return x
        st[6] += 1.0
    return _full(net, grid, p, k, g, c, i_prev)[0]


@njit
def _prepare(net, grid, p, st, work, feat, f_des, i_prev):  # noqa: ANN001, ANN202
    st[0] = 0.0
    H = net.shape[1]
    k, g = work[:H], work[H:]
    _k_part(net, feat, k)
    x, lo, hi = _full(net, grid, p, k, g, p[_P_F0] - f_des, i_prev)
    if lo < hi:
        st[0], st[1], st[2], st[3], st[4] = 1.0, i_prev, x, lo, hi


@njit
def _force(net, f0, work, feat, current_a):  # noqa: ANN001, ANN202
    """The network's force for one sample (`ScalarInverter.force`)."""
    acc = 0.0
    for h in range(net.shape[1]):
        kh = 0.0
        for j in range(feat.shape[0]):
            kh += net[5 + j, h] * feat[j]
        acc += math.tanh(kh + net[0, h] + net[1, h] * current_a) * net[2, h]
    return acc + f0


class CompiledScalarInverter(ScalarInverter):
    """`ScalarInverter`'s exact method compiled: solve, solve ahead, force (the flow method
    and the gradient method stay Python)."""

    def __init__(self, model, i_max: float, *, continuity: float = 0.0) -> None:  # noqa: ANN001
        self._st = np.zeros(7)
        super().__init__(model, i_max, continuity=continuity)
        s = self._s
        self._net = np.ascontiguousarray(np.vstack([s.a0, s.w, s.v, s.vw, s.vw * s.w, s.A.T]))
        self._grid2 = np.vstack([self._grid, self._grid_ba])
        self._p = np.array(
            [
                s.f0,
                self._h,
                self.xtol_a,
                float(self.max_iter),
                self.i_max,
                self.continuity,
                self._a,
                self._b,
                self._root_ba,
                self._vw_sum,
            ]
        )
        self._work = np.empty(model.hidden + self._grid.size)

    @property
    def ahead_used(self) -> int:
        return int(self._st[5])

    @ahead_used.setter
    def ahead_used(self, n: int) -> None:
        self._st[5] = n

    @property
    def ahead_missed(self) -> int:
        return int(self._st[6])

    @ahead_missed.setter
    def ahead_missed(self, n: int) -> None:
        self._st[6] = n

    def force(self, features: np.ndarray, current_a: float) -> float:
        return _force(self._net, self._s.f0, self._work, features, current_a)

    def solve(self, features: np.ndarray, f_des: float, i_prev: float) -> float:
        return _solve(
            self._net, self._grid2, self._p, self._st, self._work, features, f_des, i_prev
        )

    def prepare(self, features: np.ndarray, f_des: float, i_prev: float) -> None:
        _prepare(self._net, self._grid2, self._p, self._st, self._work, features, f_des, i_prev)

    def discard_prepared(self) -> None:
        self._st[0] = 0.0
