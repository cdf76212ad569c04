"""`mrrig evaluate MODEL DATA...`: a forward model's numbers on any data (CSV or recording).

Forward Et and RMSE, and network inversion's inverse-current RMSE, each sample alone and
on-line (in time order, as the daemon inverts, with the model's continuity), on all rows
or on the model's own hold-out (`--rows holdout`: the last fraction of each run that its
`mrrig train` held out, the same rows and the same numbers as the training report). The data
are read and cleaned as `mrrig train` does (bad stretches excluded unless the model was
trained with --keep-all or --keep-all is given). Et is printed per test (file) and overall;
the coverage lines say which share of the rows lies outside the model's training envelope
(`loop.coverage`), the Et inside and outside it, and the band shares of force and velocity
beside the model's. `--plot FILE.png`: measured and model force
over a window, the error histogram, force-velocity loops; `--json FILE`: the numbers.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from mrrig import json_text
from mrrig.cli_args import output_file
from mrrig.loop.coverage import (
    BAND_EDGES_HZ,
    BAND_SIGNALS,
    ENVELOPE_INPUTS,
    OUTSIDE_BITS,
    Envelope,
    band_labels,
    band_power,
    contiguous_pieces,
    model_envelope,
    shares,
)
from mrrig.loop.greybox import GreyBoxModel
from mrrig.loop.gru import GRUModel
from mrrig.loop.mlp import MLP, ModelError
from mrrig.loop.twin_model import TwinModel, load_forward_model
from mrrig.offline.datasets import DataError
from mrrig.offline.training.data import run_ids, stretches
from mrrig.offline.training.features import (
    CURRENT_INPUTS,
    feature_names,
    feature_rows,
    features,
)
from mrrig.offline.training.fit import HOLDOUT_FRACTION, block_split
from mrrig.offline.training.gru import gru_forces
from mrrig.offline.training.kinds import greybox_kind, twin_kind
from mrrig.offline.training.report import EtSum, MetricError, Scores
from mrrig.offline.training.stream import SEGMENT_ROWS, merge_reports, prepare, segments

log = logging.getLogger(__name__)

PLOT_WINDOW_S = 2.0
PLOT_MAX_ROWS = 1_000_000  # rows a plot keeps, at most, of the window and of the errors


# meta field -> (what it must be, the check): the fields of `mrrig train`'s meta read here
_META = {
    "current_input": ("one of " + ", ".join(CURRENT_INPUTS), lambda v: v in CURRENT_INPUTS),
    "lag_tau_s": ("a number > 0", lambda v: _number(v) and 0.0 < v < math.inf),
    "history_samples": ("an integer >= 0", lambda v: _integer(v) and v >= 0),
    "history_signals": ("a list of names", lambda v: isinstance(v, list)),
    "history_stride": ("an integer >= 1", lambda v: _integer(v) and v >= 1),
    "command_unit": ("A or V", lambda v: v in ("A", "V")),
    "holdout_fraction": ("a number in (0, 0.5)", lambda v: _number(v) and 0.0 < v < 0.5),
    "i_max_a": ("a number > 0", lambda v: _number(v) and 0.0 < v < math.inf),
    "online_continuity": ("a number >= 0", lambda v: _number(v) and 0.0 <= v < math.inf),
    "excluded": ("an object", lambda v: isinstance(v, dict)),
}


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _integer(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _meta(model: MLP | GRUModel, path: Path, name: str, default: Any) -> Any:
    """A field of the model's meta (`default` where absent or null); a one-line ModelError
    naming the file and the field when it is not what `_META` says."""
    value = model.meta.get(name)
    if value is None:
        return default
    what, ok = _META[name]
    if not ok(value):
        raise ModelError(f"{path}: field 'meta.{name}': expected {what}, got {value!r}")
    return value


def _options(model: MLP, path: Path) -> dict[str, Any]:
    """The model's feature options from its meta (`mrrig train` writes them), checked against
    its input names; a one-line ModelError if they do not give its inputs."""
    opts = {
        "current_input": _meta(model, path, "current_input", "commanded"),
        "lag_tau_s": _meta(model, path, "lag_tau_s", 1.0),
        "history_samples": _meta(model, path, "history_samples", 0),
        "history_signals": tuple(_meta(model, path, "history_signals", ["x", "xd"])),
        "history_stride": _meta(model, path, "history_stride", 1),
    }
    try:
        names, _ = feature_names(
            opts["history_samples"], opts["history_signals"], opts["history_stride"]
        )
    except ValueError as exc:
        raise ModelError(f"{path}: field 'meta.history_signals': {exc}") from None
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
    window: tuple[float, float] | None = None,
    max_rows: int = SEGMENT_ROWS,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The numbers (`training.report.Scores`) over every segment of the data
    (`training.stream.segments`, each prepared as `mrrig train` prepares it), and the
    arrays a plot needs (`_PlotRows`): memory bounded by a segment, whatever the data's size.
    A MetricError (exit 1) when a number is not finite."""
    opts = _options(model, model_path)
    unit = _meta(model, model_path, "command_unit", "A")
    if keep_all is None:
        keep_all = bool(_meta(model, model_path, "excluded", {}).get("keep_all", False))
    fraction = float(_meta(model, model_path, "holdout_fraction", HOLDOUT_FRACTION))
    i_max = _meta(model, model_path, "i_max_a", None)
    if i_max is None:
        raise ModelError(
            f"{model_path}: field 'meta.i_max_a': missing (not a model of `mrrig train`)"
        )
    mu = float(_meta(model, model_path, "online_continuity", 0.0))
    scores = Scores(mu, float(i_max))
    per_test: dict[str, EtSum] = {}
    coverage = _Coverage(model_envelope(model.meta, str(model_path)))
    plot_rows = _PlotRows(window)
    reports = []
    for path, raw in segments(data, columns, units, max_rows):
        if raw.current_unit != unit:
            raise DataError(
                f"{path}: command in {raw.current_unit}, but the model's command input is in {unit}"
            )
        series, excluded = prepare(path, raw, keep_all)
        reports.append(excluded)
        X, y = features(series, **opts)
        frows = feature_rows(series, opts["history_samples"], opts["history_stride"])
        stretch = stretches(run_ids(series))[frows]
        if rows == "holdout":
            pick = block_split(stretch, fraction).val
        else:
            pick = np.arange(y.size)
        f_model = scores.add(model, X, y, stretch, pick)
        per_test.setdefault(str(path), EtSum()).add(y[pick], f_model)
        coverage.add(series, frows[pick], stretch[pick], y[pick], f_model)
        plot_rows.add(series.t[frows][pick], X[pick, 1], y[pick], f_model, stretch[pick])
    numbers = scores.numbers(f"{model_path} on {', '.join(map(str, data))}")
    numbers.update(
        rows=rows,
        data=[str(p) for p in data],
        model=str(model_path),
        command_unit=unit,
        excluded=merge_reports(reports),
        per_test=[{"file": f, **s.numbers()} for f, s in per_test.items()],
        coverage=coverage.numbers(),
    )
    return numbers, plot_rows.arrays()


