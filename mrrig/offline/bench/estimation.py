"""Benchmark: Kalman filter vs finite differences on noisy data-set-B-like runs.

Every amplitude x frequency of data set B (10/15/20 mm x 2-6 Hz) as a sine sampled at 500 Hz,
with Gaussian displacement noise and 1 um quantisation; true x' and x'' are analytic. The first
0.2 s of each run (filter start-up) are left out of the errors.

    python -m mrrig.offline.bench.estimation [--seed N] [--noise-um 20] [--duration-s 2]
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Sequence

import numpy as np

from mrrig.cli_args import SEED, HelpFormatter, non_negative, positive
from mrrig.loop.estimation import Q_VAR, KalmanEstimator, finite_difference
from mrrig.offline.metrics import percentiles, rmse

log = logging.getLogger(__name__)

DT_S = 0.002
AMPLITUDES_M = (0.010, 0.015, 0.020)
FREQUENCIES_HZ = (2.0, 3.0, 4.0, 5.0, 6.0)
QUANTUM_M = 1e-6
SKIP_S = 0.2
FD_CUTOFFS_HZ = (10.0, 20.0, 30.0, 50.0, 80.0)
Q_SWEEP = (0.1, 0.3, 1.0, 3.0, 10.0)


def noisy_sine_run(
    amplitude_m: float,
    freq_hz: float,
    rng: np.random.Generator,
    duration_s: float = 2.0,
    noise_std_m: float = 20e-6,
    dt_s: float = DT_S,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A sine run with random phase: (measured x, true x', true x''), quantised to 1 um."""
    t = np.arange(round(duration_s / dt_s)) * dt_s
    w = 2.0 * np.pi * freq_hz
    phase = w * t + rng.uniform(0.0, 2.0 * np.pi)
    x = amplitude_m * np.sin(phase) + rng.normal(0.0, noise_std_m, t.size)
    x_meas = np.round(x / QUANTUM_M) * QUANTUM_M
    return x_meas, amplitude_m * w * np.cos(phase), -amplitude_m * w * w * np.sin(phase)


