"""Training stage 4, the report: forward Et and RMSE, the inverse-current RMSE of network
inversion (each sample alone, and on-line as the daemon inverts) and the tracking error
(spec/modeling.md 5), on any rows of any data: `mrrig train`'s hold-out and `mrrig evaluate`
compute them with the same functions.

All rows are evaluated vectorised: the forward network in chunks of `PREDICT_CHUNK_ROWS`
(its hidden layer of 10 million rows would not fit at once), the on-line inversion, sequential
in time, as many blocks of the data side by side in one loop (`online_inversion`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mrrig.errors import MrrigError
from mrrig.loop.inversion import exact_inversion
from mrrig.loop.mlp import MLP
from mrrig.offline.metrics import error_norm, percentiles, rmse
from mrrig.offline.training.features import (
    DEFAULT_HISTORY_SIGNALS,
    INPUT_NAMES,
    check_history,
    feature_names,
)

log = logging.getLogger(__name__)

TRACKING_QUANTILES = (50.0, 95.0)
SUPERVISED_INPUT_NAMES = ("x", "xd", "xdd", "f_des")
SUPERVISED_INPUT_UNITS = ("m", "m/s", "m/s^2", "N")
ONLINE_CONTINUITY_CANDIDATES = (0.0, 0.01, 0.03, 0.1, 0.3, 1.0)
PREDICT_CHUNK_ROWS = 100_000
# The on-line inversion of long data runs in blocks of this many rows side by side, each block
# started `ONLINE_WARMUP_ROWS` early from 0 A (its command has settled where its rows begin)
ONLINE_BLOCK_ROWS = 512
ONLINE_WARMUP_ROWS = 128
ONLINE_CHOICE_ROWS = 20_000  # training rows the continuity is chosen on, at most


def predict(model: MLP, X: np.ndarray) -> np.ndarray:
    """`model.predict` in chunks of `PREDICT_CHUNK_ROWS` (bounded memory for any N)."""
    out = np.empty(X.shape[0])
    for a in range(0, X.shape[0], PREDICT_CHUNK_ROWS):
        out[a : a + PREDICT_CHUNK_ROWS] = model.predict(X[a : a + PREDICT_CHUNK_ROWS])
    return out


def supervised_feature_names(
    history_samples: int = 0,
    history_signals: Sequence[str] = DEFAULT_HISTORY_SIGNALS,
    history_stride: int = 1,
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(names, units) of the supervised inverse's inputs: `SUPERVISED_INPUT_NAMES`, then the
    forward network's history inputs of the motion (none of the current)."""
    motion = [sig for sig in check_history(history_samples, history_signals) if sig != "current"]
    names, units = feature_names(history_samples if motion else 0, motion, history_stride)
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
        "tracking_model_n": _tracking(predict(model, Xi) - f_des),
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
    f_fwd = predict(model, X_val)
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


def _lanes(
    stretch: np.ndarray, rows: np.ndarray, block: int | None, warmup: int
) -> list[tuple[int, int, int]]:
    """(lane start, first own row, end) of the on-line inversion's lanes: each contiguous
    piece of `rows` inside a stretch, cut into blocks of `block` rows (None: uncut); a lane
    starts `warmup` rows before its own rows where its stretch has them (0: at its first
    own row), and a stretch's first row always starts from 0 A."""
    n = stretch.size
    start_of = np.zeros(n, dtype=np.int64)
    first = np.flatnonzero(np.concatenate([[True], stretch[1:] != stretch[:-1]]))
    start_of[first] = first
    start_of = np.maximum.accumulate(start_of)  # each row's stretch start
    lanes = []
    if rows.size == 0:
        return lanes
    cut = np.flatnonzero((np.diff(rows) != 1) | (stretch[rows[1:]] != stretch[rows[:-1]])) + 1
    for a, b in zip(np.r_[0, cut].tolist(), np.r_[cut, rows.size].tolist(), strict=True):
        lo, hi = int(rows[a]), int(rows[b - 1]) + 1
        step = hi - lo if block is None else block
        for s in range(lo, hi, step):
            lanes.append((max(int(start_of[s]), s - warmup), s, min(s + step, hi)))
    return lanes