def _no_fit(_series: Any) -> Any:
    raise AssertionError("evaluate scores a model given, it fits none")


def evaluate_stateful(
    model: GRUModel | TwinModel,
    model_path: Path,
    data: list[Path],
    columns: dict[str, str] | None = None,
    units: dict[str, str] | None = None,
    keep_all: bool | None = None,
    rows: str = "all",
    window: tuple[float, float] | None = None,
    max_rows: int = SEGMENT_ROWS,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """`evaluate` for a stateful forward model, a GRU or a Bouc-Wen twin: run over each
    stretch of each segment from the zero state (the GRU, `training.gru.gru_forces`) or from
    rest, a stretch that starts moving scored after its warm-up (the twin,
    `training.kinds.twin_kind`'s forces; a grey-box the same, its residual network added), as
    `mrrig train --features auto` scores them. No
    inverse command RMSE (the MLP's exact inversion); the coverage lines where the model keeps
    an envelope (a GRU of `mrrig train` does, a twin does not)."""
    if isinstance(model, GreyBoxModel):  # the twin and its residual network
        kind, unit = "grey-box", model.plant.command_unit
        fraction, envelope = HOLDOUT_FRACTION, None
        forces = greybox_kind(
            _no_fit, holdout_fraction=fraction, seed=0, i_max=1.0, hidden=model.residual.hidden
        ).forces
        model_arg = model
        keep_all = bool(keep_all)
    elif isinstance(model, TwinModel):
        kind, unit = "Bouc-Wen twin", model.plant.command_unit
        fraction, envelope = HOLDOUT_FRACTION, None
        forces = twin_kind(holdout_fraction=fraction, i_max=1.0).forces
        model_arg: Any = model.plant
        keep_all = bool(keep_all)
    else:
        kind, unit = "GRU", _meta(model, model_path, "command_unit", "A")
        fraction = float(_meta(model, model_path, "holdout_fraction", HOLDOUT_FRACTION))
        envelope = model_envelope(model.meta, str(model_path))
        forces, model_arg = gru_forces, model
        if keep_all is None:
            keep_all = bool(_meta(model, model_path, "excluded", {}).get("keep_all", False))
    overall, per_test = EtSum(), {}
    coverage = _Coverage(envelope)
    plot_rows = _PlotRows(window)
    reports = []
    for path, raw in segments(data, columns, units, max_rows):
        if raw.current_unit != unit:
            raise DataError(
                f"{path}: command in {raw.current_unit}, but the model's command input is in {unit}"
            )
        series, excluded = prepare(path, raw, keep_all)
        reports.append(excluded)
        frows, y, f_all = forces(model_arg, series)
        stretch = stretches(run_ids(series))[frows]
        pick = block_split(stretch, fraction).val if rows == "holdout" else np.arange(y.size)
        f_model = f_all[pick]
        overall.add(y[pick], f_model)
        per_test.setdefault(str(path), EtSum()).add(y[pick], f_model)
        coverage.add(series, frows[pick], stretch[pick], y[pick], f_model)
        plot_rows.add(
            series.t[frows][pick], series.xd[frows][pick], y[pick], f_model, stretch[pick]
        )
    forward = overall.numbers()
    if not math.isfinite(forward["et"]):
        raise MetricError(f"{model_path} on {', '.join(map(str, data))}: forward Et not finite")
    numbers = {
        "n": forward["n"],
        "forward": forward,
        "kind": kind,
        "rows": rows,
        "data": [str(p) for p in data],
        "model": str(model_path),
        "command_unit": unit,
        "excluded": merge_reports(reports),
        "per_test": [{"file": f, **s.numbers()} for f, s in per_test.items()],
        "coverage": coverage.numbers(),
    }
    return numbers, plot_rows.arrays()


class _Coverage:
    """Where the evaluated rows leave the model's training envelope (`loop.coverage`): the
    share outside (all inputs, and by input), Et inside and outside, and the band shares of
    the force's and the velocity's power beside the model's. Sums only (memory bounded)."""

    def __init__(self, envelope: Envelope | None) -> None:
        self.envelope = envelope
        self.inside, self.outside = EtSum(), EtSum()
        self.by_input = np.zeros(len(OUTSIDE_BITS), dtype=np.int64)
        self.power = {s: np.zeros(len(BAND_EDGES_HZ)) for s in BAND_SIGNALS}

    def add(self, series, rows, stretch, y, f_model) -> None:
        env = self.envelope
        if env is None or not rows.size:
            return
        state = np.column_stack(
            [series.x[rows], series.xd[rows], series.xdd[rows], series.current[rows]]
        )
        marks = env.outside_rows(state)
        out = marks != 0
        self.inside.add(y[~out], f_model[~out])
        self.outside.add(y[out], f_model[out])
        for k, bit in enumerate(OUTSIDE_BITS.values()):
            self.by_input[k] += int(((marks & bit) != 0).sum())
        pieces = contiguous_pieces(rows, stretch)
        dt = np.diff(series.t[rows])
        dt_s = float(np.median(dt[dt > 0.0])) if np.any(dt > 0.0) else env.sample_period_s
        self.power["force"] += band_power(y, pieces, dt_s)
        self.power["xd"] += band_power(series.xd[rows], pieces, dt_s)

    def numbers(self) -> dict[str, Any] | None:
        env = self.envelope
        if env is None:
            return None
        n = self.inside.n + self.outside.n
        return {
            "rows": n,
            "outside_rows": self.outside.n,
            "outside_share": self.outside.n / n if n else math.nan,
            "outside_share_by_input": {
                name: int(k) / n if n else math.nan
                for name, k in zip(OUTSIDE_BITS, self.by_input, strict=True)
            },
            "inside": self.inside.numbers(),
            "outside": self.outside.numbers(),
            "envelope": {"lo": list(env.lo), "hi": list(env.hi)},
            "bands": band_labels(),
            "band_shares_model": env.bands,
            "band_shares_data": {s: shares(p) for s, p in self.power.items()},
        }


class _PlotRows:
    """What a plot needs, bounded: the window's rows (default: the first `PLOT_WINDOW_S` of
    the first stretch evaluated), at most `PLOT_MAX_ROWS`, and the errors of every row for
    the histogram, thinned by halves to at most `PLOT_MAX_ROWS`."""

    def __init__(self, window: tuple[float, float] | None) -> None:
        self.window = window
        self.parts: list[tuple[np.ndarray, ...]] = []
        self.kept = 0
        self.errors: list[np.ndarray] = []
        self.stride = 1
        self.n_errors = 0
        self.started = False

    def add(self, t, xd, f_meas, f_model, stretch) -> None:
        if self.window is not None:
            w = (t >= self.window[0]) & (t <= self.window[1])
        elif self.started or not t.size:
            w = np.zeros(t.size, dtype=bool)
        else:
            first = stretch == stretch[0]
            w = first & (t <= t[first][0] + PLOT_WINDOW_S)
        self.started |= bool(t.size)
        idx = np.flatnonzero(w)[: PLOT_MAX_ROWS - self.kept]
        if idx.size:
            self.parts.append((t[idx], xd[idx], f_meas[idx], f_model[idx]))
            self.kept += idx.size
        self.errors.append((f_model - f_meas)[:: self.stride])
        self.n_errors += self.errors[-1].size
        if self.n_errors > PLOT_MAX_ROWS:
            self.errors = [np.concatenate(self.errors)[::2]]
            self.n_errors = self.errors[0].size
            self.stride *= 2

    def arrays(self) -> dict[str, np.ndarray]:
        cols = [np.concatenate(c) for c in zip(*self.parts, strict=True)] or [np.empty(0)] * 4
        t, xd, fm, fp = cols
        return {"t": t, "xd": xd, "f_meas": fm, "f_model": fp, "error": np.concatenate(self.errors)}


def _et(d: dict[str, Any]) -> str:
    return f"{d['et']:.4f} ({d['n']} rows)" if d["n"] else "- (no rows)"


def format_coverage(c: dict[str, Any] | None, unit: str) -> list[str]:
    """The coverage lines of `evaluate`'s numbers (none for a model without an envelope)."""
    if c is None:
        return ["coverage: the model keeps no training envelope (trained before models kept one)"]
    names = dict(zip(ENVELOPE_INPUTS, ("x", "xd", "xdd", f"command ({unit})"), strict=True))
    env = c["envelope"]
    ranges = ", ".join(
        f"{names[k]} [{lo:.4g}, {hi:.4g}]"
        for k, lo, hi in zip(ENVELOPE_INPUTS, env["lo"], env["hi"], strict=True)
    )
    by = ", ".join(f"{k} {v:.1%}" for k, v in c["outside_share_by_input"].items())
    lines = [
        f"coverage: {c['outside_share']:.1%} of the rows outside the model's training envelope"
        f" ({c['outside_rows']} of {c['rows']}; by input: {by})",
        f"  envelope (SI): {ranges}",
        f"  forward Et inside {_et(c['inside'])}, outside {_et(c['outside'])}",
    ]
    for sig in BAND_SIGNALS:
        model, data = c["band_shares_model"].get(sig), c["band_shares_data"].get(sig)
        if model is None or data is None:
            continue
        bands = ", ".join(
            f"{label} {m:.0%}/{d:.0%}"
            for label, m, d in zip(c["bands"], model, data, strict=True)
            if m >= 0.005 or d >= 0.005
        )
        lines.append(f"  {sig} power by band, model's training data / these data: {bands}")
    return lines


def format_numbers(r: dict[str, Any]) -> str:
    ex = r["excluded"]
    excl = (
        "nothing excluded (--keep-all)"
        if ex["keep_all"]
        else f"{ex['excluded_samples']} samples excluded as bad stretches"
    )
    tests = [f"  {t['file']}: Et {_et(t)}" for t in r["per_test"]]
    return "\n".join(
        [
            f"{r['model']} on {', '.join(r['data'])}: {r['n']} rows ({r['rows']}; {excl})",
            f"forward Et {r['forward']['et']:.4f}, RMSE {r['forward']['rmse_n']:.2f} N",
            _inverse_line(r),
            f"forward Et per test ({len(tests)}; overall {r['forward']['et']:.4f}, pooled):",
            *tests,
            *_coverage_lines(r),
        ]
    )


def _inverse_line(r: dict[str, Any]) -> str:
    unit = r["command_unit"]
    if "kind" in r:
        return (
            f"inverse command RMSE: does not apply to a {r['kind']} (the MLP's exact inversion;"
            " the daemon inverts this kind frame by frame)"
        )
    return (
        f"inverse command RMSE ({unit}): each sample alone {r['inverse_current_rmse']:.4f},"
        f" on-line {r['inverse_current_rmse_online']:.4f}"
        f" (continuity {r['continuity']:g}, bound {r['i_max']:g} {unit})"
    )


def _coverage_lines(r: dict[str, Any]) -> list[str]:
    if r["coverage"] is None and r.get("kind") == "Bouc-Wen twin":
        return ["coverage: does not apply to a Bouc-Wen twin (a plant file keeps no envelope)"]
    return format_coverage(r["coverage"], r["command_unit"])


def plot(arrays: dict[str, np.ndarray], path: Path, window: tuple[float, float] | None) -> None:
    """Measured and model force over the window's rows (`_PlotRows`), the error histogram,
    force-velocity loops measured and model."""
    import matplotlib  # noqa: PLC0415 - only --plot pays for matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    t, fm, fp, xd = arrays["t"], arrays["f_meas"], arrays["f_model"], arrays["xd"]
    if not t.size:
        raise DataError(f"--window {window}: no evaluated row in it")
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.5))
    ax[0].plot(t, fm, label="measured", lw=1.0)
    ax[0].plot(t, fp, label="model", lw=1.0)
    ax[0].set(xlabel="t (s)", ylabel="force (N)", title="force")
    ax[0].legend()
    ax[1].hist(arrays["error"], bins=80)
    ax[1].set(xlabel="model - measured (N)", ylabel="rows", title="error (all rows)")
    ax[2].plot(xd, fm, label="measured", lw=0.8)
    ax[2].plot(xd, fp, label="model", lw=0.8)
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
    ap.add_argument(
        "model", type=Path, help="forward model file (mrrig train --out: MLP, GRU, or a twin)"
    )
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
    model = load_forward_model(args.model)
    if isinstance(model, MLP) and model.current_index is None:
        raise ModelError(f"{args.model}: no input named 'current': not a forward model")
    columns = _mapping(args.columns, "--columns")
    units = _mapping(args.units, "--units")
    run = evaluate if isinstance(model, MLP) else evaluate_stateful
    try:
        numbers, arrays = run(
            model, args.model, args.data, columns, units, args.keep_all, args.rows, args.window
        )
    except MetricError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(format_numbers(numbers))
    if args.plot:
        plot(arrays, args.plot, args.window)
        print(f"figure: {args.plot}")
    if args.json:
        args.json.write_text(json_text.dumps(numbers, indent=2), encoding="utf-8")
    return 0
