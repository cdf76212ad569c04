"""`mrrig evaluate MODEL DATA...`: a forward model's numbers on any data (CSV or recording).

Forward Et and RMSE, and network inversion's inverse-current RMSE, each sample alone and
on-line (in time order, as the daemon inverts, with the model's continuity), on all rows
or on the model's own hold-out (`--rows holdout`: the last fraction of each run that its
`mrrig train` held out, the same rows and the same numbers as the training report). The data
are read and cleaned as `mrrig train` does (bad stretches excluded unless the model was
trained with --keep-all or --keep-all is given). `--plot FILE.png`: measured and model force
over a window, the error histogram, force-velocity loops; `--json FILE`: the numbers.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

import numpy as np

from mrrig import json_text
from mrrig.cli_args import output_file
from mrrig.loop.mlp import MLP, ModelError
from mrrig.offline.datasets import DataError
from mrrig.offline.training.data import (
    exclude_bad_stretches,
    load_training_data,
    run_ids,
    stretches,
)
from mrrig.offline.training.features import feature_names, feature_rows, features
from mrrig.offline.training.fit import HOLDOUT_FRACTION, block_split
from mrrig.offline.training.report import evaluate_rows, predict

log = logging.getLogger(__name__)

PLOT_WINDOW_S = 2.0


def _options(model: MLP, path: Path) -> dict[str, Any]:
    """The model's feature options from its meta (`mrrig train` writes them), checked against
    its input names; a one-line ModelError if they do not give its inputs."""
    m = model.meta
    opts = {
        "current_input": m.get("current_input") or "commanded",
        "lag_tau_s": m.get("lag_tau_s") or 1.0,
        "history_samples": int(m.get("history_samples") or 0),
        "history_signals": tuple(m.get("history_signals") or ("x", "xd")),
        "history_stride": int(m.get("history_stride") or 1),
    }
    names, _ = feature_names(
        opts["history_samples"], opts["history_signals"], opts["history_stride"]
    )
    if list(names) != list(model.input_names):
        raise ModelError(
            f"{path}: inputs {', '.join(model.input_names)} are not what its meta's feature "
            f"options give ({', '.join(names)}): not a model of `mrrig train`"
        )
    return opts


def evaluate(
    model: MLP,
    model_path: Path,
    data: list[Path],
    columns: dict[str, str] | None = None,
    units: dict[str, str] | None = None,
    keep_all: bool | None = None,
    rows: str = "all",
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The numbers (`training.report.evaluate_rows`) and the arrays a plot needs."""
    opts = _options(model, model_path)
    series = load_training_data(data, columns, units)
    unit = model.meta.get("command_unit", "A")
    if series.current_unit != unit:
        raise DataError(
            f"{'+'.join(map(str, data))}: command in {series.current_unit}, but the model's "
            f"command input is in {unit}"
        )
    if keep_all is None:
        keep_all = bool((model.meta.get("excluded") or {}).get("keep_all", False))
    series, excluded = exclude_bad_stretches(series, keep_all)
    X, y = features(series, **opts)
    frows = feature_rows(series, opts["history_samples"], opts["history_stride"])
    stretch = stretches(run_ids(series))[frows]
    if rows == "holdout":
        fraction = model.meta.get("holdout_fraction") or HOLDOUT_FRACTION
        pick = block_split(stretch, float(fraction)).val
    else:
        pick = np.arange(y.size)
    i_max = float(model.meta.get("i_max_a") or X[:, model.current_index].max())
    mu = float(model.meta.get("online_continuity") or 0.0)
    numbers = evaluate_rows(model, X, y, stretch, pick, i_max, mu)
    numbers.update(
        rows=rows,
        data=[str(p) for p in data],
        model=str(model_path),
        command_unit=unit,
        excluded=excluded,
    )
    arrays = {
        "t": series.t[frows][pick],
        "xd": X[pick, 1],
        "f_meas": y[pick],
        "f_model": predict(model, X[pick]),
        "stretch": stretch[pick],
    }
    return numbers, arrays