def online_inversion(
    model: MLP,
    X: np.ndarray,
    f_des: np.ndarray,
    stretch: np.ndarray,
    i_max: float,
    continuity: float,
    rows: np.ndarray | None = None,
    block: int | None = None,
    warmup: int = ONLINE_WARMUP_ROWS,
) -> np.ndarray:
    """Inverse currents (N,) for the rows as the real-time loop makes them: the rows of each
    contiguous stretch (`stretch` ids, rows in time order) one after the other, each solved
    exactly (`continuity`: mrrig/loop/inversion.py) from the previous row's inverse current, 0 A
    at a stretch's start; the stretches advance in lockstep as one batch. Only the motion
    columns and the force are used, never the data's current (past currents among history
    inputs excepted: they are the data's).

    `rows` (sorted indices; default all): only these are returned (NaN elsewhere), each
    piece of them run from `warmup` rows before it. `block`: long pieces are cut into
    blocks of so many rows (`_lanes`) that run side by side too, so the loop has about
    `block + warmup` steps whatever the data's length."""
    feats = np.delete(np.asarray(X, dtype=float), model.current_index, axis=1)
    f_des = np.asarray(f_des, dtype=float)
    rows = np.arange(len(f_des)) if rows is None else np.asarray(rows, dtype=np.int64)
    lanes = _lanes(np.asarray(stretch), rows, block, warmup)
    out = np.full(len(f_des), np.nan)
    if not lanes:
        return out
    start = np.array([a for a, _, _ in lanes])
    own = np.array([s for _, s, _ in lanes])
    length = np.array([e for _, _, e in lanes]) - start
    prev = np.zeros(start.size)
    for k in range(int(length.max())):
        live = length > k
        r = start[live] + k
        prev[live] = exact_inversion(
            model, feats[r], f_des[r], prev[live], i_max=i_max, continuity=continuity
        )
        mine = r >= own[live]
        out[r[mine]] = prev[live][mine]
    return out


def choice_rows(
    stretch: np.ndarray, train_rows: np.ndarray, max_rows: int | None, seed: int = 0
) -> np.ndarray:
    """The training rows the continuity is chosen on: all, or where there are more than
    `max_rows`, random whole blocks of `ONLINE_BLOCK_ROWS` contiguous training rows (the
    on-line inversion needs contiguous rows) up to about `max_rows`."""
    if max_rows is None or train_rows.size <= max_rows:
        return train_rows
    lanes = _lanes(stretch, train_rows, ONLINE_BLOCK_ROWS, 0)
    order = np.random.default_rng(seed).permutation(len(lanes))
    picked, total = [], 0
    for j in order.tolist():
        a, _, e = lanes[j]
        picked.append(np.arange(a, e))
        total += e - a
        if total >= max_rows:
            break
    return np.sort(np.concatenate(picked))


def choose_continuity(
    model: MLP,
    X: np.ndarray,
    f_des: np.ndarray,
    stretch: np.ndarray,
    i_max: float,
    train_rows: np.ndarray,
    candidates: Sequence[float] = ONLINE_CONTINUITY_CANDIDATES,
    block: int | None = None,
    max_rows: int | None = None,
) -> tuple[float, np.ndarray, dict[str, float]]:
    """The continuity of the on-line inversion chosen on the TRAINING rows alone (smallest
    inverse-current RMSE there); returns it, its inverse currents (for every row, or with
    `block`/`max_rows` only for the rows it was chosen on, NaN elsewhere) and the RMSE of
    each candidate. The validation rows play no part in the choice. `block` and `max_rows`
    bound the cost for large data (`online_inversion`, `choice_rows`)."""
    c = model.current_index
    rows = choice_rows(np.asarray(stretch), np.asarray(train_rows), max_rows)
    run_rows = None if block is None and max_rows is None else rows
    scores: dict[str, float] = {}
    best: tuple[float, float, np.ndarray] | None = None
    for mu in candidates:
        i = online_inversion(model, X, f_des, stretch, i_max, mu, rows=run_rows, block=block)
        score = rmse(i[rows], X[rows, c])
        scores[f"{mu:g}"] = score
        log.info("on-line inversion, continuity %g: training-row current RMSE %.4f A", mu, score)
        if best is None or score < best[1]:
            best = (mu, score, i)
    assert best is not None
    return best[0], best[2], scores


class MetricError(MrrigError, ArithmeticError):
    """A metric that came out NaN or infinite: the data cannot be scored as they are."""


