"""The kinds of forward model `mrrig train` chooses among (`kind_choice`): the static MLP, the
history MLP, the grey-box, the Bouc-Wen twin and the GRU, each with its final fit, its fold fit
and its forces on data.

Each fold is fitted on the rest by the kind's fold fit: the final model's procedure cut down to
fit the time budget (an MLP: `fold_rows` LM rows, at most `FOLD_EPOCHS` epochs, one start, or
where `mrrig train` is given several tests the mean of `ENSEMBLE_MEMBERS` starts, as its final
model; a GRU: the seconds a fold may take). The MLP structures come from
`select.choose_features`: the static MLP is its best candidate without history inputs, the
history MLP its best with them. The twin is `mrrig identify`'s fit (`offline.identify.fit`) on
the training rows, at most `TWIN_FIT_WINDOWS` windows of them; eq. 36's eta stays at the
start's where the command is held per run (such data cannot tell the lag, and the fit would
take it anywhere).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from damper.plant_file import Plant
from mrrig.loop.controllers import Controller, ControllerSettings, make_controller
from mrrig.loop.greybox import GreyBoxModel
from mrrig.loop.twin_model import SUBSTEP_S, TwinModel
from mrrig.offline.datasets import Series
from mrrig.offline.identify.fit import FREE, Run, fit, run_force, warm_rows
from mrrig.offline.identify.identify import start_plant
from mrrig.offline.training.data import run_ids, sample_period, stretch_bounds, stretches
from mrrig.offline.training.ensemble import average_mlps
from mrrig.offline.training.features import COIL_LAG_TAU_S, feature_rows, features
from mrrig.offline.training.fit import block_split, train_forward
from mrrig.offline.training.greybox import HIDDEN as GREYBOX_HIDDEN
from mrrig.offline.training.greybox import fit_residual, greybox_run_forces
from mrrig.offline.training.gru import DEFAULT_HIDDEN as GRU_HIDDEN
from mrrig.offline.training.gru import fit_gru, gru_forces
from mrrig.offline.training.report import EtSum, predict
from mrrig.offline.training.select import Candidate, command_varies, equal_work_rows

log = logging.getLogger(__name__)

STATIC_MLP, HISTORY_MLP, GRU, TWIN = "static MLP", "history MLP", "GRU", "Bouc-Wen twin"
GREYBOX = "grey-box"
KIND_NAMES = (STATIC_MLP, HISTORY_MLP, GREYBOX, TWIN, GRU)  # what `model_kinds` builds
SEARCH_SHARE = 0.3  # of the budget, the MLP structure search's at most
FOLD_ROWS = 3000  # an MLP fold fit's LM rows at least; more for a smaller network, the same
FOLD_WORK = 8000 * 281**2  # LM work (rows x weights^2: 8000 rows of a 12-20-1 MLP), up to
FOLD_MAX_ROWS = 6000  # at most (a static MLP at its equal-work rows, 12771, took 97 s for 38 folds)
FOLD_EPOCHS = 150  # an MLP fold fit's LM epochs at most
GRU_MIN_FOLD_S = 20.0  # the GRU is not tried where its folds would get less each
TWIN_MIN_FOLD_S = 3.0  # nor the twin (its least-squares fit: seconds even on little data)
COST_DT_S = 0.002  # the rig's period, at which the work per frame is measured
# the twin's fit: at most so many windows of its training rows (each 0.5 s scored after 0.2 s
# from rest: `identify.fit.windows`), spread evenly, and so many least-squares evaluations
TWIN_FIT_WINDOWS = 64
TWIN_WINDOW_S, TWIN_BURN_IN_S = 0.5, 0.2
TWIN_MAX_EVALUATIONS = 60
# the folds over tests at most of every kind but the first (k-fold over tests beyond: whole
# tests left out still), so that all kinds are scored within the budget on a matrix (38 tests:
# the first kind's leave-one-test-out takes half of it)
LATER_MAX_FOLDS = 6
# an MLP kind's members where several tests are given (`mlp_kind`; `mrrig train` averages as
# many starts): on Labcontrol's 38 tests the other-test Et of the history MLP's fold fit was
# 0.0524 with one, 0.0491 with two, 0.0479 with three (three take half again the time of two)
ENSEMBLE_MEMBERS = 2


@dataclass(frozen=True)
class ModelKind:
    """A kind of forward model: how to fit one to a Series (its own block hold-out kept out),
    the (rows, measured, predicted) force of a Series' rows, the daemon's controller, and the
    fit of a cross-validation fold (given the seconds it may take; cut down from `fit` to fit
    the choice's budget), with the least seconds a fold of it needs (0: no floor)."""

    name: str
    label: str
    fit: Callable[[Series], Any]
    forces: Callable[[Any, Series], tuple[np.ndarray, np.ndarray, np.ndarray]]
    controller: Callable[[Any], Controller]
    fold_fit: Callable[[Series, float], Any] | None = None
    min_fold_s: float = 0.0
    max_folds: int | None = None  # at most so many folds over tests (k-fold beyond)
    members: int = 1  # fits averaged (an MLP kind's, `mlp_kind`)
    # the fit whose block hold-out figure is printed (it keeps that block out); default fit_fold
    block_fit: Callable[[Series, float], Any] | None = None

    def fit_fold(self, series: Series, seconds: float) -> Any:
        return self.fit(series) if self.fold_fit is None else self.fold_fit(series, seconds)


def _network_controller(model: Any, i_max: float, ahead: bool) -> Controller:
    """The daemon's network inversion of `model` (its default: feedback, one step ahead where
    the model allows it), for the work per frame."""
    settings = ControllerSettings(
        i_max, dt_s=COST_DT_S, model=model, ahead=ahead, feedback_tau_s=0.0
    )
    return make_controller("network_inversion", settings)


def mlp_kind(
    name: str,
    cand: Candidate,
    label: str,
    *,
    seed: int,
    max_epochs: int,
    holdout_fraction: float,
    i_max: float,
    members: int = 1,
) -> ModelKind:
    """An MLP of the structure `cand` (`select.Candidate`), trained as `mrrig train` does:
    the mean of `members` fits (`ensemble.average_mlps`, one network the daemon inverts),
    member k from seed + k (its initial weights, its rows and, in a fold, the tests it stops
    on), as the final model averages as many starts."""
    if members < 1:
        raise ValueError(f"an MLP kind needs at least one member, got {members}")
    feat = dict(
        current_input=cand.current_input,
        lag_tau_s=cand.lag_tau_s,
        history_samples=cand.history_samples,
        history_signals=cand.history_signals,
        history_stride=cand.history_stride,
    )

    def fit_mlp(series: Series) -> Any:
        fits = [
            train_forward(
                series,
                seed=seed + k,
                max_epochs=max_epochs,
                split="blocks",
                holdout_fraction=holdout_fraction,
                hidden=cand.hidden,
                **feat,
            )[0]
            for k in range(members)
        ]
        return average_mlps(fits)

    def cut_down(series: Series, split: str) -> Any:
        fits = [
            train_forward(
                series,
                seed=seed + k,
                max_epochs=min(max_epochs, FOLD_EPOCHS),
                split=split,
                holdout_fraction=holdout_fraction,
                hidden=cand.hidden,
                max_fit_rows=fold_rows(cand),
                rows_per_weight=0,
                **feat,
            )[0]
            for k in range(members)
        ]
        return average_mlps(fits)

    def fold_mlp(series: Series, _seconds: float) -> Any:
        """A fold: early-stopped on whole tests (segments) of the fold's own training data
        (`fit.stretch_split`), not on a block of the tests it trains on."""
        return cut_down(series, "stretches")

    def block_mlp(series: Series, _seconds: float) -> Any:
        return cut_down(series, "blocks")  # the block hold-out kept out

    def forces(model: Any, series: Series) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        X, y = features(series, **feat)
        return feature_rows(series, cand.history_samples, cand.history_stride), y, predict(model, X)

    ahead = cand.history_samples == 0
    return ModelKind(
        name,
        label,
        fit_mlp,
        forces,
        lambda m: _network_controller(m, i_max, ahead),
        fold_mlp,
        block_fit=block_mlp,
        members=members,
    )


def fold_rows(cand: Candidate) -> int:
    """An MLP fold fit's LM rows (each member's): the same work (`FOLD_WORK`) whatever its
    size, within `FOLD_ROWS` and `FOLD_MAX_ROWS`."""
    return equal_work_rows(cand, FOLD_WORK, FOLD_ROWS, FOLD_MAX_ROWS)


def _stretch_runs(series: Series) -> tuple[list[Run], list[np.ndarray]]:
    """The Series' contiguous stretches of 3 samples or more as runs, and their rows."""
    first, length = stretch_bounds(stretches(run_ids(series)))
    runs, rows = [], []
    for f, n in zip(first.tolist(), length.tolist(), strict=True):
        if n >= 3:
            sl = slice(f, f + n)
            s = (series.t, series.x, series.xd, series.current, series.force)
            runs.append(Run(*(a[sl] for a in s)))
            rows.append(np.arange(f, f + n))
    if not runs:
        raise ValueError("no run of 3 samples or more for the twin")
    return runs, rows


def twin_runs(
    series: Series, fit_rows: np.ndarray, max_windows: int = TWIN_FIT_WINDOWS
) -> tuple[list[Run], list[np.ndarray]]:
    """The Series' stretches as runs for `identify.fit`, with the rows it may fit (`fit_rows`,
    a mask); where these make more than `max_windows` windows, that many slices of burn-in
    plus window spread evenly over them instead, each scored after its burn-in."""
    runs, index = _stretch_runs(series)
    rows = [fit_rows[i] for i in index]
    period = min(r.period_s for r in runs)
    n_burn, n_win = round(TWIN_BURN_IN_S / period), max(1, round(TWIN_WINDOW_S / period))
    if sum(math.ceil(int(m.sum()) / n_win) for m in rows) <= max_windows:
        return runs, rows
    width = n_burn + n_win
    starts = [
        (j, a)
        for j, m in enumerate(rows)
        for a in range(0, m.size - width + 1, width)
        if m[a + n_burn : a + width].all()
    ]
    if not starts:
        return runs, rows
    pick = np.unique(np.linspace(0, len(starts) - 1, max_windows).round().astype(int))
    out_runs, out_rows = [], []
    for j, a in (starts[k] for k in pick.tolist()):
        r, sl = runs[j], slice(a, a + width)
        out_runs.append(Run(r.t[sl], r.x[sl], r.xd[sl], r.command[sl], r.force[sl], r.name))
        out_rows.append(np.arange(width) >= n_burn)
    return out_runs, out_rows


def block_holdout(series: Series, rows: np.ndarray, fraction: float) -> np.ndarray:
    """The block hold-out of the Series' `rows` (indices): the last `fraction` of each
    stretch, as `fit.block_split` holds it out (a bool mask over `rows`)."""
    val = np.zeros(rows.size, dtype=bool)
    val[block_split(stretches(run_ids(series))[rows], fraction).val] = True
    return val


def twin_kind(
    *,
    holdout_fraction: float,
    max_evaluations: int = TWIN_MAX_EVALUATIONS,
    start: str = "paper",
    i_max: float,
) -> ModelKind:
    """The modified Bouc-Wen twin (eqs 30-36 and an offset) fitted by `identify.fit` to the
    training rows (the block hold-out kept out, as the MLPs keep it)."""
    first = start_plant(start)

    def fit_twin(series: Series) -> Plant:
        # a command held per run cannot tell eq. 36's lag: eta stays at the start's
        free = FREE if command_varies(series) else tuple(n for n in FREE if n != "eta")
        every = np.arange(len(series))
        runs, rows = twin_runs(series, ~block_holdout(series, every, holdout_fraction))
        fitted = [r.force[m] for r, m in zip(runs, rows, strict=True)]
        offset0 = float(np.mean(np.concatenate(fitted)))
        res = fit(
            runs,
            rows,
            first.params,
            offset0,
            window_s=TWIN_WINDOW_S,
            burn_in_s=TWIN_BURN_IN_S,
            max_evaluations=max_evaluations,
            progress=log.debug,
            free=free,
        )
        log.info(
            "twin fitted to %d rows%s: Et %.4f on the fitted rows (%d evaluations, %.0f s)",
            sum(int(m.sum()) for m in rows),
            "" if "eta" in free else " (eta held: the command is held per run)",
            res.cost_et,
            res.evaluations,
            res.seconds,
        )
        identified = {
            "fitted_rows_et": res.cost_et,
            "evaluations": res.evaluations,
            "free_parameters": [*free, "offset_n"],
        }
        return Plant(res.params, res.offset_n, series.current_unit, identified)

    def forces(plant: Plant, series: Series) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The twin run open loop over each stretch from rest at its first sample; a stretch
        that starts moving scored after its warm-up (`identify.fit.warm_rows`)."""
        runs, index = _stretch_runs(series)
        f = [run_force(plant.params, plant.offset_n, r, SUBSTEP_S) for r in runs]
        warm = [warm_rows(r) for r in runs]
        rows = np.concatenate([i[w] for i, w in zip(index, warm, strict=True)])
        f = np.concatenate([g[w] for g, w in zip(f, warm, strict=True)])
        return rows, series.force[rows], f

    label = f"modified Bouc-Wen (eqs 30-36) and an offset, fitted from {start}"
    return ModelKind(
        TWIN,
        label,
        fit_twin,
        forces,
        lambda p: _network_controller(TwinModel(p), i_max, True),
        min_fold_s=TWIN_MIN_FOLD_S,
    )


def _memoized(fit_twin: Callable[[Series], Plant]) -> Callable[[Series], Plant]:
    """`fit_twin` remembering its fits by the rows fitted: the twin kind fits the twin of each
    fold first, the grey-box kind's folds (the same rows) then reuse it as their first stage."""
    memo: dict[tuple, Plant] = {}

    def fit_once(series: Series) -> Plant:
        key = (len(series), *(float(np.sum(a)) for a in (series.t, series.x, series.force)))
        if key not in memo:
            memo[key] = fit_twin(series)
        return memo[key]

    return fit_once


def greybox_kind(
    fit_twin: Callable[[Series], Plant],
    *,
    holdout_fraction: float,
    seed: int,
    i_max: float,
    hidden: int = GREYBOX_HIDDEN,
) -> ModelKind:
    """The grey-box: the twin (`fit_twin`, the twin kind's fit) and a small network on its
    residual (`training.greybox.fit_residual`: of the twin's states and the measured motion),
    in two stages, the block hold-out kept out of both (the network early-stopped on it)."""

    def fit_gb(series: Series) -> GreyBoxModel:
        plant = fit_twin(series)
        runs, index = _stretch_runs(series)
        held = block_holdout(series, np.arange(len(series)), holdout_fraction)
        model, numbers = fit_residual(
            plant, runs, [held[i] for i in index], hidden=hidden, seed=seed
        )
        log.info(
            "grey-box residual network (%d hidden) fitted on %d rows, best epoch %d of %d;"
            " the twin's RMS residual %.1f N",
            hidden,
            numbers["residual_rows"],
            numbers["residual_best_epoch"],
            numbers["residual_epochs"],
            numbers["twin_rms_residual_n"],
        )
        return model

    def forces(model: GreyBoxModel, series: Series) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Run over each stretch from rest at its first sample, scored after the warm-up of
        a stretch that starts moving, as the twin is."""
        runs, index = _stretch_runs(series)
        f = greybox_run_forces(model, runs)
        warm = [warm_rows(r) for r in runs]
        rows = np.concatenate([i[w] for i, w in zip(index, warm, strict=True)])
        f = np.concatenate([g[w] for g, w in zip(f, warm, strict=True)])
        return rows, series.force[rows], f

    label = (
        f"the Bouc-Wen twin and a {hidden}-hidden network on its residual (of z, x - y, u, x,"
        " xd), two stages"
    )
    return ModelKind(
        GREYBOX,
        label,
        fit_gb,
        forces,
        lambda m: _network_controller(m, i_max, True),
        min_fold_s=TWIN_MIN_FOLD_S,
        max_folds=LATER_MAX_FOLDS,
    )


def gru_kind(*, seed: int, holdout_fraction: float, lag_tau_s: float, i_max: float) -> ModelKind:
    """The GRU forward model (`training.gru.fit_gru`, its defaults) of the lagged command
    (`lag_tau_s`: the structure search's fitted lag where it fitted one), run over each
    stretch from the zero state (`gru_forces`)."""

    def fit(series: Series, seconds: float | None = None) -> Any:
        model, report = fit_gru(
            series,
            seed=seed,
            holdout_fraction=holdout_fraction,
            lag_tau_s=lag_tau_s,
            max_seconds=seconds,
        )
        log.info(
            "GRU fitted: best epoch %d of %d%s, %.0f s",
            report["best_epoch"],
            report["epochs"],
            " (time limit)" if report["time_limited"] else "",
            report["seconds"],
        )
        return model

    label = f"{GRU_HIDDEN} units, the command lagged {lag_tau_s * 1e3:.2f} ms"
    return ModelKind(
        GRU,
        label,
        fit,
        gru_forces,
        lambda m: _network_controller(m, i_max, True),
        fit,
        GRU_MIN_FOLD_S,
    )


def best_candidates(search: dict[str, Any]) -> dict[str, Candidate]:
    """The MLP search's best candidate without history inputs and with them (lowest CV Et in
    its inversion budget, else lowest), from `select.choose_features`' report."""
    names = {f.name for f in fields(Candidate)}
    best: dict[str, tuple[bool, float, Candidate]] = {}
    for c in search["candidates"]:
        kind = HISTORY_MLP if c["history_samples"] else STATIC_MLP
        args = {k: v for k, v in c.items() if k in names}
        args["history_signals"] = tuple(args["history_signals"])
        key = (not c["in_budget"], c["cv_et"])
        if kind not in best or key < best[kind][:2]:
            best[kind] = (*key, Candidate(**args))
    return {k: v[2] for k, v in best.items()}


def model_kinds(
    series: Series,
    search: dict[str, Any],
    *,
    seed: int,
    max_epochs: int,
    holdout_fraction: float,
    i_max: float,
    members: int = 1,
) -> tuple[list[ModelKind], dict[str, Candidate], dict[str, str]]:
    """The kinds to choose among, the MLP structures of the two MLP kinds, and the kinds left
    out with why: the static and history MLPs of the structure search (`search`; the one it
    found better first: the first kind is scored whatever the budget, and by leaving each
    test out; every later kind by at most `LATER_MAX_FOLDS` folds over tests), the twin, the
    grey-box (its first stage the twin's fits, remembered) and the GRU (the slowest to fit:
    last, so that the budget cuts it first). Each MLP kind averages `members` fits
    (`mlp_kind`), as the final model averages as many starts."""
    cands = best_candidates(search)
    kinds, left_out = [], {}
    for name in sorted((STATIC_MLP, HISTORY_MLP), key=lambda n: _search_et(search, n)):
        if name in cands:
            kind = mlp_kind(
                name,
                cands[name],
                cands[name].label(_period(series)),
                seed=seed,
                max_epochs=max_epochs,
                holdout_fraction=holdout_fraction,
                i_max=i_max,
                members=members,
            )
            kinds.append(replace(kind, max_folds=LATER_MAX_FOLDS) if kinds else kind)
        else:
            left_out[name] = "the structure search tried no such candidate"
    twin = twin_kind(holdout_fraction=holdout_fraction, i_max=i_max)
    fit_twin = _memoized(twin.fit)
    kinds.append(replace(twin, fit=fit_twin, max_folds=LATER_MAX_FOLDS))
    kinds.append(greybox_kind(fit_twin, holdout_fraction=holdout_fraction, seed=seed, i_max=i_max))
    lag = search.get("lag_fit") or {"tau_s": COIL_LAG_TAU_S}
    gru = gru_kind(
        seed=seed, holdout_fraction=holdout_fraction, lag_tau_s=lag["tau_s"], i_max=i_max
    )
    kinds.append(replace(gru, max_folds=LATER_MAX_FOLDS))
    return kinds, cands, left_out


def _search_et(search: dict[str, Any], name: str) -> float:
    """The structure search's lowest CV Et of the MLP kind `name` (inf where it tried none)."""
    ets = [
        c["cv_et"]
        for c in search["candidates"]
        if bool(c["history_samples"]) == (name == HISTORY_MLP)
    ]
    return min(ets, default=math.inf)


def _period(series: Series) -> float:
    """The first stretch's sample period (the MLP candidates' labels count taps in time)."""
    first, length = stretch_bounds(stretches(run_ids(series)))
    return sample_period(series.t[first[0] : first[0] + length[0]]) if len(series) > 1 else 1.0


def kind_result(
    kind: ModelKind,
    series: Series,
    holdout_fraction: float,
    validate: list[tuple[str, Series]],
) -> tuple[Any, dict[str, Any]]:
    """The chosen kind's model (a twin, a GRU), fitted to all the training rows (the block
    hold-out kept out), with its Et on the block hold-out and on each validation test
    (`validate`: name, Series)."""
    model = kind.fit(series)
    rows, y, f = kind.forces(model, series)
    val = block_holdout(series, rows, holdout_fraction)
    block = EtSum()
    block.add(y[val], f[val])
    per, pooled = [], EtSum()
    for name, s in validate:
        _, yv, fv = kind.forces(model, s)
        one = EtSum()
        one.add(yv, fv)
        pooled.add(yv, fv)
        per.append({"file": name, **one.numbers()})
    report = {
        "block_holdout": block.numbers(),
        "holdout_fraction": holdout_fraction,
        "validate": {"per_test": per, "forward": pooled.numbers()} if validate else None,
    }
    return model, report
