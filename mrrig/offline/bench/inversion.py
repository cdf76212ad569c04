"""Benchmark: LM training time, and the paper's gradient inversion vs the exact solve.

Trains the 4-30-1 forward network on 12771 samples (the paper's split size; 1419 more for
validation) of data set A (volts), B (amperes) or a synthetic smooth force, or takes a saved
model, then inverts it on the validation samples (desired force = the plant's force) and
prints the per-sample cost (median, p99) of each method on the batch and the scalar path
(the exact solve also with a continuity weight, as the daemon solves with a model's own),
their speed ratio, and each method's force and current errors. With `--gru PATH` (a GRU
forward model, `mrrig train --features gru`), also its per-frame solve (mrrig/loop/gru.py) run
frame by frame over runs of data set B, each frame's target the model's own force for the
command held (reachable): us per solve and the command's error.

    python -m mrrig.offline.bench.inversion [--data a|b|synthetic] [--model PATH] [--epochs 1000]
        [--gru PATH]
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import time
from collections.abc import Callable, Sequence

import numpy as np

from mrrig.cli_args import COUNT, SEED, HelpFormatter, non_negative, output_file
from mrrig.loop.inversion import ScalarInverter, exact_inversion, gradient_inversion
from mrrig.loop.mlp import MLP
from mrrig.offline.metrics import error_norm, percentiles, rmse

log = logging.getLogger(__name__)

DEMO_CONTINUITY = 0.03  # the demo model's own (mrrig train's choice on data set B)
N_TRAIN = 12771
N_VAL = 1419
NAMES = ["x", "xd", "xdd", "current"]
CHUNK = 64  # samples per timed batch call
GRU_RUNS = 20  # runs of data set B (450 frames each) the GRU's solve is timed over


def synthetic(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """A smooth force, monotone in current: (300 + 900 i) tanh(xd / 0.05) + viscous + spring."""
    X = np.column_stack(
        [
            rng.uniform(-0.02, 0.02, n),
            rng.uniform(-0.4, 0.4, n),
            rng.uniform(-20.0, 20.0, n),
            rng.uniform(0.0, 1.8, n),
        ]
    )
    y = (
        (300.0 + 900.0 * X[:, 3]) * np.tanh(X[:, 1] / 0.05)
        + (700.0 + 500.0 * X[:, 3]) * X[:, 1]
        + 2000.0 * X[:, 0]
        + 4.0 * X[:, 2]
    )
    return X, y, 1.8


def load_data(name: str, seed: int) -> tuple[np.ndarray, np.ndarray, float, str, str]:
    """(X, y, i_max, unit of the current input, description)."""
    rng = np.random.default_rng(seed)
    if name == "synthetic":
        X, y, i_max = synthetic(N_TRAIN + N_VAL, rng)
        return X, y, i_max, "A", "synthetic smooth force"
    from mrrig.offline import datasets

    if name == "a":
        s = datasets.dataset_a_training()
        unit, i_max = "V", 12.0
    else:
        s = datasets.dataset_b()
        unit, i_max = "A", float(np.max(s.current))
    pick = rng.choice(len(s), size=N_TRAIN + N_VAL, replace=False)
    X = np.column_stack([s.x, s.xd, s.xdd, s.current])[pick]
    return X, s.force[pick], i_max, unit, f"data set {name.upper()} ({s.name})"


def _per_sample_batch_us(
    fn: Callable[[slice], np.ndarray], n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Run fn over chunks of CHUNK samples; (results, per-sample cost of each chunk in us)."""
    out, cost = [], []
    for start in range(0, n, CHUNK):
        sl = slice(start, min(start + CHUNK, n))
        t0 = time.perf_counter_ns()
        out.append(fn(sl))
        cost.append((time.perf_counter_ns() - t0) * 1e-3 / (sl.stop - sl.start))
    return np.concatenate(out), np.array(cost)


