"""`mrrig bench matrix`: training on the full characterization matrix (paper Table 1) on the
simulator, and the paper's validation numbers (spec/modeling.md 4 B, 5).

Simulates the 150 runs (data set B defaults: 0.5 kHz, sensor noise and quantisation), gives
the daemon's Kalman estimates of xd/xdd from the noisy displacement (`estimate_derivatives`,
first 0.1 s of each run dropped), trains the forward network and the supervised inverse MLP as
`mrrig train` does (the last 15 % of each run held out, LM on a 12771-row coverage subsample
of the rest; the paper drew a random 12771 / 1419), and prints forward Et, the inverse-current
RMSE (A) and the tracking error (N) of network inversion against the supervised inverse. The
plant's force for the inverted currents is its steady-state response: the damper run at that
constant current through the sample's own sine, read at the sample's instant.

Then the closed-loop check: for a few runs the plant (preset rig-current) is driven at 0.5 kHz by
each controller tracking the run's measured force, the controller seeing Kalman estimates of the
noisy displacement and the plant the true motion (the loop of `mrrig.offline.simulation.closed_loop`
with that one difference). The loop starts settle_s before the run at rest; the desired force
there is the plant's own open-loop force, and only the run's own second is scored. Network
inversion (with the continuity `mrrig train` keeps in the model file, the daemon's default)
runs without the load-cell feedback, with it (residual time constant `FEEDBACK_TAU_S`) and
incremental (the last residual as it is); the root (continuity 0) without feedback beside them.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from damper.plant import BoucWenDamper, BoucWenParams, simulate
from damper.signals import sine
from mrrig import json_text
from mrrig.cli_args import COUNT, SEED, HelpFormatter, output_file
from mrrig.loop.controllers import ControlInput, Controller, NetworkInversion, SupervisedInverse
from mrrig.loop.estimation import KalmanEstimator
from mrrig.loop.mlp import MLP
from mrrig.offline.datasets import DISPLACEMENT_LSB_M, Series, dataset_b, dataset_b_conditions
from mrrig.offline.metrics import error_norm, percentiles
from mrrig.offline.training import measured_series, train_and_validate

log = logging.getLogger(__name__)

FS_HZ = 500.0
DT_S = 1.0 / FS_HZ
SETTLE_S = 0.5  # dataset_b's default: the runs start this long after the damper was at rest
DISPLACEMENT_NOISE_M = 1e-5  # dataset_b's defaults
AMPLITUDES_M = (0.010, 0.015, 0.020)
FREQS_HZ = (2.0, 3.0, 4.0, 5.0, 6.0)
CURRENTS_A = tuple(round(0.2 * k, 1) for k in range(10))
# (amplitude m, frequency Hz, current A) of the closed-loop runs: corners and the middle
CLOSED_LOOP_RUNS = (
    (0.010, 2.0, 0.4),
    (0.015, 4.0, 1.0),
    (0.020, 6.0, 1.8),
    (0.020, 2.0, 0.0),
    (0.010, 6.0, 1.4),
    (0.015, 3.0, 0.8),
)
FEEDBACK_TAU_S = 0.002
PAPER = {"inverse_current_rmse_a": 0.09, "supervised_current_rmse_a": 0.20, "tracking_p95_n": 50.0}


def _conditions() -> np.ndarray:
    return dataset_b_conditions(AMPLITUDES_M, FREQS_HZ, CURRENTS_A)


def make_plant_force(s: Series, params: BoucWenParams, cond: np.ndarray | None = None):
    """plant_force(rows, current_a): the plant's steady-state force at the sample rows of `s`,
    had each run been made at the given constant current (one damper per row, one batch).
    `cond` are the runs' [amplitude_m, freq_hz, current_a] rows (default: the full matrix)."""
    cond = _conditions() if cond is None else cond

    def plant_force(rows: np.ndarray, current_a: np.ndarray) -> np.ndarray:
        amp, freq = cond[s.run_id[rows], 0], cond[s.run_id[rows], 1]
        k = np.round((SETTLE_S + s.t[rows]) / DT_S).astype(int)
        tau = np.arange(int(k.max()) + 1) * DT_S
        x, xd, _ = sine(tau[None, :], amp[:, None], freq[:, None])
        f = simulate(params, tau, x, xd, np.asarray(current_a, dtype=float)[:, None])
        return f[np.arange(rows.size), k]

    return plant_force