def format_numbers(r: dict[str, Any]) -> str:
    unit = r["command_unit"]
    ex = r["excluded"]
    excl = (
        "nothing excluded (--keep-all)"
        if ex["keep_all"]
        else f"{ex['excluded_samples']} samples excluded as bad stretches"
    )
    return "\n".join(
        [
            f"{r['model']} on {', '.join(r['data'])}: {r['n']} rows ({r['rows']}; {excl})",
            f"forward Et {r['forward']['et']:.4f}, RMSE {r['forward']['rmse_n']:.2f} N",
            f"inverse command RMSE ({unit}): each sample alone {r['inverse_current_rmse']:.4f},"
            f" on-line {r['inverse_current_rmse_online']:.4f}"
            f" (continuity {r['continuity']:g}, bound {r['i_max']:g} {unit})",
        ]
    )


def plot(arrays: dict[str, np.ndarray], path: Path, window: tuple[float, float] | None) -> None:
    """Measured and model force over the window (default: the first `PLOT_WINDOW_S` of the
    first run evaluated), the error histogram, force-velocity loops measured and model."""
    import matplotlib  # noqa: PLC0415 - only --plot pays for matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    t, fm, fp, xd = arrays["t"], arrays["f_meas"], arrays["f_model"], arrays["xd"]
    if window is None:
        first = arrays["stretch"] == arrays["stretch"][0]
        w = first & (t <= t[first][0] + PLOT_WINDOW_S)
    else:
        w = (t >= window[0]) & (t <= window[1])
    if not w.any():
        raise DataError(f"--window {window}: no evaluated row in it")
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.5))
    ax[0].plot(t[w], fm[w], label="measured", lw=1.0)
    ax[0].plot(t[w], fp[w], label="model", lw=1.0)
    ax[0].set(xlabel="t (s)", ylabel="force (N)", title="force")
    ax[0].legend()
    ax[1].hist(fp - fm, bins=80)
    ax[1].set(xlabel="model - measured (N)", ylabel="rows", title="error (all rows)")
    ax[2].plot(xd[w], fm[w], label="measured", lw=0.8)
    ax[2].plot(xd[w], fp[w], label="model", lw=0.8)
    ax[2].set(xlabel="velocity (m/s)", ylabel="force (N)", title="force-velocity (window)")
    ax[2].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _window(text: str) -> tuple[float, float]:
    a, sep, b = text.partition(",")
    try:
        lo, hi = float(a), float(b)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START,END in s, got {text!r}") from None
    if not sep or not hi > lo:
        raise argparse.ArgumentTypeError(f"expected START,END in s with END > START, got {text!r}")
    return lo, hi


def main(argv: list[str] | None = None) -> int:
    from mrrig.cli.train import _mapping  # noqa: PLC0415 - the same column-map syntax

    ap = argparse.ArgumentParser(prog="mrrig evaluate", description=__doc__.splitlines()[0])
    ap.add_argument("model", type=Path, help="forward model file (mrrig train --out)")
    ap.add_argument("data", nargs="+", type=Path, help="tidy CSV, .rrd recording or CSV")
    ap.add_argument("--columns", help="CSV column map, as for mrrig train")
    ap.add_argument("--units", help="CSV units, as for mrrig train")
    ap.add_argument(
        "--rows",
        choices=("all", "holdout"),
        default="all",
        help="all rows, or the model's own time-block hold-out (default %(default)s)",
    )
    ap.add_argument(
        "--keep-all",
        action="store_true",
        default=None,
        help="keep the bad stretches (default: as the model was trained)",
    )
    ap.add_argument("--plot", type=output_file, help="write a figure (PNG)")
    ap.add_argument("--window", type=_window, help="the plot's time window START,END (s)")
    ap.add_argument("--json", type=output_file, help="write the numbers as JSON")
    args = ap.parse_args(argv)
    model = MLP.load(args.model)
    if model.current_index is None:
        raise ModelError(f"{args.model}: no input named 'current': not a forward model")
    columns = _mapping(args.columns, "--columns")
    units = _mapping(args.units, "--units")
    numbers, arrays = evaluate(
        model, args.model, args.data, columns, units, args.keep_all, args.rows
    )
    print(format_numbers(numbers))
    if args.plot:
        plot(arrays, args.plot, args.window)
        print(f"figure: {args.plot}")
    if args.json:
        args.json.write_text(json_text.dumps(numbers, indent=2), encoding="utf-8")
    return 0
