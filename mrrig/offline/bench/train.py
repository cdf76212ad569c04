"""`mrrig bench train`: `mrrig train`'s cost against the data's size (10k to 10M samples).

The data are the simulator's (preset rig-current, 0.5 kHz): runs of band-limited random
displacement (0-5 Hz, peak 20 mm) and random coil current (0-3 Hz, 0-2 A), the rig's sensor
noise and quantisation on displacement and force. A pool of `POOL_RUNS` distinct runs
(1M samples) is simulated once (cached in the temporary folder); larger sizes repeat the
pool's runs with fresh sensor noise. Each size is trained in its own process, so that its
peak memory (the process's maximum resident set) is its own: the pipeline of `mrrig train`
on a fixed structure (lagged current, no history, one start, no supervised inverse):
Kalman estimates, bad-stretch exclusion, features, the time-block split, LM on the coverage
subsample, the on-line continuity choice and the hold-out report. Printed per size: wall
time, the LM's part, peak memory, the cost per sample (all, and without LM) and its ratio to
the previous size's and to 100k's, and the marginal cost per added sample. Then the scaling
(`scaling`): from 100k (or the smallest size) to the largest, the ratio of the cost per sample
and the spread of the marginal cost between the steps, each against a factor of 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from damper.plant import BoucWenParams, simulate
from damper.signals import bandlimited_noise
from mrrig import json_text
from mrrig.cli_args import COUNT, output_file
from mrrig.offline.datasets import DISPLACEMENT_LSB_M, FORCE_LSB_N, Series

log = logging.getLogger(__name__)

FS_HZ = 500.0
RUN_S = 4.0
POOL_RUNS = 500  # x 2000 samples: 1M
SCALING_BASE = 100_000  # the scaling is judged from this size (or the smallest) upwards
SCALING_FACTOR = 2.0
SUBSTEP_S = 2e-4
SIZES = (10_000, 100_000, 1_000_000, 10_000_000)
DISPLACEMENT_NOISE_M = 1e-5
FORCE_NOISE_N = 2.0
SEED = 4404


def _pool_path(runs: int) -> Path:
    return Path(tempfile.gettempdir()) / f"mrrig-bench-train-pool-{SEED}-{runs}.npz"


def make_pool(runs: int = POOL_RUNS) -> Path:
    """Simulate (or reuse) the pool of runs: x, current, force, each (runs, T)."""
    path = _pool_path(runs)
    if path.is_file():
        return path
    rng = np.random.default_rng(SEED)
    n = round(RUN_S * FS_HZ)
    dt = 1.0 / FS_HZ
    x, xd, cur = (np.empty((runs, n)) for _ in range(3))
    for j in range(runs):
        x[j], xd[j], _ = bandlimited_noise(n, dt, 5.0, 0.02, rng)
        cur[j] = np.clip(bandlimited_noise(n, dt, 3.0, 1.2, rng)[0] + 1.0, 0.0, 2.0)
    t0 = time.perf_counter()
    log.info("simulating the pool: %d runs x %d samples (once; cached at %s)", runs, n, path)
    f = simulate(BoucWenParams.preset("rig-current"), np.arange(n) * dt, x, xd, cur, SUBSTEP_S)
    log.info("pool simulated in %.0f s", time.perf_counter() - t0)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, x=x, current=cur, force=f)
    os.replace(tmp, path)
    return path


def series_of_size(pool: Path, n: int, seed: int = 0) -> Series:
    """n samples: whole runs of the pool (the last one cut), repeated with fresh noise."""
    p = np.load(pool)
    runs, length = p["x"].shape
    k = -(-n // length)  # runs needed
    pick = np.arange(k) % runs
    rng = np.random.default_rng(seed)
    x = p["x"][pick].ravel()[:n]
    f = p["force"][pick].ravel()[:n]
    x_meas = np.round((x + rng.normal(0.0, DISPLACEMENT_NOISE_M, n)) / DISPLACEMENT_LSB_M)
    f_meas = np.round((f + rng.normal(0.0, FORCE_NOISE_N, n)) / FORCE_LSB_N)
    run_id = np.repeat(np.arange(k), length)[:n]
    return Series(
        t=np.tile(np.arange(length) / FS_HZ, k)[:n],
        x=x_meas * DISPLACEMENT_LSB_M,
        xd=None,
        xdd=None,
        current=p["current"][pick].ravel()[:n],
        force=f_meas * FORCE_LSB_N,
        name=f"bench-{n}",
        run_id=run_id,
    )


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def child(n: int, epochs: int, pool_runs: int = POOL_RUNS) -> dict:
    """One size, in this process: the numbers of `run`'s table."""
    import torch

    from mrrig.offline.training import (
        estimate_derivatives,
        exclude_bad_stretches,
        train_and_validate,
    )

    torch.set_num_threads(1)
    s = series_of_size(make_pool(pool_runs), n)
    data_mb = _rss_mb()
    t0 = time.perf_counter()
    s = estimate_derivatives(s)
    t_kalman = time.perf_counter() - t0
    s, excluded = exclude_bad_stretches(s)
    t1 = time.perf_counter()
    _, _, report = train_and_validate(
        s, current_input="lagged", max_epochs=epochs, supervised=False, restarts=1
    )
    wall = time.perf_counter() - t0
    return {
        "samples": n,
        "wall_s": wall,
        "kalman_s": t_kalman,
        "exclusion_s": t1 - t0 - t_kalman,
        "lm_s": report["seconds"],
        "epochs": report["epochs"],
        "rest_s": wall - (t1 - t0) - report["seconds"],
        "peak_rss_mb": _rss_mb(),
        "data_rss_mb": data_mb,
        "excluded_samples": excluded["excluded_samples"],
        "holdout_et": report["forward"]["et"],
        "lm_rows": report["split"]["n_fit"],
    }