@dataclass
class Scores:
    """A model's numbers on rows given piece by piece (`add`): forward Et and RMSE, and network
    inversion's inverse-current RMSE, each sample alone (from 0 A) and on-line
    (`online_inversion`). Sums only, so memory does not grow with the rows; the force's
    spread is combined piece by piece (Chan et al.), so one piece gives exactly what
    `metrics.error_norm` and `metrics.rmse` give. What `mrrig evaluate` prints."""

    continuity: float
    i_max: float
    n: int = 0
    mean_f: float = 0.0
    m2_f: float = 0.0  # sum of squared deviations of the measured force from its mean
    sse_f: float = 0.0
    sse_alone: float = 0.0
    sse_online: float = 0.0

    def add(
        self,
        model: MLP,
        X: np.ndarray,
        y: np.ndarray,
        stretch: np.ndarray,
        rows: np.ndarray,
        block: int | None = ONLINE_BLOCK_ROWS,
    ) -> np.ndarray:
        """Score `rows` of (X, y) (stretch ids `stretch`, the on-line inversion running from
        `ONLINE_WARMUP_ROWS` rows before each piece of them); returns the model's force there."""
        c = model.current_index
        y_r = y[rows]
        f = predict(model, X[rows])
        i_alone = np.empty(rows.size)
        for a in range(0, rows.size, PREDICT_CHUNK_ROWS):
            r = rows[a : a + PREDICT_CHUNK_ROWS]
            feats = np.delete(X[r], c, axis=1)
            i_alone[a : a + r.size] = exact_inversion(model, feats, y[r], 0.0, i_max=self.i_max)
        i_on = online_inversion(
            model, X, y, stretch, self.i_max, self.continuity, rows=rows, block=block
        )[rows]
        i_true = X[rows, c]
        n, mean = rows.size, float(np.mean(y_r)) if rows.size else 0.0
        m2 = float(np.sum((y_r - mean) ** 2))
        if self.n == 0:
            self.mean_f, self.m2_f = mean, m2
        elif n:
            delta, total = mean - self.mean_f, self.n + n
            self.mean_f += delta * n / total
            self.m2_f += m2 + delta * delta * self.n * n / total
        self.n += n
        d = y_r - f
        self.sse_f += float(np.sum(d * d))
        d = i_alone - i_true
        self.sse_alone += float(np.sum(d * d))
        d = i_on - i_true
        self.sse_online += float(np.sum(d * d))
        return f

    def numbers(self, where: str) -> dict[str, Any]:
        """The numbers (eqs 41-43 for Et); a MetricError naming `where` and the reason when
        one is not finite."""
        if self.n == 0:
            raise MetricError(f"{where}: no row to evaluate")
        with np.errstate(divide="ignore", invalid="ignore"):
            et = float(np.sqrt(self.sse_f) / np.sqrt(self.m2_f))  # eqs 41-43
        out = {
            "n": self.n,
            "forward": {"et": et, "rmse_n": float(np.sqrt(self.sse_f / self.n))},
            "inverse_current_rmse": float(np.sqrt(self.sse_alone / self.n)),
            "inverse_current_rmse_online": float(np.sqrt(self.sse_online / self.n)),
            "continuity": self.continuity,
            "i_max": self.i_max,
        }
        if not self.m2_f > 0.0:
            raise MetricError(
                f"{where}: forward Et is {et}: the measured force does not vary over the"
                f" {self.n} rows (Et is relative to its spread)"
            )
        check_finite(
            out,
            f"{where}, {self.n} rows",
            "the model's force or the data's values overflow (a model of other data, or"
            " values far outside what it was trained on)",
        )
        return out


def check_finite(numbers: dict[str, Any], where: str, why: str) -> None:
    """A MetricError naming `where`, every number of `numbers` (nested) that is NaN or
    infinite, and `why`: a report that cannot be trusted."""
    bad = [f"{k} {v}" for k, v in _flat_numbers(numbers).items() if not math.isfinite(v)]
    if bad:
        raise MetricError(f"{where}: {', '.join(bad)}: not finite: {why}")


def _flat_numbers(d: Any, prefix: str = "") -> dict[str, float]:
    out: dict[str, float] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(_flat_numbers(v, f"{prefix}{k}."))
    elif isinstance(d, float | int) and not isinstance(d, bool):
        out[prefix.rstrip(".")] = float(d)
    return out


@dataclass
class EtSum:
    """Forward Et (eqs 41-43) and RMSE of rows given piece by piece (`add`): sums only, the
    force's spread combined piece by piece (Chan et al.), as `Scores` does."""

    n: int = 0
    mean_f: float = 0.0
    m2_f: float = 0.0
    sse_f: float = 0.0

    def add(self, y: np.ndarray, f: np.ndarray) -> None:
        y, f = np.asarray(y, dtype=float), np.asarray(f, dtype=float)
        n = y.size
        if not n:
            return
        mean = float(np.mean(y))
        m2 = float(np.sum((y - mean) ** 2))
        total = self.n + n
        delta = mean - self.mean_f
        self.m2_f += m2 + delta * delta * self.n * n / total
        self.mean_f += delta * n / total
        self.n = total
        self.sse_f += float(np.sum((y - f) ** 2))

    def numbers(self) -> dict[str, Any]:
        """n, et (NaN without rows or without spread of the force) and rmse_n."""
        et = math.sqrt(self.sse_f) / math.sqrt(self.m2_f) if self.m2_f > 0.0 else math.nan
        rms = math.sqrt(self.sse_f / self.n) if self.n else math.nan
        return {"n": self.n, "et": et, "rmse_n": rms}