def _kalman_timed(est: KalmanEstimator, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
    """Sample-by-sample `update` as the loop calls it, with the cost of each call in us."""
    xd = np.empty_like(x)
    xdd = np.empty_like(x)
    cost_us = []
    est.reset(float(x[0]))
    for k, value in enumerate(x.tolist()):
        t0 = time.perf_counter_ns()
        _, xd[k], xdd[k] = est.update(value)
        cost_us.append((time.perf_counter_ns() - t0) * 1e-3)
    return xd, xdd, cost_us


def _medians(sweep: dict) -> dict:
    return {k: (float(np.median(v)), float(np.median(a))) for k, (v, a) in sweep.items()}


def run(seed: int = 0, noise_std_m: float = 20e-6, duration_s: float = 2.0) -> dict:
    """Errors of both estimators on all 15 runs, their medians, and sweeps of q and cutoff."""
    rng = np.random.default_rng(seed)
    skip = round(SKIP_S / DT_S)
    est = KalmanEstimator(DT_S)
    rows = []
    cost_us: list[float] = []
    fd_sweep = {fc: ([], []) for fc in FD_CUTOFFS_HZ}
    q_sweep = {q: ([], []) for q in Q_SWEEP}
    for amp in AMPLITUDES_M:
        for freq in FREQUENCIES_HZ:
            log.info("run %.0f mm %.0f Hz", amp * 1e3, freq)
            x, xd_true, xdd_true = noisy_sine_run(amp, freq, rng, duration_s, noise_std_m)
            kf_xd, kf_xdd, costs = _kalman_timed(est, x)
            cost_us.extend(costs)
            fd_xd, fd_xdd = finite_difference(x, DT_S)
            ref_v, ref_a = xd_true[skip:], xdd_true[skip:]
            rows.append(
                {
                    "amplitude_m": amp,
                    "freq_hz": freq,
                    "kf_vel_rmse": rmse(kf_xd[skip:], ref_v),
                    "fd_vel_rmse": rmse(fd_xd[skip:], ref_v),
                    "kf_acc_rmse": rmse(kf_xdd[skip:], ref_a),
                    "fd_acc_rmse": rmse(fd_xdd[skip:], ref_a),
                }
            )
            for fc, (vel, acc) in fd_sweep.items():
                v, a = finite_difference(x, DT_S, cutoff_hz=fc)
                vel.append(rmse(v[skip:], ref_v))
                acc.append(rmse(a[skip:], ref_a))
            for q, (vel, acc) in q_sweep.items():
                _, v, a = KalmanEstimator(DT_S, q=q).estimate(x)
                vel.append(rmse(v[skip:], ref_v))
                acc.append(rmse(a[skip:], ref_a))
    median = {k: float(np.median([r[k] for r in rows])) for k in rows[0] if k.endswith("rmse")}
    return {
        "seed": seed,
        "noise_std_m": noise_std_m,
        "runs": rows,
        "median": median,
        "ratio_vel": median["kf_vel_rmse"] / median["fd_vel_rmse"],
        "ratio_acc": median["kf_acc_rmse"] / median["fd_acc_rmse"],
        "update_cost_us": percentiles(np.array(cost_us), (50, 99)),
        "fd_cutoff_sweep": _medians(fd_sweep),
        "kf_q_sweep": _medians(q_sweep),
    }


def _print_table(res: dict) -> None:
    print(
        f"Velocity / acceleration RMSE, seed {res['seed']}, noise {res['noise_std_m'] * 1e6:g} um,"
        f" first {SKIP_S:g} s skipped"
    )
    head = ("KF m/s", "FD m/s", "KF m/s2", "FD m/s2")
    print(f"{'amp mm':>6} {'f Hz':>4} | {head[0]:>8} {head[1]:>8} | {head[2]:>8} {head[3]:>8}")
    for r in res["runs"]:
        print(
            f"{r['amplitude_m'] * 1e3:6.0f} {r['freq_hz']:4.0f} | {r['kf_vel_rmse']:8.4f} "
            f"{r['fd_vel_rmse']:8.4f} | {r['kf_acc_rmse']:8.3f} {r['fd_acc_rmse']:8.3f}"
        )
    m = res["median"]
    print(
        f"{'median':>11} | {m['kf_vel_rmse']:8.4f} {m['fd_vel_rmse']:8.4f} | "
        f"{m['kf_acc_rmse']:8.3f} {m['fd_acc_rmse']:8.3f}"
    )
    print(f"ratio KF/FD: velocity {res['ratio_vel']:.3f}, acceleration {res['ratio_acc']:.3f}")
    c = res["update_cost_us"]
    print(f"Kalman update cost: median {c['p50']:.1f} us, p99 {c['p99']:.1f} us")
    print("FD cutoff sweep (2nd-order Butterworth), median RMSE vel m/s / acc m/s2:")
    for fc, (v, a) in res["fd_cutoff_sweep"].items():
        print(f"  {fc:5.0f} Hz: {v:.4f} / {a:.3f}")
    print(f"Kalman q sweep (default {Q_VAR:g}), median RMSE vel m/s / acc m/s2:")
    for q, (v, a) in res["kf_q_sweep"].items():
        print(f"  q {q:5g}: {v:.4f} / {a:.3f}")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        formatter_class=HelpFormatter,
        prog="mrrig bench estimation",
        description=__doc__.splitlines()[0],
    )
    parser.add_argument("--seed", type=SEED, default=0)
    parser.add_argument(
        "--noise-um", type=non_negative, default=20.0, help="displacement noise std"
    )
    parser.add_argument("--duration-s", type=positive, default=2.0, help="length of each run")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING)
    res = run(seed=args.seed, noise_std_m=args.noise_um * 1e-6, duration_s=args.duration_s)
    _print_table(res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