def format_table(rows: list[dict]) -> str:
    """The table: per size its wall time and parts, peak memory, the cost per sample (all,
    and without LM's constant part) and their ratios to the previous size's and to 100k's."""
    lines = [
        f"{'samples':>10} {'wall s':>8} {'Kalman s':>9} {'LM s':>7} {'epochs':>6} {'other s':>8}"
        f" {'peak MB':>8} {'us/sample':>10} {'x prev':>7} {'x 100k':>7}"
        f" {'no-LM us/s':>10} {'x prev':>7} {'x 100k':>7} {'marginal us/s':>13}"
        f" {'hold-out Et':>11}"
    ]

    def per(r: dict, lm: bool) -> float:
        return (r["wall_s"] - (0.0 if lm else r["lm_s"])) / r["samples"] * 1e6

    def ratio(a: dict, b: dict | None, lm: bool) -> str:
        return f"{per(a, lm) / per(b, lm):7.2f}" if b else " " * 7

    def marginal(a: dict, b: dict | None) -> str:
        if b is None or a["samples"] == b["samples"]:
            return " " * 13
        return f"{(a['wall_s'] - b['wall_s']) / (a['samples'] - b['samples']) * 1e6:13.2f}"

    base = next((r for r in rows if r["samples"] == 100_000), None)
    prev = None
    for r in rows:
        lines.append(
            f"{r['samples']:>10} {r['wall_s']:8.1f} {r['kalman_s']:9.1f} {r['lm_s']:7.1f}"
            f" {r['epochs']:>6} {r['rest_s']:8.1f} {r['peak_rss_mb']:8.0f} {per(r, True):10.2f}"
            f" {ratio(r, prev, True)} {ratio(r, base, True)} {per(r, False):10.2f}"
            f" {ratio(r, prev, False)} {ratio(r, base, False)} {marginal(r, prev)}"
            f" {r['holdout_et']:11.4f}"
        )
        prev = r
    lines.append(
        "us/sample: wall time over samples; no-LM: without the LM fit, whose cost is constant"
        " (at most its coverage subsample of rows); x prev, x 100k: over the previous size's and"
        " over 100k's (1 = linear; under 1: cheaper per sample); marginal: the added wall time per"
        " added sample from the previous size (the linear part's cost). Peak: the process's maximum"
        " resident memory, data included."
    )
    return "\n".join(lines)


