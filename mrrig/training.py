"""Training the forward network (and the supervised inverse) from measured data, and the
validation report of the paper's section on network inversion (spec/modeling.md 2, 4 B/C, 5).

Data comes from tidy characterization CSVs, from daemon recordings (.rrd) and from any CSV with a
column map and units; everything is converted to a `Series` in SI units with a run id per
sample. Velocity and acceleration, where a file lacks them, come from the daemon's Kalman filter
run over each run; the filter's start-up transient (`KALMAN_WARMUP_S`) is dropped.

The split is the paper's: a random 12771 training / 1419 validation samples out of all the data
(the rest is not used), or 90/10 of everything when there are fewer samples than that.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal

from mrrig.controllers import HISTORY_SIGNALS, history_input_names
from mrrig.datasets import TIDY_HEADER, DataError, Series, load_csv
from mrrig.estimation import KalmanEstimator
from mrrig.inversion import exact_inversion
from mrrig.metrics import error_norm, percentiles, rmse
from mrrig.model.mlp import MLP, data_fingerprint
from mrrig.model.train import ProgressFn, train_lm

log = logging.getLogger(__name__)

PAPER_N_TRAIN = 12771  # the paper's split (spec/modeling.md 4 B)
PAPER_N_VAL = 1419
SMALL_DATA_VAL_FRACTION = 0.1
COIL_LAG_TAU_S = 1.0 / 190.0  # the plant's command lag, 1/eta (paper Table 3)
KALMAN_WARMUP_S = 0.1  # dropped at the start of each run whose xd/xdd we estimate
CURRENT_INPUTS = ("commanded", "lagged")
INPUT_NAMES = ("x", "xd", "xdd", "current")
INPUT_UNITS = ("m", "m/s", "m/s^2", "A")
CURRENT_COLUMN = INPUT_NAMES.index("current")
SUPERVISED_INPUT_NAMES = ("x", "xd", "xdd", "f_des")
SUPERVISED_INPUT_UNITS = ("m", "m/s", "m/s^2", "N")
# The hysteresis state of the damper shows in its past motion. Past currents are no default:
# where the current is constant per run (the characterization matrix) they are collinear with
# the present current, and the force would no longer pin the present current down.
DEFAULT_HISTORY_SIGNALS = ("x", "xd")
TRACKING_QUANTILES = (50.0, 95.0)

# plant_force(rows, current_a) -> force_n: the plant's force at sample rows of the series, had
# the damper run at the given (constant) currents; only the simulator benchmark has one.
PlantForceFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _is_tidy(path: Path) -> bool:
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            header = next(csv.reader(fh), [])
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DataError(f"{path}: cannot read: {exc}".replace("\n", " ")) from exc
    return tuple(h.strip() for h in header) == TIDY_HEADER


def load_tidy(path: str | Path) -> Series:
    """Read a tidy characterization CSV. xd/xdd are None when the file has any nan in them
    (the caller estimates them). current_meas_a is not used for training."""
    path = Path(path)
    if not _is_tidy(path):
        header = ",".join(TIDY_HEADER)
        raise DataError(f"{path}: not a tidy characterization file (header {header})")
    try:
        a = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, encoding="utf-8")
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: {exc}".replace("\n", " ")) from exc
    if a.shape[0] == 0:
        raise DataError(f"{path}: no data rows")
    if a.shape[1] != len(TIDY_HEADER):
        raise DataError(f"{path}: {a.shape[1]} columns, want {len(TIDY_HEADER)}")
    for j in (0, 1, 2, 5, 6):
        if not np.all(np.isfinite(a[:, j])):
            row = int(np.flatnonzero(~np.isfinite(a[:, j]))[0]) + 1
            raise DataError(f"{path}: column {TIDY_HEADER[j]!r}, data row {row}: not finite")
    if np.any(a[:, 0] != np.round(a[:, 0])):
        raise DataError(f"{path}: column 'run_id' must hold integers")
    has_est = bool(np.all(np.isfinite(a[:, 3:5])))
    return Series(
        t=a[:, 1],
        x=a[:, 2],
        xd=a[:, 3] if has_est else None,
        xdd=a[:, 4] if has_est else None,
        current=a[:, 6],
        force=a[:, 5],
        name=path.stem,
        run_id=a[:, 0].astype(int),
    )


def _runs_from_time(t: np.ndarray) -> np.ndarray:
    """Run ids for a file without a run column: a new run wherever time does not increase."""
    return np.concatenate([[0], np.cumsum(np.diff(t) <= 0.0)]).astype(int)


def load_recording(path: str | Path) -> Series:
    """A daemon recording (.rrd) as a Series: x_est, xd, xdd (the daemon's own Kalman
    estimates, the inputs its controller saw), f_meas, i_cmd.

    Samples in FAULT are dropped: there the command path is not trusted. In IDLE the daemon
    sends SAFE 0 A and records i_cmd = 0, which is what the firmware applies, so those samples
    stay (they are the 0 A part of the data). The first `KALMAN_WARMUP_S` of the file are
    dropped too (the daemon's filter starts with it). A new run id starts after every dropped
    stretch or time gap over 5 sample periods, so lag filters restart there.
    """
    # rerun and pyarrow are slow to import: only .rrd inputs pay for them
    from mrrig.review import read_recording
    from mrrig.samples import RigState

    path = Path(path)
    s = read_recording(path).samples
    fields = ("t", "x_est", "xd", "xdd", "f_meas", "i_cmd")
    keep = s["state"] != RigState.FAULT
    for f in fields:
        keep &= np.isfinite(s[f])
    if s.size:
        period = float(np.median(np.diff(s["t"]))) if s.size > 1 else 0.0
        keep &= s["t"] - s["t"][0] > KALMAN_WARMUP_S - 0.5 * period
    if keep.sum() < 2:
        raise DataError(f"{path}: fewer than 2 usable samples (not FAULT, all fields finite)")
    idx = np.flatnonzero(keep)
    t = s["t"][idx]
    dt = np.diff(t)
    period = float(np.median(dt))
    new_run = (np.diff(idx) > 1) | (dt > 5.0 * period) | (dt <= 0.0)
    return Series(
        t=t,
        x=s["x_est"][idx],
        xd=s["xd"][idx],
        xdd=s["xdd"][idx],
        current=s["i_cmd"][idx],
        force=s["f_meas"][idx],
        name=path.stem,
        run_id=np.concatenate([[0], np.cumsum(new_run)]).astype(int),
    )


def estimate_derivatives(series: Series, warmup_s: float = KALMAN_WARMUP_S) -> Series:
    """Fill xd/xdd with the Kalman filter (the daemon's, paper eqs 17-29) run over each run at
    its median sample period, and drop the first `warmup_s` of each run (the filter's start-up
    transient). x becomes the filtered displacement, as the daemon's controller sees it."""
    run_id = series.run_id if series.run_id is not None else _runs_from_time(series.t)
    x, xd, xdd = (np.empty(len(series)) for _ in range(3))
    keep = np.zeros(len(series), dtype=bool)
    for r in np.unique(run_id):
        rows = np.flatnonzero(run_id == r)
        t = series.t[rows]
        if rows.size < 2 or np.any(np.diff(t) <= 0.0):
            raise DataError(f"{series.name}: run {r}: time must increase (and >= 2 samples)")
        dt_s = float(np.median(np.diff(t)))
        x[rows], xd[rows], xdd[rows] = KalmanEstimator(dt_s).estimate(series.x[rows])
        keep[rows] = t - t[0] > warmup_s - 0.5 * dt_s  # round(warmup_s / dt_s) samples dropped
    out = replace(series, x=x, xd=xd, xdd=xdd, run_id=run_id, x_meas=None, force_meas=None)
    return _select(out, keep)


def _select(s: Series, rows: np.ndarray) -> Series:
    """The Series restricted to rows (a boolean mask or indices)."""
    pick = {
        f: (None if getattr(s, f) is None else getattr(s, f)[rows])
        for f in ("t", "x", "xd", "xdd", "current", "force", "run_id", "x_meas", "force_meas")
    }
    return Series(name=s.name, **pick)


def concatenate(parts: Sequence[Series], name: str = "") -> Series:
    """One Series from several, run ids renumbered so that every part's runs stay distinct."""
    runs, offset = [], 0
    for p in parts:
        rid = p.run_id if p.run_id is not None else _runs_from_time(p.t)
        _, dense = np.unique(rid, return_inverse=True)
        runs.append(dense + offset)
        offset += int(dense.max()) + 1
    cat = lambda f: np.concatenate([getattr(p, f) for p in parts])  # noqa: E731
    return Series(
        t=cat("t"),
        x=cat("x"),
        xd=cat("xd"),
        xdd=cat("xdd"),
        current=cat("current"),
        force=cat("force"),
        name=name,
        run_id=np.concatenate(runs),
    )


def load_training_data(
    paths: Sequence[str | Path],
    columns: dict[str, str] | None = None,
    units: dict[str, str] | None = None,
) -> Series:
    """Load and concatenate training files into one Series with xd/xdd present.

    By file: `.rrd` -> `load_recording`; a CSV with the tidy header -> `load_tidy`; any other
    CSV -> `datasets.load_csv` with `columns`/`units` (a new run wherever time does not
    increase). Files without velocity/acceleration get them from `estimate_derivatives`.
    Errors are one-line `DataError`s naming the file.
    """
    if not paths:
        raise DataError("no training data files given")
    parts = []
    for p in map(Path, paths):
        if not p.is_file():
            raise DataError(f"{p}: no such file")
        if p.suffix.lower() == ".rrd":
            s = load_recording(p)
        elif _is_tidy(p):
            s = load_tidy(p)
        elif columns is None:
            raise DataError(f"{p}: not a tidy characterization CSV: give a column map (--columns)")
        else:
            s = load_csv(p, columns, units)
            s = replace(s, run_id=_runs_from_time(s.t))
        if s.xd is None or s.xdd is None:
            s = estimate_derivatives(s)
            if len(s) == 0:
                raise DataError(f"{p}: no samples left after the Kalman warm-up")
        log.info("%s: %d samples, %d runs", p, len(s), np.unique(s.run_id).size)
        parts.append(s)
    return concatenate(parts, name="+".join(s.name for s in parts))


# ---------------------------------------------------------------------------------- features
def lagged_current(
    current: np.ndarray, t_s: np.ndarray, run_id: np.ndarray, tau_s: float = COIL_LAG_TAU_S
) -> np.ndarray:
    """The coil driver's first-order lag of the command, u' = (v - u) / tau (paper eq. 36 with
    eta = 1/tau), discretised exactly for a command held over each sample period (ZOH), at each
    run's median period; u starts at the run's first command."""
    if not tau_s > 0.0:
        raise ValueError(f"lag_tau_s must be positive, got {tau_s}")
    u = np.empty_like(current, dtype=float)
    for r in np.unique(run_id):
        rows = np.flatnonzero(run_id == r)
        v = current[rows]
        dt = float(np.median(np.diff(t_s[rows]))) if rows.size > 1 else tau_s
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


def feature_names(
    history_samples: int = 0, history_signals: Sequence[str] = DEFAULT_HISTORY_SIGNALS
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(names, units) of the forward network's inputs: `INPUT_NAMES`, then the history inputs
    `SIGNAL_K` (K samples back, newest first; `controllers.history_input_names`)."""
    signals = check_history(history_samples, history_signals)
    hist = history_input_names(history_samples, signals)
    unit = dict(zip(INPUT_NAMES, INPUT_UNITS, strict=True))
    return INPUT_NAMES + hist, INPUT_UNITS + tuple(unit[n.rpartition("_")[0]] for n in hist)


def feature_rows(series: Series, history_samples: int = 0) -> np.ndarray:
    """Indices of the samples that have `history_samples` earlier samples in their own run:
    all but the first `history_samples` of each run (a run that is not contiguous in the
    series counts as one run per contiguous stretch). History never crosses a run boundary."""
    run_id = series.run_id if series.run_id is not None else _runs_from_time(series.t)
    n = len(series)
    start = np.flatnonzero(np.concatenate([[True], run_id[1:] != run_id[:-1]]))
    first = np.repeat(start, np.diff(np.append(start, n)))  # each row's stretch start
    return np.flatnonzero(np.arange(n) - first >= history_samples)


def features(
    series: Series,
    current_input: str = "commanded",
    lag_tau_s: float = COIL_LAG_TAU_S,
    history_samples: int = 0,
    history_signals: Sequence[str] = DEFAULT_HISTORY_SIGNALS,
) -> tuple[np.ndarray, np.ndarray]:
    """Forward-network rows X and the target y = force, at the samples `feature_rows` keeps.

    The columns are `feature_names`: (x, xd, xdd, current), then the previous
    `history_samples` samples of `history_signals`, default x and xd (the hysteresis state).
    Past currents are no default: where the current is constant in each run (the
    characterization matrix) a past current equals the present one, the network can take
    the force from either, and its inversion for the present current becomes ill-posed; add
    "current" only for data that varies the current within runs. With
    current_input="lagged" the current column, and any past current, is `lagged_current`.
    """
    if current_input not in CURRENT_INPUTS:
        raise ValueError(f"unknown current input {current_input!r} ({', '.join(CURRENT_INPUTS)})")
    signals = check_history(history_samples, history_signals)
    if series.xd is None or series.xdd is None:
        raise ValueError(f"{series.name}: no velocity/acceleration: use estimate_derivatives")
    current = series.current
    if current_input == "lagged":
        run_id = series.run_id if series.run_id is not None else _runs_from_time(series.t)
        current = lagged_current(series.current, series.t, run_id, lag_tau_s)
    base = {"x": series.x, "xd": series.xd, "xdd": series.xdd, "current": current}
    rows = feature_rows(series, history_samples)
    cols = [base[name][rows] for name in INPUT_NAMES]
    cols += [base[sig][rows - k] for k in range(1, history_samples + 1) for sig in signals]
    return np.column_stack(cols), series.force[rows]


def series_fingerprint(series: Series) -> str:
    """sha256 of the whole training data set (independent of the split and the options)."""
    run_id = series.run_id if series.run_id is not None else np.zeros(len(series))
    return data_fingerprint(
        run_id, series.t, series.x, series.xd, series.xdd, series.current, series.force
    )


# ---------------------------------------------------------------------------------- training
@dataclass(frozen=True)
class Split:
    train: np.ndarray  # row indices, sorted
    val: np.ndarray
    rule: str  # how the sizes were chosen, for the report


def split_samples(
    n: int, n_train: int = PAPER_N_TRAIN, n_val: int = PAPER_N_VAL, seed: int = 0
) -> Split:
    """A random disjoint split: n_train / n_val out of n (the rest unused), or 90/10 of all n
    when n < n_train + n_val. The same (n, sizes, seed) always gives the same split."""
    if n_train < 1 or n_val < 1:
        raise ValueError(f"split sizes must be positive, got {n_train} / {n_val}")
    if n < n_train + n_val:
        rule = f"90/10 of all {n} samples (fewer than {n_train} + {n_val})"
        n_val = max(1, round(SMALL_DATA_VAL_FRACTION * n))
        n_train = n - n_val
        if n_train < 1:
            raise DataError(f"only {n} samples: too few to train")
    else:
        rule = f"random {n_train} / {n_val} of {n} samples (the paper's split)"
    perm = np.random.default_rng(seed).permutation(n)
    return Split(np.sort(perm[:n_train]), np.sort(perm[n_train : n_train + n_val]), rule)


def train_forward(
    series: Series,
    n_train: int = PAPER_N_TRAIN,
    n_val: int = PAPER_N_VAL,
    seed: int = 0,
    progress: ProgressFn | None = None,
    current_input: str = "commanded",
    lag_tau_s: float = COIL_LAG_TAU_S,
    max_epochs: int = 1000,
    history_samples: int = 0,
    history_signals: Sequence[str] = DEFAULT_HISTORY_SIGNALS,
    init_seed: int | None = None,
) -> tuple[MLP, dict[str, Any]]:
    """The 4-30-1 forward network (4 + history inputs) by Levenberg-Marquardt on the random
    split of the `features` rows, early-stopped on the validation part. `seed` draws the
    split and, unless `init_seed` is given, the initial weights. The model's meta records the
    options, the split and the data's fingerprint; the returned report has the training
    numbers and the split's rule."""
    X, y = features(series, current_input, lag_tau_s, history_samples, history_signals)
    names, units = feature_names(history_samples, history_signals)
    split = split_samples(len(y), n_train, n_val, seed)
    log.info("training the forward network (MSE in N^2): %s", split.rule)
    model, tr = train_lm(
        X[split.train],
        y[split.train],
        names,
        units,
        "force",
        "N",
        validation=(X[split.val], y[split.val]),
        max_epochs=max_epochs,
        seed=seed if init_seed is None else init_seed,
        progress=progress,
        description=series.name,
    )
    model.meta.update(
        init_seed=seed if init_seed is None else init_seed,
        current_input=current_input,
        lag_tau_s=lag_tau_s if current_input == "lagged" else None,
        history_samples=history_samples,
        history_signals=list(check_history(history_samples, history_signals)),
        split_rule=split.rule,
        split_seed=seed,
        n_samples=len(y),
        n_runs=int(np.unique(series.run_id).size) if series.run_id is not None else 1,
        data_fingerprint=series_fingerprint(series),
        current_range_a=[float(X[:, CURRENT_COLUMN].min()), float(X[:, CURRENT_COLUMN].max())],
    )
    report = {
        "split": {"rule": split.rule, "n_train": tr.n_train, "n_val": tr.n_val, "seed": seed},
        "epochs": tr.epochs,
        "best_epoch": tr.best_epoch,
        "stop_reason": tr.stop_reason,
        "seconds": tr.seconds,
        "train_mse_n2": tr.train_mse,
        "val_mse_n2": tr.val_mse,
    }
    return model, report


def train_supervised(
    series: Series,
    split: Split,
    seed: int = 0,
    progress: ProgressFn | None = None,
    current_input: str = "commanded",
    lag_tau_s: float = COIL_LAG_TAU_S,
    max_epochs: int = 1000,
    history_samples: int = 0,
    history_signals: Sequence[str] = DEFAULT_HISTORY_SIGNALS,
) -> tuple[MLP, dict[str, Any]]:
    """The supervised inverse MLP (x, xd, xdd, f) -> current (paper Fig. 10), same split of
    the same `features` rows. It gets the forward network's history of the motion, not of
    the current (`controllers.SupervisedInverse`)."""
    X, y = features(series, current_input, lag_tau_s, history_samples, history_signals)
    names, units = supervised_feature_names(history_samples, history_signals)
    Xs = supervised_rows(X, y, feature_names(history_samples, history_signals)[0], names)
    log.info("training the supervised inverse MLP (MSE in A^2)")
    model, tr = train_lm(
        Xs[split.train],
        X[split.train, CURRENT_COLUMN],
        names,
        units,
        "current",
        "A",
        validation=(Xs[split.val], X[split.val, CURRENT_COLUMN]),
        max_epochs=max_epochs,
        seed=seed,
        progress=progress,
        description=series.name,
    )
    motion = [sig for sig in check_history(history_samples, history_signals) if sig != "current"]
    model.meta.update(
        current_input=current_input,
        history_samples=history_samples if motion else 0,
        history_signals=motion,
        data_fingerprint=series_fingerprint(series),
    )
    return model, {"epochs": tr.epochs, "stop_reason": tr.stop_reason, "seconds": tr.seconds}


def supervised_feature_names(
    history_samples: int = 0, history_signals: Sequence[str] = DEFAULT_HISTORY_SIGNALS
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(names, units) of the supervised inverse's inputs: `SUPERVISED_INPUT_NAMES`, then the
    forward network's history inputs of the motion (none of the current)."""
    motion = [sig for sig in check_history(history_samples, history_signals) if sig != "current"]
    names, units = feature_names(history_samples if motion else 0, motion)
    n = len(INPUT_NAMES)
    return SUPERVISED_INPUT_NAMES + names[n:], SUPERVISED_INPUT_UNITS + units[n:]


def supervised_rows(
    X: np.ndarray, f_des: np.ndarray, forward_names: Sequence[str], names: Sequence[str]
) -> np.ndarray:
    """Input rows of a supervised inverse (inputs `names`) from forward-network rows X (inputs
    `forward_names`) and the desired force; a one-line ValueError for an input X lacks."""
    cols = []
    for name in names:
        if name == "f_des":
            cols.append(np.asarray(f_des, dtype=float))
        elif name in forward_names and name != "current":
            cols.append(X[:, list(forward_names).index(name)])
        else:
            raise ValueError(f"supervised input {name!r}: not among the forward model's inputs")
    return np.column_stack(cols)


# ---------------------------------------------------------------------------------- validation
def _tracking(errors_n: np.ndarray) -> dict[str, float]:
    p = percentiles(np.abs(errors_n), TRACKING_QUANTILES)
    p["rms"] = float(np.sqrt(np.mean(errors_n**2)))
    return p


def _inverse_metrics(
    model: MLP,
    X_val: np.ndarray,
    f_des: np.ndarray,
    current_a: np.ndarray,
    i_max: float,
    plant_force: Callable[[np.ndarray], np.ndarray] | None,
) -> dict[str, Any]:
    c = model.current_index
    Xi = X_val.copy()
    Xi[:, c] = current_a
    out: dict[str, Any] = {
        "current_rmse_a": rmse(current_a, X_val[:, c]),
        "at_bound_fraction": float(np.mean((current_a <= 0.0) | (current_a >= i_max))),
        "tracking_model_n": _tracking(model.predict(Xi) - f_des),
        "tracking_plant_n": None,
    }
    if plant_force is not None:
        out["tracking_plant_n"] = _tracking(plant_force(current_a) - f_des)
    return out


TRACKING_DEFINITIONS = {
    "desired force": "the measured force of each validation sample",
    "tracking_model_n": "|forward-model force at the inverted current - desired force|: "
    "zero for an exact inversion unless the force is out of reach",
    "tracking_plant_n": "|plant force, damper run in steady state at the inverted current "
    "in the sample's own motion - desired force|: only where the plant is known (simulator)",
}


def validation_report(
    model: MLP,
    X_val: np.ndarray,
    y_val: np.ndarray,
    i_max: float,
    supervised: MLP | None = None,
    plant_force: Callable[[np.ndarray], np.ndarray] | None = None,
) -> dict[str, Any]:
    """Forward Et, and for network inversion (and the supervised inverse, if given): the
    inverse-current RMSE (A) against the current that produced each sample's force, and the
    tracking error percentiles (N) as `TRACKING_DEFINITIONS` states.

    Each validation sample is inverted alone for its measured force by the exact scalar solve
    over [0, i_max]; offline there is no previous command, so i_prev = 0 (as at the start of a
    run) picks the smallest current where several give the force. `plant_force(current_a)`
    gives the plant's force at the validation samples for the given currents. X_val's
    columns are the model's inputs (history inputs included, as `features` gives them); the
    supervised inverse's rows are taken from them by name (`supervised_rows`).
    """
    if model.current_index is None:
        raise ValueError("validation_report needs a forward model with an input named 'current'")
    X_val = np.asarray(X_val, dtype=float)
    y_val = np.asarray(y_val, dtype=float)
    f_fwd = model.predict(X_val)
    report: dict[str, Any] = {
        "n_val": int(y_val.size),
        "i_max_a": float(i_max),
        "forward": {"et": error_norm(y_val, f_fwd), "rmse_n": rmse(y_val, f_fwd)},
        "definitions": TRACKING_DEFINITIONS,
    }
    features_val = np.delete(X_val, model.current_index, axis=1)
    i_ni = exact_inversion(model, features_val, y_val, 0.0, i_max=i_max)
    report["network_inversion"] = _inverse_metrics(model, X_val, y_val, i_ni, i_max, plant_force)
    if supervised is not None:
        Xs = supervised_rows(X_val, y_val, model.input_names, supervised.input_names)
        i_sup = np.clip(supervised.predict(Xs), 0.0, i_max)
        report["supervised"] = _inverse_metrics(model, X_val, y_val, i_sup, i_max, plant_force)
    return report


ONLINE_CONTINUITY_CANDIDATES = (0.0, 0.01, 0.03, 0.1, 0.3, 1.0)
DEFAULT_RESTARTS = 3  # forward-network starts of train_and_validate


def online_inversion(
    model: MLP, X: np.ndarray, f_des: np.ndarray, stretch: np.ndarray, i_max: float, continuity
) -> np.ndarray:
    """Inverse currents (N,) for every row as the real-time loop makes them: the rows of each
    contiguous stretch (`stretch` ids, rows in time order) one after the other, each solved
    exactly (`continuity`: mrrig/inversion.py) from the previous row's inverse current, 0 A
    at a stretch's start; the stretches advance in lockstep as one batch. Only the motion
    columns and the force are used, never the data's current (past currents among history
    inputs excepted: they are the data's)."""
    feats = np.delete(np.asarray(X, dtype=float), model.current_index, axis=1)
    f_des = np.asarray(f_des, dtype=float)
    first = np.flatnonzero(np.concatenate([[True], stretch[1:] != stretch[:-1]]))
    length = np.diff(np.append(first, len(f_des)))
    out = np.empty(len(f_des))
    prev = np.zeros(first.size)
    for k in range(int(length.max()) if first.size else 0):
        live = length > k
        rows = first[live] + k
        out[rows] = prev[live] = exact_inversion(
            model, feats[rows], f_des[rows], prev[live], i_max=i_max, continuity=continuity
        )
    return out


def choose_continuity(
    model: MLP,
    X: np.ndarray,
    f_des: np.ndarray,
    stretch: np.ndarray,
    i_max: float,
    train_rows: np.ndarray,
    candidates: Sequence[float] = ONLINE_CONTINUITY_CANDIDATES,
) -> tuple[float, np.ndarray, dict[str, float]]:
    """The continuity of the on-line inversion chosen on the TRAINING rows alone (smallest
    inverse-current RMSE there); returns it, its inverse currents for every row, and the
    training-row RMSE of each candidate. The validation rows play no part in the choice."""
    c = model.current_index
    scores: dict[str, float] = {}
    best: tuple[float, float, np.ndarray] | None = None
    for mu in candidates:
        i = online_inversion(model, X, f_des, stretch, i_max, mu)
        score = rmse(i[train_rows], X[train_rows, c])
        scores[f"{mu:g}"] = score
        log.info("on-line inversion, continuity %g: training-row current RMSE %.4f A", mu, score)
        if best is None or score < best[1]:
            best = (mu, score, i)
    assert best is not None
    return best[0], best[2], scores


def train_and_validate(
    series: Series,
    n_train: int = PAPER_N_TRAIN,
    n_val: int = PAPER_N_VAL,
    seed: int = 0,
    progress: ProgressFn | None = None,
    current_input: str = "commanded",
    lag_tau_s: float = COIL_LAG_TAU_S,
    max_epochs: int = 1000,
    i_max: float | None = None,
    supervised: bool = True,
    plant_force: PlantForceFn | None = None,
    history_samples: int = 0,
    history_signals: Sequence[str] = DEFAULT_HISTORY_SIGNALS,
    restarts: int = DEFAULT_RESTARTS,
) -> tuple[MLP, MLP | None, dict[str, Any]]:
    """Forward network, supervised inverse (optional) and the validation report, one split.

    i_max (the inversion's bracket) defaults to the largest current in the data: beyond it the
    network is extrapolating. The report's numbers are also stored in the model's metrics.
    With history inputs, the split is over the `feature_rows` (the first `history_samples` of
    each run have no history and are left out).

    The forward network is trained `restarts` times on the same split from different initial
    weights (seeds seed, seed + 1, ...), and the one whose on-line inverse (with its own best
    continuity, `choose_continuity`) gives the smallest current RMSE on the TRAINING rows is
    kept. A good force fit does not make a good inverse: with a few current levels in the
    data, a network can fit the force well and still wiggle between the levels, so that
    another current gives the same force. The validation rows play no part in the choice.
    """
    if restarts < 1:
        raise ValueError(f"restarts must be >= 1, got {restarts}")
    # the trailing parameters that train_forward and train_supervised share, in their order
    options = (current_input, lag_tau_s, max_epochs, history_samples, history_signals)
    X, y = features(series, current_input, lag_tau_s, history_samples, history_signals)
    rows = feature_rows(series, history_samples)
    split = split_samples(len(y), n_train, n_val, seed)
    i_max = float(X[:, CURRENT_COLUMN].max()) if i_max is None else float(i_max)
    if not i_max > 0.0:
        raise DataError(f"{series.name}: all currents are 0 A: nothing to invert")
    run_id = series.run_id if series.run_id is not None else _runs_from_time(series.t)
    stretch = np.cumsum(np.concatenate([[True], run_id[1:] != run_id[:-1]]))[rows]
    starts = []
    for k in range(restarts):
        fwd_k, report_k = train_forward(
            series, n_train, n_val, seed, progress, *options, init_seed=seed + k
        )
        mu_k, i_k, scores_k = choose_continuity(fwd_k, X, y, stretch, i_max, split.train)
        starts.append((scores_k[f"{mu_k:g}"], k, fwd_k, report_k, mu_k, i_k, scores_k))
        log.info(
            "start %d of %d: on-line inverse, training-row current RMSE %.4f A",
            k + 1,
            restarts,
            starts[-1][0],
        )
    _, kept, fwd, report, mu, i_online, scores = min(starts, key=lambda st: (st[0], st[1]))
    report["starts"] = {
        "init_seeds": [seed + k for k in range(restarts)],
        "training_rmse_a": [st[0] for st in starts],
        "kept": kept,
    }
    sup = None
    if supervised:
        sup, report["supervised_training"] = train_supervised(
            series, split, seed, progress, *options
        )
    rows_plant = None
    if plant_force is not None:
        rows_plant = lambda i: plant_force(rows[split.val], i)  # noqa: E731
    val = validation_report(fwd, X[split.val], y[split.val], i_max, sup, rows_plant)
    # the on-line inverse (as the daemon runs it), its continuity chosen on the training rows
    online = _inverse_metrics(
        fwd, X[split.val], y[split.val], i_online[split.val], i_max, rows_plant
    )
    val["network_inversion_online"] = {
        **online,
        "continuity": mu,
        "training_rmse_by_continuity": scores,
    }
    report.update(val)
    report["current_input"] = current_input
    report["lag_tau_s"] = lag_tau_s if current_input == "lagged" else None
    report["history_samples"] = history_samples
    report["history_signals"] = list(check_history(history_samples, history_signals))
    fwd.metrics.update(
        val_et=val["forward"]["et"],
        inverse_current_rmse_a=val["network_inversion"]["current_rmse_a"],
        tracking_model_p95_n=val["network_inversion"]["tracking_model_n"]["p95"],
        inverse_current_rmse_online_a=online["current_rmse_a"],
    )
    fwd.meta["i_max_a"] = i_max
    fwd.meta["online_continuity"] = mu
    fwd.meta["starts"] = restarts
    return fwd, sup, report


def measured_series(b: Series) -> Series:
    """What the rig records of data set B: noisy displacement and force, the command; xd/xdd
    by the daemon's Kalman filter (first 0.1 s of each run dropped)."""
    raw = Series(
        t=b.t,
        x=b.x_meas,
        xd=None,
        xdd=None,
        current=b.current,
        force=b.force_meas,
        name="B-measured",
        run_id=b.run_id,
    )
    return estimate_derivatives(raw)


def simulated_matrix_model(path: str | Path, seed: int = 0, max_epochs: int = 1000) -> MLP:
    """A forward model trained on the simulated characterization matrix (data set B, the
    simulator's plant and sensor noise), saved to `path`: the demo's and the tests' model.
    As `mrrig train` makes it, from one start: of the lagged current (the daemon's default
    one-step-ahead inversion inverts the coil's lag), the on-line continuity chosen on its
    training rows with it (meta `online_continuity`, the daemon's default)."""
    from mrrig.datasets import dataset_b

    series = measured_series(dataset_b())
    model, _, report = train_and_validate(
        series,
        seed=seed,
        max_epochs=max_epochs,
        supervised=False,
        restarts=1,
        current_input="lagged",
    )
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    model.save(path)
    log.info(
        "forward model trained on the simulated matrix in %.1f s: %s",
        report.get("seconds", float("nan")),
        path,
    )
    return model
