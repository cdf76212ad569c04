"""Training stage 2, the features: the forward network's input rows from a Series.

(x, xd, xdd, command), the command as given or through the coil's (or driver's) first-order
lag, then history inputs: earlier samples of chosen signals, `history_samples` taps
`history_stride` samples apart (names `SIGNAL_K`, K samples back, as the controllers read
them). History never crosses a run boundary: the first samples of each run, which have none,
are left out. `fit_lag_tau` finds the lag's time constant from the data by a 1-D search.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import optimize, signal

from mrrig.loop.controller_base import HISTORY_SIGNALS
from mrrig.offline.datasets import Series
from mrrig.offline.training.data import run_ids, sample_period, stretch_bounds, stretches

COIL_LAG_TAU_S = 1.0 / 190.0  # the plant's command lag, 1/eta (paper Table 3)
CURRENT_INPUTS = ("commanded", "lagged")
INPUT_NAMES = ("x", "xd", "xdd", "current")
INPUT_UNITS = ("m", "m/s", "m/s^2", "A")
CURRENT_COLUMN = INPUT_NAMES.index("current")
# The hysteresis state of the damper shows in its past motion. Past currents are no default:
# where the current is constant per run (the characterization matrix) they are collinear with
# the present current, and the force would no longer pin the present current down.
DEFAULT_HISTORY_SIGNALS = ("x", "xd")
LAG_SEARCH_S = (1e-4, 0.2)  # the bracket of `fit_lag_tau`
LAG_FIT_ROWS = 50_000  # rows of the proxy regression of `fit_lag_tau`


def lagged_current(
    current: np.ndarray, t_s: np.ndarray, run_id: np.ndarray, tau_s: float = COIL_LAG_TAU_S
) -> np.ndarray:
    """The coil driver's first-order lag of the command, u' = (v - u) / tau (paper eq. 36 with
    eta = 1/tau), discretised exactly for a command held over each sample period (ZOH), at each
    run's sample period (`data.sample_period`); u starts at the run's first command. A run
    split into pieces (`data.stretches`) restarts in each piece."""
    if not tau_s > 0.0:
        raise ValueError(f"lag_tau_s must be positive, got {tau_s}")
    u = np.empty_like(current, dtype=float)
    first, length = stretch_bounds(stretches(run_id))
    for f, n in zip(first.tolist(), length.tolist(), strict=True):
        rows = slice(f, f + n)
        v = current[rows]
        dt = sample_period(t_s[rows]) if n > 1 else tau_s
        a = -math.expm1(-dt / tau_s)
        # u[k] = (1 - a) u[k-1] + a v[k-1], from u[0] = v[0]
        u[rows] = v[0] + signal.lfilter([0.0, a], [1.0, a - 1.0], v - v[0])
    return u


def check_history(history_samples: int, history_signals: Sequence[str]) -> tuple[str, ...]:
    """The history signals as a tuple (empty without history); a one-line ValueError for
    a negative sample count, an unknown or repeated signal, or no signal."""
    if isinstance(history_samples, bool) or not isinstance(history_samples, int | np.integer):
        raise ValueError(f"history samples must be an integer, got {history_samples!r}")
    if history_samples < 0:
        raise ValueError(f"history samples must be >= 0, got {history_samples}")
    signals = tuple(history_signals)
    for sig in signals:
        if sig not in HISTORY_SIGNALS:
            raise ValueError(f"history signal {sig!r}: unknown ({', '.join(HISTORY_SIGNALS)})")
        if signals.count(sig) > 1:
            raise ValueError(f"history signal {sig!r}: given twice")
    if history_samples > 0 and not signals:
        raise ValueError("history signals: none given")
    return signals if history_samples > 0 else ()


def _check_stride(history_stride: int) -> int:
    if isinstance(history_stride, bool) or not isinstance(history_stride, int | np.integer):
        raise ValueError(f"history stride must be an integer, got {history_stride!r}")
    if history_stride < 1:
        raise ValueError(f"history stride must be >= 1, got {history_stride}")
    return int(history_stride)


def feature_names(
    history_samples: int = 0,
    history_signals: Sequence[str] = DEFAULT_HISTORY_SIGNALS,
    history_stride: int = 1,
    command_unit: str = "A",
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(names, units) of the forward network's inputs: `INPUT_NAMES`, then the history inputs
    `SIGNAL_K` (K = stride, 2 stride, ... samples back, newest first, signals in their order
    at each tap). The command's unit is `command_unit` (A, or V for a driver voltage)."""
    signals = check_history(history_samples, history_signals)
    stride = _check_stride(history_stride)
    hist = tuple(f"{sig}_{stride * k}" for k in range(1, history_samples + 1) for sig in signals)
    unit = dict(zip(INPUT_NAMES, INPUT_UNITS, strict=True)) | {"current": command_unit}
    units = tuple(unit[n] for n in INPUT_NAMES) + tuple(unit[n.rpartition("_")[0]] for n in hist)
    return INPUT_NAMES + hist, units