def closed_loop_estimated(
    controller: Controller,
    params: BoucWenParams,
    x: np.ndarray,
    xd: np.ndarray,
    est: tuple[np.ndarray, np.ndarray, np.ndarray],
    f_meas_noise: np.ndarray,
    f_des: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """`simulation.closed_loop`, except that the controller sees the estimates `est` (B, n) and
    a noisy load cell while the plant moves along the true (x, xd). Returns (f_act, command)."""
    batch, n = f_des.shape
    plants = [BoucWenDamper(params) for _ in range(batch)]
    xs, xds = x.tolist(), xd.tolist()
    f_a = np.array([p.reset(xs[b][0], xds[b][0], 0.0) for b, p in enumerate(plants)])
    controller.reset(batch)
    f_act, command = np.empty((batch, n)), np.empty((batch, n))
    for k in range(n):
        f_act[:, k] = f_a
        s = ControlInput(
            est[0][:, k], est[1][:, k], est[2][:, k], f_a + f_meas_noise[:, k], f_des[:, k]
        )
        command[:, k] = controller.command(s)
        if k + 1 < n:
            cmd = command[:, k].tolist()
            f_a = np.array(
                [p.step(xs[b][k + 1], xds[b][k + 1], cmd[b], DT_S) for b, p in enumerate(plants)]
            )
    return f_act, command


def closed_loop_check(
    b: Series, controllers: dict[str, Controller], params: BoucWenParams, seed: int
) -> dict:
    """Tracking of the measured force of `CLOSED_LOOP_RUNS` by each controller."""
    cond = _conditions()
    runs = [int(np.flatnonzero(np.all(np.isclose(cond, c), axis=1))[0]) for c in CLOSED_LOOP_RUNS]
    n_run = int(np.sum(b.run_id == 0))
    n_settle = round(SETTLE_S * FS_HZ)
    tau = np.arange(n_settle + n_run) * DT_S
    amp, freq, cur = (cond[runs, j][:, None] for j in range(3))
    x, xd, _ = sine(tau[None, :], amp, freq)
    f_true = simulate(params, tau, x, xd, np.broadcast_to(cur, x.shape))
    f_des = f_true.copy()
    f_des[:, n_settle:] = np.stack([b.force_meas[b.run_id == r] for r in runs])
    rng = np.random.default_rng(seed)
    x_meas = np.round((x + rng.normal(0.0, DISPLACEMENT_NOISE_M, x.shape)) / DISPLACEMENT_LSB_M)
    est = [np.empty_like(x) for _ in range(3)]
    for i in range(len(runs)):
        e = KalmanEstimator(DT_S).estimate(x_meas[i] * DISPLACEMENT_LSB_M)
        for j in range(3):
            est[j][i] = e[j]
    load_cell_noise = f_des[:, :] - f_true  # the measured force's own noise, 0 in the settle part
    score = slice(n_settle, None)
    out: dict = {"runs": [list(c) for c in CLOSED_LOOP_RUNS], "controllers": {}}
    for name, ctrl in controllers.items():
        t0 = time.perf_counter()
        f_act, _ = closed_loop_estimated(ctrl, params, x, xd, tuple(est), load_cell_noise, f_des)
        err = f_act[:, score] - f_des[:, score]
        out["controllers"][name] = {
            "et": [error_norm(f_des[i, score], f_act[i, score]) for i in range(len(runs))],
            "tracking_n": percentiles(np.abs(err), (50.0, 95.0)),
            "seconds": time.perf_counter() - t0,
        }
        log.info("closed loop %s: p95 %.1f N", name, out["controllers"][name]["tracking_n"]["p95"])
    return out


def run(seed: int = 0, epochs: int = 1000, current_input: str = "commanded") -> dict:
    """The whole benchmark; returns every number it prints."""
    params = BoucWenParams.preset("rig-current")
    t0 = time.perf_counter()
    b = dataset_b()
    s = measured_series(b)
    data_s = time.perf_counter() - t0
    log.info(
        "data set B: %d runs, %d samples after the Kalman warm-up (%.1f s)",
        int(np.unique(s.run_id).size),
        len(s),
        data_s,
    )

    def progress(epoch: int, mse: float, val: float | None, mu: float) -> None:
        if epoch % 25 == 0:
            log.info(
                "  epoch %d: train MSE %.4g, val MSE %.4g, mu %.3g",
                epoch,
                mse,
                val if val is not None else float("nan"),
                mu,
            )

    plant_force = make_plant_force(s, params)
    t0 = time.perf_counter()
    fwd, sup, report = train_and_validate(
        s,
        seed=seed,
        progress=progress,
        current_input=current_input,
        max_epochs=epochs,
        plant_force=plant_force,
    )
    total_s = time.perf_counter() - t0
    # the plant's steady-state response at the currents that produced the data must be the
    # data's own noise-free force: a check of plant_force, printed with the rest
    rows = np.arange(0, len(b), 97)
    check = make_plant_force(b, params)(rows, b.current[rows]) - b.force[rows]
    plant_check_n = float(np.max(np.abs(check)))
    assert isinstance(sup, MLP)
    i_max = float(report["i_max_a"])
    mu = float(fwd.meta["online_continuity"])  # the daemon's default for this model
    ctrls: dict[str, Controller] = {
        "network_inversion": NetworkInversion(i_max, fwd, method="exact", dt_s=DT_S, continuity=mu),
        "network_inversion_feedback": NetworkInversion(
            i_max, fwd, method="exact", feedback_tau_s=FEEDBACK_TAU_S, dt_s=DT_S, continuity=mu
        ),
        # the last residual as it is (feedback_tau_s = 0): the network gives only how the
        # force changes with the current and the motion
        "network_inversion_incremental": NetworkInversion(
            i_max, fwd, method="exact", feedback_tau_s=0.0, dt_s=DT_S, continuity=mu
        ),
        "network_inversion_root": NetworkInversion(i_max, fwd, method="exact", dt_s=DT_S),
        "supervised": SupervisedInverse(i_max, sup),
    }
    closed = closed_loop_check(b, ctrls, params, seed)
    closed["continuity"] = mu
    return {
        "seed": seed,
        "epochs_limit": epochs,
        "samples_after_warmup": len(s),
        "data_seconds": data_s,
        "train_and_validate_seconds": total_s,
        "plant_force_check_max_n": plant_check_n,
        "report": report,
        "closed_loop": closed,
        "paper": PAPER,
    }


def _pct(d: dict | None) -> str:
    if d is None:
        return "-"
    return f"p50 {d['p50']:7.1f}  p95 {d['p95']:7.1f}  max {d['max']:7.1f}"


def format_report(r: dict) -> str:
    rep = r["report"]
    ni, sup = rep["network_inversion"], rep["supervised"]
    on = rep["network_inversion_online"]
    tr, st = rep, rep["supervised_training"]
    lines = [
        f"Characterization matrix (150 runs, 0.5 kHz, noisy), current input {rep['current_input']}",
        f"split: {rep['split']['rule']}, seed {rep['split']['seed']}",
        f"forward 4-30-1: {tr['epochs']} epochs ({tr['stop_reason']}), {tr['seconds']:.1f} s;"
        f" supervised: {st['epochs']} epochs ({st['stop_reason']}), {st['seconds']:.1f} s;"
        f" all incl. validation {r['train_and_validate_seconds']:.1f} s",
        f"forward model on the {rep['n_val']} validation samples: Et {rep['forward']['et']:.4f},"
        f" RMSE {rep['forward']['rmse_n']:.1f} N",
        "",
        f"{'':<28}{'NI, per sample':>16}{'NI, on-line':>14}{'supervised MLP':>16}"
        f"{'paper NI / sup.':>18}",
        f"{'inverse-current RMSE (A)':<28}{ni['current_rmse_a']:>16.4f}"
        f"{on['current_rmse_a']:>14.4f}{sup['current_rmse_a']:>16.4f}{'0.09 / 0.20':>18}",
        f"{'at 0 or i_max (fraction)':<28}{ni['at_bound_fraction']:>16.4f}"
        f"{on['at_bound_fraction']:>14.4f}{sup['at_bound_fraction']:>16.4f}",
        "NI per sample: each validation sample inverted alone (previous current 0 A).",
        "NI on-line: every run inverted in time order as the daemon does, each sample from the"
        f" previous inverse current, continuity {on['continuity']:g} chosen on the training rows"
        " (training-row RMSE by continuity: "
        + ", ".join(f"{k}: {v:.4f}" for k, v in on["training_rmse_by_continuity"].items())
        + ")",
        "",
        "tracking error |f - f_des| (N), f_des = the sample's measured force; paper: p95 < 50 N",
        "  plant (steady state at the inverted current):",
        f"    NI, per sample      {_pct(ni['tracking_plant_n'])}",
        f"    NI, on-line         {_pct(on['tracking_plant_n'])}",
        f"    supervised MLP      {_pct(sup['tracking_plant_n'])}",
        "  forward model at the inverted current:",
        f"    NI, per sample      {_pct(ni['tracking_model_n'])}",
        f"    NI, on-line         {_pct(on['tracking_model_n'])}",
        f"    supervised MLP      {_pct(sup['tracking_model_n'])}",
        f"  (check: plant at the data's own currents vs the data's true force, max"
        f" {r['plant_force_check_max_n']:.2e} N)",
        "",
        "closed loop, 0.5 kHz, Kalman estimates, runs (amplitude m, Hz, A): "
        + ", ".join(str(tuple(c)) for c in r["closed_loop"]["runs"]),
        f"  network inversion with the model file's continuity {r['closed_loop']['continuity']:g}"
        " (the daemon's default), and the root:",
    ]
    for name, c in r["closed_loop"]["controllers"].items():
        lines.append(
            f"  {name:<30} {_pct(c['tracking_n'])}   Et " + " ".join(f"{e:.3f}" for e in c["et"])
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter,
        prog="mrrig bench matrix",
        description=__doc__.splitlines()[0],
    )
    ap.add_argument("--json", type=output_file, help="also write the numbers to this JSON file")
    ap.add_argument("--seed", type=SEED, default=0)
    ap.add_argument("--epochs", type=COUNT, default=1000, help="LM epoch limit (default 1000)")
    ap.add_argument("--current-input", choices=("commanded", "lagged"), default="commanded")
    args = ap.parse_args(argv)
    result = run(seed=args.seed, epochs=args.epochs, current_input=args.current_input)
    print(format_report(result))
    if args.json:
        args.json.write_text(json_text.dumps(result, indent=2))
        log.info("wrote %s", args.json)
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    raise SystemExit(main())