def _scalar_us(
    inv: ScalarInverter, F: np.ndarray, f_des: np.ndarray, i_prev: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    rows = [np.ascontiguousarray(r) for r in F[:n]]
    fd, ip = f_des[:n].tolist(), i_prev[:n].tolist()
    out, cost = np.empty(n), np.empty(n)
    for k in range(n):
        t0 = time.perf_counter_ns()
        out[k] = inv.solve(rows[k], fd[k], ip[k])
        cost[k] = (time.perf_counter_ns() - t0) * 1e-3
    return out, cost


def gru_solves(path: str, runs: int = GRU_RUNS) -> tuple[np.ndarray, np.ndarray, int]:
    """(us per solve, |command - the command held|, hidden units) of the GRU's per-frame
    solve over the first `runs` runs of data set B, frame by frame as the daemon solves."""
    from mrrig.loop.gru import GRUModel, GruTracker
    from mrrig.loop.twin_model import load_forward_model
    from mrrig.offline import datasets

    model = load_forward_model(path)
    if not isinstance(model, GRUModel):
        raise SystemExit(f"error: {path}: not a GRU forward model (mrrig-gru/1)")
    s = datasets.dataset_b()
    i_max = float(np.max(s.current))
    g = GruTracker(model, float(np.median(np.diff(s.t[:10]))), i_max)
    cost, err = [], []
    per_run = len(s) // int(np.max(s.run_id) + 1)
    for r in range(runs):
        sl = slice(r * per_run, (r + 1) * per_run)
        x, xd, xdd, cur = (a[sl] for a in (s.x, s.xd, s.xdd, s.current))
        g.reset()
        for k in range(per_run - 1):
            g.advance(float(x[k]), float(xd[k]), float(xdd[k]))
            nxt, held = (float(x[k + 1]), float(xd[k + 1]), float(xdd[k + 1])), float(cur[k])
            target = g.force_next(*nxt, held)
            t0 = time.perf_counter_ns()
            i = g.solve(target, *nxt)
            cost.append((time.perf_counter_ns() - t0) * 1e-3)
            err.append(abs(i - held))
            g.command = held
    return np.array(cost), np.array(err), model.hidden


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter,
        prog="mrrig bench inversion",
        description=__doc__.split("\n")[0],
    )
    ap.add_argument("--data", choices=("a", "b", "synthetic"), default="a")
    ap.add_argument("--model", help="a saved forward model (skips training)")
    ap.add_argument("--epochs", type=COUNT, default=1000, help="LM max epochs (default 1000)")
    ap.add_argument("--seed", type=SEED, default=0)
    ap.add_argument(
        "--gradient-scalar-samples",
        type=COUNT,
        default=50,
        help="samples for the slow scalar gradient path (default 50)",
    )
    ap.add_argument(
        "--continuity",
        type=non_negative,
        help="the regularised solve's weight to time as well (default: the model's own"
        f" online_continuity, as the daemon solves; {DEMO_CONTINUITY:g} for a model without one)",
    )
    ap.add_argument("--save", type=output_file, help="write the trained model here")
    ap.add_argument("--gru", help="a GRU forward model: its per-frame solve too")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)

    X, y, i_max, unit, description = load_data(args.data, args.seed)
    Xt, yt, Xv, yv = X[:N_TRAIN], y[:N_TRAIN], X[N_TRAIN:], y[N_TRAIN:]
    print(
        f"data: {description}; {len(yt)} training + {len(yv)} validation samples; "
        f"current bound {i_max:g} {unit}; OPENBLAS_NUM_THREADS="
        f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}, {os.cpu_count()} CPUs"
    )
    if args.model:
        model = MLP.load(args.model)
        print(f"model: {args.model}")
    else:
        from mrrig.offline.training.lm import train_lm

        model, rep = train_lm(
            Xt,
            yt,
            NAMES,
            ["m", "m/s", "m/s^2", unit],
            "force",
            "N",
            max_epochs=args.epochs,
            validation=(Xv, yv),
            seed=args.seed,
            description=description,
        )
        print(
            f"LM training 4-30-1 on {rep.n_train} samples: {rep.seconds:.2f} s, "
            f"{rep.epochs} epochs ({rep.seconds / max(rep.epochs, 1) * 1e3:.1f} ms/epoch), "
            f"stop: {rep.stop_reason}, best epoch {rep.best_epoch}  [target <= 10 s]"
        )
        if args.save:
            model.save(args.save)
    print(f"forward model held-out Et {error_norm(yv, model.predict(Xv)):.4f}")

    F, i_true = Xv[:, :3], Xv[:, 3]
    n = len(yv)
    mu = args.continuity
    if mu is None:
        mu = float(model.meta.get("online_continuity", DEMO_CONTINUITY))
    i_prev = np.zeros(n)
    gc.collect()
    gc.disable()
    try:
        rng = np.random.default_rng(args.seed)
        i_grad, grad_batch = _per_sample_batch_us(
            lambda sl: gradient_inversion(model, F[sl], yv[sl], i_max=i_max, rng=rng), n
        )
        i_exact, exact_batch = _per_sample_batch_us(
            lambda sl: exact_inversion(model, F[sl], yv[sl], i_prev[sl], i_max=i_max), n
        )
        ng = min(args.gradient_scalar_samples, n)
        _, grad_scalar = _scalar_us(
            ScalarInverter(model, i_max, "gradient", seed=args.seed), F, yv, i_prev, ng
        )
        inv = ScalarInverter(model, i_max)
        scalar_runs = [_scalar_us(inv, F, yv, i_prev, n) for _ in range(3)]
        inv_mu = ScalarInverter(model, i_max, continuity=mu)
        mu_runs = [_scalar_us(inv_mu, F, yv, i_prev, n) for _ in range(3)]
    finally:
        gc.enable()
    i_scalar = scalar_runs[0][0]
    exact_scalar = np.concatenate([r[1] for r in scalar_runs])

    def row(name: str, cost: np.ndarray) -> str:
        p = percentiles(cost, (50, 99))
        return f"  {name:34s} median {p['p50']:10.1f} us   p99 {p['p99']:10.1f} us"

    print(
        f"per-sample inversion cost ({n} validation samples; batch timed in chunks of "
        f"{CHUNK}; scalar gradient on {ng} samples):"
    )
    print(row("gradient (paper), batch", grad_batch))
    print(row("gradient (paper), scalar", grad_scalar))
    print(row("exact, batch", exact_batch))
    print(row("exact, scalar (real-time path)", exact_scalar) + "   [target <= 20 us]")
    mu_scalar = np.concatenate([r[1] for r in mu_runs])
    print(row(f"exact, continuity {mu:g}, scalar", mu_scalar) + "   [target <= 20 us]")
    ratio_batch = np.median(grad_batch) / np.median(exact_batch)
    ratio_scalar = np.median(grad_scalar) / np.median(exact_scalar)
    print(f"  speed ratio gradient/exact: batch {ratio_batch:.0f}x, scalar {ratio_scalar:.0f}x")
    print(f"  scalar == batch (exact): max |difference| {np.max(np.abs(i_scalar - i_exact)):.2e}")
    if args.gru:
        gc.disable()
        try:
            cost, err, hidden = gru_solves(args.gru)
        finally:
            gc.enable()
        print(
            row(f"GRU ({hidden} units), per frame", cost)
            + f"   [{cost.size} frames of data set B; command error max {err.max():.2e} A]"
        )

    for name, i in (("gradient (paper)", i_grad), ("exact", i_exact)):
        Xi = np.column_stack([F, i])
        err = np.abs(model.predict(Xi) - yv)
        print(
            f"  {name:17s} force error vs desired: RMS {rmse(model.predict(Xi), yv):9.3g} N, "
            f"p95 {np.percentile(err, 95):9.3g} N, max {err.max():9.3g} N; "
            f"current RMSE vs the true command {rmse(i, i_true):.4f} {unit}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