def scaling(rows: list[dict]) -> dict | None:
    """How the cost grows with the data, from `SCALING_BASE` samples (or the smallest size)
    to the largest; None with one size. `per_sample_ratio`: the wall time per sample at the
    largest size over the base's (1: linear; under 1: cheaper per sample, the fixed part
    spread over more samples). `marginal_steps`: the added wall time per added sample of
    each step above the base; `marginal_spread`: their largest over their smallest (the part
    of the cost that grows with the data: linear where it stays within `SCALING_FACTOR`)."""
    ordered = sorted(rows, key=lambda r: r["samples"])
    base = next((r for r in ordered if r["samples"] == SCALING_BASE), ordered[0])
    above = [r for r in ordered if r["samples"] > base["samples"]]
    if not above:
        return None

    def per(r: dict) -> float:
        return r["wall_s"] / r["samples"] * 1e6

    steps, prev = [], base
    for r in above:
        added = (r["wall_s"] - prev["wall_s"]) / (r["samples"] - prev["samples"]) * 1e6
        steps.append({"from": prev["samples"], "to": r["samples"], "marginal_us": added})
        prev = r
    marginal = [st["marginal_us"] for st in steps]
    spread = max(marginal) / min(marginal) if len(steps) > 1 and min(marginal) > 0.0 else None
    ratio = per(above[-1]) / per(base)
    return {
        "from": base["samples"],
        "to": above[-1]["samples"],
        "per_sample_us": [per(base), per(above[-1])],
        "per_sample_ratio": ratio,
        "per_sample_within_factor": 1.0 / SCALING_FACTOR <= ratio <= SCALING_FACTOR,
        "marginal_steps": steps,
        "marginal_spread": spread,
        "marginal_within_factor": spread is not None and spread <= SCALING_FACTOR,
        "factor": SCALING_FACTOR,
    }


def scaling_lines(sc: dict | None) -> list[str]:
    """`scaling` in words: the raw per-sample ratio and the marginal costs' spread."""
    if sc is None:
        return ["scaling: one size only"]
    f = sc["factor"]
    a, b = sc["per_sample_us"]
    steps = ", ".join(
        f"{st['from']}->{st['to']} {st['marginal_us']:.2f} us" for st in sc["marginal_steps"]
    )
    spread = sc["marginal_spread"]
    return [
        f"scaling {sc['from']} -> {sc['to']} samples, against a factor of {f:g}:",
        f"  cost per sample {a:.2f} -> {b:.2f} us: x {sc['per_sample_ratio']:.3f}"
        f" (within a factor of {f:g}: {'yes' if sc['per_sample_within_factor'] else 'no'})",
        f"  marginal cost per added sample: {steps};"
        + (
            f" largest / smallest {spread:.2f}"
            f" (within a factor of {f:g}: {'yes' if sc['marginal_within_factor'] else 'no'})"
            if spread is not None
            else " (a spread needs two steps with a positive cost)"
        ),
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="mrrig bench train", description=__doc__.splitlines()[0])
    ap.add_argument(
        "--sizes",
        default=",".join(map(str, SIZES)),
        help="sample counts, comma-separated (default %(default)s)",
    )
    ap.add_argument("--epochs", type=COUNT, default=1000, help="LM epoch limit (default 1000)")
    ap.add_argument(
        "--pool-runs",
        type=COUNT,
        default=POOL_RUNS,
        help="distinct simulated runs of 2000 samples, repeated with fresh noise for larger"
        " sizes (default %(default)s)",
    )
    ap.add_argument("--json", type=output_file, help="also write the numbers to this JSON file")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--table", type=Path, help=argparse.SUPPRESS)  # reprint a --json file
    args = ap.parse_args(argv)
    if args.table is not None:
        rows = json.loads(args.table.read_text())["sizes"]
        print("\n".join([format_table(rows), *scaling_lines(scaling(rows))]))
        return 0
    if args.child is not None:
        print(json.dumps(child(args.child, args.epochs, args.pool_runs)))
        return 0
    try:
        sizes = [int(v) for v in args.sizes.split(",")]
    except ValueError:
        ap.error(f"argument --sizes: expected integers, got {args.sizes!r}")
    if any(n < 5_000 for n in sizes):
        ap.error("argument --sizes: each must be >= 5000")
    make_pool(args.pool_runs)
    rows = []
    for n in sizes:
        log.info("training on %d samples (own process)", n)
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "mrrig.offline.bench.train",
                "--child",
                str(n),
                "--epochs",
                str(args.epochs),
                "--pool-runs",
                str(args.pool_runs),
            ],
            check=True,
            stdout=subprocess.PIPE,
            text=True,
        )
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        log.info(
            "%d samples: %.1f s wall, peak %.0f MB", n, rows[-1]["wall_s"], rows[-1]["peak_rss_mb"]
        )
    sc = scaling(rows)
    print("\n".join([format_table(rows), *scaling_lines(sc)]))
    if args.json:
        args.json.write_text(
            json_text.dumps({"sizes": rows, "scaling": sc}, indent=2), encoding="utf-8"
        )
    return 0


if __name__ == "__main__":
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    raise SystemExit(main())