def feature_rows(series: Series, history_samples: int = 0, history_stride: int = 1) -> np.ndarray:
    """Indices of the samples that have `history_samples * history_stride` earlier samples in
    their own run: all but the first so many of each run (a run that is not contiguous in the
    series counts as one run per contiguous stretch). History never crosses a run boundary."""
    depth = history_samples * _check_stride(history_stride)
    n = len(series)
    first, length = stretch_bounds(stretches(run_ids(series)))
    start = np.repeat(first, length)  # each row's stretch start
    return np.flatnonzero(np.arange(n) - start >= depth)


def command_input(
    series: Series, current_input: str = "commanded", lag_tau_s: float = COIL_LAG_TAU_S
) -> np.ndarray:
    """The command column: as given, or `lagged_current` with `lag_tau_s`."""
    if current_input not in CURRENT_INPUTS:
        raise ValueError(f"unknown current input {current_input!r} ({', '.join(CURRENT_INPUTS)})")
    if current_input == "commanded":
        return series.current
    return lagged_current(series.current, series.t, run_ids(series), lag_tau_s)


def features(
    series: Series,
    current_input: str = "commanded",
    lag_tau_s: float = COIL_LAG_TAU_S,
    history_samples: int = 0,
    history_signals: Sequence[str] = DEFAULT_HISTORY_SIGNALS,
    history_stride: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Forward-network rows X and the target y = force, at the samples `feature_rows` keeps.

    The columns are `feature_names`: (x, xd, xdd, current), then the history inputs of
    `history_signals`, default x and xd (the hysteresis state). Past currents are no
    default: where the current is constant in each run (the characterization matrix) a past
    current equals the present one, the network can take the force from either, and its
    inversion for the present current becomes ill-posed; add "current" only for data that
    varies the current within runs. With current_input="lagged" the current column, and any
    past current, is `lagged_current`.
    """
    signals = check_history(history_samples, history_signals)
    stride = _check_stride(history_stride)
    if series.xd is None or series.xdd is None:
        raise ValueError(f"{series.name}: no velocity/acceleration: use estimate_derivatives")
    current = command_input(series, current_input, lag_tau_s)
    base = {"x": series.x, "xd": series.xd, "xdd": series.xdd, "current": current}
    rows = feature_rows(series, history_samples, stride)
    X = np.empty((rows.size, len(INPUT_NAMES) + history_samples * len(signals)))
    for j, name in enumerate(INPUT_NAMES):
        X[:, j] = base[name][rows]
    j = len(INPUT_NAMES)
    for k in range(1, history_samples + 1):
        for sig in signals:
            X[:, j] = base[sig][rows - stride * k]
            j += 1
    return X, series.force[rows]


def _lag_proxy_rows(series: Series, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
    """A damper-shaped linear basis (Bingham-like: viscous, friction and their change with the
    command) whose least-squares fit scores a lag constant."""
    x, xd = series.x[rows], series.xd[rows]
    s = np.tanh(xd / (0.1 * (np.std(xd) or 1.0)))
    u = u[rows]
    return np.column_stack([np.ones(rows.size), x, xd, s, series.xdd[rows], u, u * xd, u * s])


def fit_lag_tau(series: Series, fit_rows: np.ndarray, seed: int = 0) -> tuple[float, float]:
    """(tau_s, residual RMS N) of the command's first-order lag that best explains the force,
    by a 1-D bounded search over log tau in `LAG_SEARCH_S`: for each tau, the least-squares
    fit of a damper-shaped linear model (`_lag_proxy_rows`) on up to `LAG_FIT_ROWS` of
    `fit_rows` (training rows only). Cheap (a regression per tau), so the network's search
    gets one fitted tau instead of a grid of them."""
    rng = np.random.default_rng(seed)
    rows = (
        np.sort(rng.permutation(fit_rows)[:LAG_FIT_ROWS])
        if fit_rows.size > LAG_FIT_ROWS
        else fit_rows
    )
    run_id = run_ids(series)
    y = series.force[rows]

    def residual(log_tau: float) -> float:
        u = lagged_current(series.current, series.t, run_id, 10.0**log_tau)
        A = _lag_proxy_rows(series, rows, u)
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        return float(np.sqrt(np.mean((A @ coef - y) ** 2)))

    lo, hi = (math.log10(v) for v in LAG_SEARCH_S)
    res = optimize.minimize_scalar(
        residual, bounds=(lo, hi), method="bounded", options={"xatol": 0.02}
    )
    return float(10.0**res.x), float(res.fun)
