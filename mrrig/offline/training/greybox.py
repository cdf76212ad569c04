"""Training the grey-box forward model (`mrrig.loop.greybox`) in two stages: the Bouc-Wen twin
first (`kinds.twin_kind`'s fit, `mrrig identify`'s), then a small tanh network on what the
twin misses, of the twin's own states and the measured motion.

The twin's states are computed as the daemon's tracker carries them (`twin_states`: from rest
with the coil off at the first sample of each stretch, the command of each sample held until
the next, the integrator at `SUBSTEP_S`). The network is fitted by Levenberg-Marquardt
(`lm.train_lm`) on at most `max_rows` rows drawn from the training rows of runs spread over
the data (about `RUN_SAMPLES` samples per row; a stretch's warm-up, `identify.fit.warm_rows`,
left out: its states are not yet the motion's), early-stopped on the block hold-out's rows.
Pure numerics.
"""

from __future__ import annotations

import math
from dataclasses import astuple

import numpy as np

from damper.plant import BoucWenDamper, bouc_wen_force
from damper.plant_file import Plant
from mrrig.loop.greybox import RESIDUAL_INPUTS, GreyBoxModel, force_and_du, residual_rows
from mrrig.offline.identify.fit import Run, warm_rows
from mrrig.offline.training.lm import train_lm

SUBSTEP_S = 1e-3  # the grey-box twin's integrator sub-step (the daemon's tracker uses the same)
HIDDEN = 8  # the residual network's hidden units
MAX_ROWS = 4000  # the network's LM rows at most (and half as many early-stopping rows)
RUN_SAMPLES = 5  # the runs the rows are drawn from: so many samples per LM row at most


def twin_states(plant: Plant, runs: list[Run], substep_s: float = SUBSTEP_S) -> list[np.ndarray]:
    """Per run, its twin's (z, y, u) at each sample (3 x n), as `GreyBoxTracker` carries them:
    at rest with u = 0 at the first sample, then stepped to each sample with the previous
    sample's command held (plain floats: many times as fast as a numpy batch of runs)."""
    out = []
    for r in runs:
        damper = BoucWenDamper(plant.params, substep_s)
        x, xd, cmd = r.x.tolist(), r.xd.tolist(), r.command.tolist()
        states = np.empty((3, len(x)))
        damper.reset(x[0], xd[0], 0.0)
        states[:, 0] = damper.state
        period = r.period_s if len(x) > 1 else 1.0
        for k in range(1, len(x)):
            damper.step(x[k], xd[k], cmd[k - 1], period)
            states[:, k] = damper.state
        out.append(states)
    return out


def _spread(
    runs: list[Run], val: list[np.ndarray], samples: int
) -> tuple[list[Run], list[np.ndarray]]:
    """Where the runs hold more than `samples` samples, as many of them, spread evenly over
    the list, as hold about that many (the twin's states are the second stage's cost)."""
    total = sum(r.t.size for r in runs)
    if total <= samples:
        return runs, val
    k = max(1, min(len(runs), math.ceil(len(runs) * samples / total)))
    pick = np.unique(np.linspace(0, len(runs) - 1, k).round().astype(int)).tolist()
    return [runs[j] for j in pick], [val[j] for j in pick]


def greybox_run_forces(model: GreyBoxModel, runs: list[Run]) -> list[np.ndarray]:
    """The grey-box force over each run (its twin from rest at the first sample)."""
    out = []
    for r, s in zip(runs, twin_states(model.plant, runs, model.substep_s), strict=True):
        f, _ = force_and_du(model, s[0], s[1], s[2], r.x, r.xd)
        out.append(f)
    return out


def fit_residual(
    plant: Plant,
    runs: list[Run],
    val: list[np.ndarray],
    *,
    hidden: int = HIDDEN,
    max_epochs: int = 300,
    max_rows: int = MAX_ROWS,
    seed: int = 0,
) -> tuple[GreyBoxModel, dict]:
    """The second stage: the network on the twin's residual over the runs' warm rows, fitted
    on those not in `val` (per run, a bool mask: the block hold-out), early-stopped on those
    in it; the grey-box model and the LM report's numbers."""
    runs, val = _spread(runs, val, RUN_SAMPLES * max_rows)
    states = twin_states(plant, runs, SUBSTEP_S)
    X, r, held = [], [], []
    k = astuple(plant.params)
    for run, s, v in zip(runs, states, val, strict=True):
        w = warm_rows(run)
        f_twin = bouc_wen_force(s[0], s[1], s[2], run.x, run.xd, k) + plant.offset_n
        X.append(residual_rows(s[0], s[1], s[2], run.x, run.xd)[w])
        r.append((run.force - f_twin)[w])
        held.append(v[w])
    Xa, ra, va = np.concatenate(X), np.concatenate(r), np.concatenate(held)
    rng = np.random.default_rng(seed)
    fit_idx, val_idx = np.flatnonzero(~va), np.flatnonzero(va)
    if fit_idx.size > max_rows:
        fit_idx = np.sort(rng.choice(fit_idx, max_rows, replace=False))
    if val_idx.size > max_rows // 2:
        val_idx = np.sort(rng.choice(val_idx, max_rows // 2, replace=False))
    units = ["m", "m", plant.command_unit, "m", "m/s"]
    net, rep = train_lm(
        Xa[fit_idx],
        ra[fit_idx],
        RESIDUAL_INPUTS,
        units,
        "force_residual",
        "N",
        hidden=hidden,
        max_epochs=max_epochs,
        validation=(Xa[val_idx], ra[val_idx]) if val_idx.size else None,
        validation_fraction=0.1,
        seed=seed,
    )
    numbers = {
        "residual_rows": int(fit_idx.size),
        "residual_hidden": hidden,
        "residual_epochs": rep.epochs,
        "residual_best_epoch": rep.best_epoch,
        "twin_rms_residual_n": float(np.sqrt(np.mean(ra**2))),
    }
    return GreyBoxModel(plant, "greybox", net, SUBSTEP_S, numbers), numbers
