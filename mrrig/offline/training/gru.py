"""Training the recurrent (GRU) forward model with torch, exported for the daemon's numpy loop
(mrrig/loop/gru.py).

The API (stable; `kinds` and `mrrig train --features gru` call it):

    fit_gru(series, *, seed=0, hidden=DEFAULT_HIDDEN, max_epochs=DEFAULT_EPOCHS,
            holdout_fraction=HOLDOUT_FRACTION, current_input="lagged",
            lag_tau_s=COIL_LAG_TAU_S, window_s=WINDOW_S, burn_in_s=BURN_IN_S,
            u_in_cell=False)
        -> (GRUModel, report: dict)
    gru_forces(model, series) -> (rows, measured force, predicted force)
    gru_result(series, *, tests, test_names, validate=(), max_folds=MAX_FOLDS, **fit_gru options)
        -> (GRUModel, report: dict)   (what `mrrig train --features gru` prints)
    simulated_matrix_gru(path, seed=0, hidden=DEFAULT_HIDDEN) -> GRUModel   (the demo's data)

The data pipeline is the MLP's: a Series in SI units (`data`), its stretches (a run split by
excluded samples is one stretch per piece), the time-block split of `fit.block_split` (the last
`holdout_fraction` of each stretch held out, early stopping on the same fraction before it).
The fitted part of each stretch is cut into windows of `burn_in_s + window_s`, half a window
apart: the state starts at zero at a window's start and is warmed over its burn-in, the loss
(mean squared standardised force) is taken on the rest. Adam, full batch, early stopping on
the stopping part's windows, the best epoch kept. `gru_forces` runs the model over each whole
stretch from the zero state, as the daemon runs it from `reset`; the report's Et on the hold-out
is that run's on the held-out rows (eqs 41-43). Deterministic for a seed: torch's seed, one
thread, float32 on the CPU.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mrrig.loop.gru import GRUModel, affine_solve
from mrrig.offline.datasets import DataError, Series
from mrrig.offline.metrics import error_norm, rmse
from mrrig.offline.training.crossval import MAX_FOLDS, cross_validate_with
from mrrig.offline.training.data import measured_series, run_ids, stretch_bounds, stretches
from mrrig.offline.training.features import COIL_LAG_TAU_S, INPUT_NAMES, command_input
from mrrig.offline.training.fit import (
    HOLDOUT_FRACTION,
    _period,
    block_split,
    series_fingerprint,
    training_envelope,
)
from mrrig.offline.training.report import ONLINE_CONTINUITY_CANDIDATES, EtSum

log = logging.getLogger(__name__)

# chosen on the simulated matrix's block hold-out Et at 1000 epochs: u in the read-out, 12 units
# 0.0139, 16 units 0.0101; u in the cell too, 12: 0.0197, 16: 0.0161. The daemon's solve with
# 16 takes about 30 us a frame
DEFAULT_HIDDEN = 16
DEFAULT_EPOCHS = 3000  # at most: the stopping blocks end it (1453 epochs on the simulated matrix)
WINDOW_S = 0.3  # the scored part of a training window
BURN_IN_S = 0.1  # the state warmed before it
LEARNING_RATE = 1e-2
MAX_FAIL = 30  # epochs without a better stopping loss before the fit stops
TORCH_THREADS = 1


def model_inputs(series: Series, current_input: str, lag_tau_s: float) -> np.ndarray:
    """The GRU's inputs (N, 4): x, xd, xdd and u, u the lagged current (`current_input =
    "lagged"`, eq. 36) or the command held over the period before each sample
    ("commanded"); both depend only on commands sent before the sample."""
    if series.xd is None or series.xdd is None:
        raise ValueError(f"{series.name}: no velocity/acceleration: use estimate_derivatives")
    if current_input == "lagged":
        u = command_input(series, "lagged", lag_tau_s)
    elif current_input == "commanded":
        u = series.current.astype(float).copy()
        first, length = stretch_bounds(stretches(run_ids(series)))
        for f, n in zip(first.tolist(), length.tolist(), strict=True):
            u[f + 1 : f + n] = series.current[f : f + n - 1]
    else:
        raise ValueError(f"unknown current input {current_input!r} (lagged, commanded)")
    return np.column_stack([series.x, series.xd, series.xdd, u])


def _windows(pieces: list[tuple[int, int]], burn: int, win: int) -> list[int]:
    """Start rows of windows of burn + win rows inside the pieces (first, stop), half a
    window apart; a piece too short for one gets one of its own length if it has more than
    `burn` rows to score (the caller pads)."""
    starts = []
    for a, b in pieces:
        if b - a >= burn + win:
            starts += list(range(a, b - burn - win + 1, max(1, win // 2)))
        elif b - a > burn + 1:
            starts.append(a)
    return starts


def _batch(Z: np.ndarray, y: np.ndarray, starts: list[int], stops: list[int], width: int):
    """(inputs (B, width, 4), targets (B, width), mask (B, width)) of the windows, padded."""
    B = len(starts)
    Xb = np.zeros((B, width, Z.shape[1]), dtype=np.float32)
    yb = np.zeros((B, width), dtype=np.float32)
    mb = np.zeros((B, width), dtype=np.float32)
    for j, (a, b) in enumerate(zip(starts, stops, strict=True)):
        n = min(width, b - a)
        Xb[j, :n], yb[j, :n], mb[j, :n] = Z[a : a + n], y[a : a + n], 1.0
    return Xb, yb, mb


def fit_gru(
    series: Series,
    *,
    seed: int = 0,
    hidden: int = DEFAULT_HIDDEN,
    max_epochs: int = DEFAULT_EPOCHS,
    holdout_fraction: float = HOLDOUT_FRACTION,
    current_input: str = "lagged",
    lag_tau_s: float = COIL_LAG_TAU_S,
    window_s: float = WINDOW_S,
    burn_in_s: float = BURN_IN_S,
    u_in_cell: bool = False,
    max_seconds: float | None = None,
) -> tuple[GRUModel, dict[str, Any]]:
    """A GRU forward model of `hidden` units fitted to the training blocks of `series` (module
    docstring); the report: epochs, best epoch, seconds, the split's rule, and `holdout_et`,
    the block hold-out's Et (the optimistic figure: the same tests, later in time).
    `max_seconds`: the training stops after the epoch that spends it (the best epoch kept;
    the report's `time_limited` says so)."""
    import torch  # the offline work alone imports torch (import-linter)

    t0 = time.perf_counter()
    X = model_inputs(series, current_input, lag_tau_s)
    y = np.asarray(series.force, dtype=float)
    stretch = stretches(run_ids(series))
    sp = block_split(stretch, holdout_fraction)
    dt = _period(series)
    if dt is None:
        raise DataError(f"{series.name}: no run of two samples or more: no sample period")
    burn, win = max(1, round(burn_in_s / dt)), max(2, round(window_s / dt))
    train_mask = np.zeros(len(y), dtype=bool)
    train_mask[sp.train] = True
    stop_mask = np.zeros(len(y), dtype=bool)
    if sp.stop is not None:
        stop_mask[sp.stop] = True
    fit_mask = train_mask & ~stop_mask
    in_mean = X[fit_mask].mean(axis=0)
    in_std = X[fit_mask].std(axis=0)
    in_std[in_std <= 1e-12 * np.maximum(1.0, np.abs(in_mean))] = 1.0  # a constant input
    out_mean, out_std = float(y[fit_mask].mean()), float(y[fit_mask].std()) or 1.0
    Z = (X - in_mean) / in_std
    ys = (y - out_mean) / out_std

    first, length = stretch_bounds(stretch)

    def pieces(mask: np.ndarray, lead: bool) -> tuple[list[int], list[int]]:
        """Windows over each stretch's rows in `mask`; with `lead` a window starts `burn`
        rows before them (the state warmed on the rows just before, which are trained)."""
        out: list[tuple[int, int]] = []
        for f, n in zip(first.tolist(), length.tolist(), strict=True):
            rows = np.flatnonzero(mask[f : f + n])
            if rows.size:
                a, b = f + int(rows[0]), f + int(rows[-1]) + 1
                out.append((max(f, a - burn) if lead else a, b))
        starts = _windows(out, burn, win)
        stops = [next(b for a, b in out if a <= s < b) for s in starts]
        return starts, stops

    fit_starts, fit_stops = pieces(fit_mask, False)
    stop_starts, stop_stops = pieces(stop_mask, True)
    if not fit_starts:
        raise DataError(
            f"{series.name}: no training window of {burn_in_s + window_s:g} s: runs too short"
        )
    width = burn + win
    Xf, yf, mf = _batch(Z, ys, fit_starts, fit_stops, width)
    mf[:, :burn] = 0.0  # the burn-in warms the state, it is not scored
    torch.manual_seed(seed)
    torch.set_num_threads(TORCH_THREADS)
    n_cell = 4 if u_in_cell else 3
    net = torch.nn.GRU(n_cell, hidden, batch_first=True)
    head, gain = torch.nn.Linear(hidden, 1), torch.nn.Linear(hidden, 1)
    params = [*net.parameters(), *head.parameters(), *gain.parameters()]
    opt = torch.optim.Adam(params, lr=LEARNING_RATE)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=10)

    def loss_of(xb, yb, mb) -> torch.Tensor:
        h = net(xb[..., :n_cell])[0]
        out = (head(h) + xb[..., 3:4] * gain(h))[..., 0]
        return ((out - yb) ** 2 * mb).sum() / mb.sum()

    fit_t = tuple(torch.from_numpy(a) for a in (Xf, yf, mf))
    stop_t = None
    if stop_starts:
        Xs, ys_, ms = _batch(Z, ys, stop_starts, stop_stops, width)
        ms[:, :burn] = 0.0
        stop_t = tuple(torch.from_numpy(a) for a in (Xs, ys_, ms))
    best = (np.inf, 0, [p.detach().clone() for p in params])
    epoch = fails = 0
    time_limited = False
    for epoch in range(1, max_epochs + 1):
        opt.zero_grad()
        loss = loss_of(*fit_t)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        with torch.no_grad():
            judged = float(loss_of(*stop_t)) if stop_t is not None else float(loss)
        sched.step(judged)
        if judged < best[0]:
            best, fails = (judged, epoch, [p.detach().clone() for p in params]), 0
        else:
            fails += 1
            if fails >= MAX_FAIL:
                break
        if max_seconds is not None and time.perf_counter() - t0 > max_seconds:
            time_limited = epoch < max_epochs
            break
    with torch.no_grad():
        for p, b in zip(params, best[2], strict=True):
            p.copy_(b)
    model = export_gru(
        net,
        head,
        gain,
        in_mean=in_mean,
        in_std=in_std,
        out_mean=out_mean,
        out_std=out_std,
        command_unit=series.current_unit,
        meta={
            "kind": "gru",
            "trainer": f"torch {torch.__version__} Adam, windows with burn-in",
            "hidden": hidden,
            "seed": seed,
            "current_input": current_input,
            "lag_tau_s": lag_tau_s if current_input == "lagged" else None,
            "command_unit": series.current_unit,
            "sample_period_s": dt,
            "window_s": window_s,
            "burn_in_s": burn_in_s,
            "u_in_cell": u_in_cell,
            "split": sp.kind,
            "split_rule": sp.rule,
            "holdout_fraction": holdout_fraction,
            "n_samples": len(y),
            "n_runs": int(np.unique(run_ids(series)).size),
            "data_fingerprint": series_fingerprint(series),
            "current_range_a": [float(series.current.min()), float(series.current.max())],
        },
    )
    envelope = training_envelope(series, np.arange(len(y)), sp)
    if envelope is not None:
        model.meta["envelope"] = envelope.to_meta()
    if not u_in_cell:
        mu, scores = choose_gru_continuity(model, series, sp.train)
        model.meta["online_continuity"] = mu
        model.metrics["online_continuity_rmse"] = scores
    rows, measured, predicted = gru_forces(model, series)
    held = np.zeros(len(y), dtype=bool)
    held[sp.val] = True
    holdout_et = error_norm(measured[held[rows]], predicted[held[rows]])
    model.metrics["holdout_et"] = holdout_et
    report = {
        "split": {"rule": sp.rule, "kind": sp.kind, "n_train": int(sp.train.size)},
        "windows": len(fit_starts),
        "stop_windows": len(stop_starts),
        "epochs": epoch,
        "best_epoch": best[1],
        "time_limited": time_limited,
        "stop_loss": best[0],
        "seconds": time.perf_counter() - t0,
        "holdout_et": holdout_et,
    }
    log.info(
        "GRU %d units: %d windows, best epoch %d of %d, %.1f s, block hold-out Et %.4f",
        hidden,
        len(fit_starts),
        best[1],
        epoch,
        report["seconds"],
        holdout_et,
    )
    return model, report


def export_gru(
    net: Any,
    head: Any,
    gain: Any,
    *,
    in_mean: np.ndarray,
    in_std: np.ndarray,
    out_mean: float,
    out_std: float,
    command_unit: str,
    meta: dict[str, Any],
) -> GRUModel:
    """The numpy model of a torch `nn.GRU` (one layer, batch_first) and its read-out, `head`
    plus the standardised u times `gain` (each an `nn.Linear(H, 1)`), with the standardisation
    they were trained in (float64 copies of the weights)."""

    def w(p: Any) -> np.ndarray:
        return p.detach().double().numpy().copy()

    return GRUModel(
        input_names=list(INPUT_NAMES),
        input_units=["m", "m/s", "m/s^2", command_unit],
        output_name="force",
        output_unit="N",
        in_mean=in_mean,
        in_std=in_std,
        out_mean=out_mean,
        out_std=out_std,
        W_ih=w(net.weight_ih_l0),
        W_hh=w(net.weight_hh_l0),
        b_ih=w(net.bias_ih_l0),
        b_hh=w(net.bias_hh_l0),
        W_out=w(head.weight)[0],
        b_out=float(w(head.bias)[0]),
        V_out=w(gain.weight)[0],
        c_out=float(w(gain.bias)[0]),
        meta=meta,
    )


def online_gru_inversion(model: GRUModel, series: Series, continuity: float) -> np.ndarray:
    """The u (N,) the daemon's solve makes for each row's measured force, each stretch from
    u = 0, each row from the previous row's u with `continuity` (`loop.gru.affine_solve`), over
    the data's range of commands: `report.online_inversion` for a GRU whose u is the
    read-out's alone (its states do not depend on u)."""
    lag = model.lag_tau_s
    X = model_inputs(series, model.meta["current_input"], lag if lag is not None else 1.0)
    lo, hi = 0.0, float(np.max(series.current))
    m, s = float(model.in_mean[3]), float(model.in_std[3])
    w_force, w_cont = 1.0 / model.out_std**2, continuity / s**2
    out = np.empty(len(series))
    first, length = stretch_bounds(stretches(run_ids(series)))
    for f, n in zip(first.tolist(), length.tolist(), strict=True):
        H = model.states(X[f : f + n])
        f_m = model.read_out(H, 0.0).tolist()
        gain = (model.out_std * (H @ model.V_out + model.c_out) / s).tolist()
        target = series.force[f : f + n].tolist()
        u = 0.0
        for k in range(n):
            u = affine_solve(f_m[k], gain[k], m, target[k], u, lo, hi, w_force, w_cont)
            out[f + k] = u
    return out


def choose_gru_continuity(
    model: GRUModel, series: Series, train_rows: np.ndarray
) -> tuple[float, dict[str, float]]:
    """The continuity of the on-line inversion chosen on the training rows alone (the smallest
    RMSE of u there), as `report.choose_continuity` chooses the network's; and each
    candidate's RMSE."""
    lag = model.lag_tau_s
    u_true = model_inputs(series, model.meta["current_input"], lag if lag is not None else 1.0)
    scores = {
        f"{mu:g}": rmse(online_gru_inversion(model, series, mu)[train_rows], u_true[train_rows, 3])
        for mu in ONLINE_CONTINUITY_CANDIDATES
    }
    best = min(scores, key=scores.get)
    log.info("GRU on-line inversion, training-row u RMSE by continuity: %s", scores)
    return float(best), scores


def gru_forces(model: GRUModel, series: Series) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, measured, predicted) force over every row of `series`: the model run over each
    stretch from the zero state, as the daemon runs it after `reset`."""
    lag = model.lag_tau_s
    X = model_inputs(series, model.meta["current_input"], lag if lag is not None else 1.0)
    pred = np.empty(len(series))
    first, length = stretch_bounds(stretches(run_ids(series)))
    for f, n in zip(first.tolist(), length.tolist(), strict=True):
        pred[f : f + n] = model.predict(X[f : f + n])
    return np.arange(len(series)), np.asarray(series.force, dtype=float), pred


def gru_result(
    series: Series,
    *,
    tests: np.ndarray,
    test_names: Sequence[str],
    validate: Sequence[tuple[str, Series]] = (),
    max_folds: int = MAX_FOLDS,
    **options: Any,
) -> tuple[GRUModel, dict[str, Any]]:
    """`mrrig train --features gru`: the GRU fitted to `series` (`fit_gru` with `options`),
    its block hold-out Et (the optimistic figure), the other-test estimate where several tests
    are given (`crossval.cross_validate_with`: each fold a GRU fitted on the other tests, run
    over the left-out ones) and its Et on each validation test (never trained on)."""
    model, report = fit_gru(series, **options)
    if max_folds and np.unique(tests).size > 1:
        report["other_tests"] = cross_validate_with(
            series,
            tests,
            test_names,
            lambda s: fit_gru(s, **options)[0],
            lambda m, s: gru_forces(m, s)[1:],
            max_folds=max_folds,
            seed=options.get("seed", 0),
        )
        model.metrics["other_test_et"] = report["other_tests"]["overall"]["et"]
    per, pooled = [], EtSum()
    for name, s in validate:
        _, y, f = gru_forces(model, s)
        one = EtSum()
        one.add(y, f)
        pooled.add(y, f)
        per.append({"file": name, **one.numbers()})
    report["validate"] = {"per_test": per, "forward": pooled.numbers()} if validate else None
    if validate:
        model.metrics["validate_et"] = pooled.numbers()["et"]
    return model, report


def simulated_matrix_gru(path: str | Path, seed: int = 0, hidden: int = DEFAULT_HIDDEN) -> GRUModel:
    """A GRU trained on the simulated characterization matrix (data set B, the simulator's
    plant and sensor noise: the data of the demo's network, `fit.simulated_matrix_model`) with
    its defaults, saved to `path`."""
    from mrrig.offline.datasets import dataset_b

    model, _ = fit_gru(measured_series(dataset_b()), seed=seed, hidden=hidden)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    model.save(path)
    return model
