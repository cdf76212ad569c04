"""`mrrig train DATA...`: the forward network (and the supervised inverse) from measured data.

DATA are tidy characterization CSVs, daemon recordings (.rrd) or other CSVs with a column map
(`--columns x=Pos,force=F,current=I,t=time`) and units (`--units x=cm,force=kN`), or headers
that name field and unit (`x_cm`, `command_v`). Bad stretches (saturation, idle, transients)
are excluded unless `--keep-all`; the end of each run is held out (`--split blocks`);
`--features auto` (the default) chooses the inputs and the hidden size by cross-validation on
the training blocks: over whole tests where several are given (a file is a test), else over
time blocks; then the kind of model among the static MLP, the history MLP, the GRU and the
Bouc-Wen twin by the other-test estimate: leaving whole tests out, or on a single test its
segments of different character (amplitude, frequency, command level), never their
neighbours; within the loop's work per frame and `--budget-s` (the block hold-out of each kind
printed beside, optimistic). A twin chosen is written
as a plant file (network inversion inverts it, firmware_sim runs it), a GRU as its file. The
block hold-out is optimistic (its neighbours were trained on): the report puts the
other-test estimate beside it (leave one test out, `--cv-folds`) and the Et of tests kept out
altogether (`--validate FILES`).
Writes the model file and prints the validation report (spec/modeling.md section 5).
`--history N` adds N earlier samples of `--history-signals` (default x,xd) to the forward
network's inputs.
`--config FILE` (configs/train.toml) gives the defaults of the options; flags win over it.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from damper.plant_file import PARAM_NAMES, save_plant
from mrrig import json_text
from mrrig.cli.train_gru import write_gru
from mrrig.cli.train_report import (
    format_excluded,
    format_kinds,
    format_other_tests,
    format_report,
    format_search,
)
from mrrig.cli_args import COUNT, SEED, HelpFormatter, output_file, positive
from mrrig.loop.mlp import MIN_SCALE, ModelError
from mrrig.offline.datasets import DataError, Series
from mrrig.offline.evaluate import evaluate
from mrrig.offline.train_config import TrainConfig, load_train_config
from mrrig.offline.training import (
    CURRENT_INPUTS,
    HISTORY_SIGNALS,
    SPLITS,
    check_history,
    train_and_validate,
)
from mrrig.offline.training.crossval import (
    MAX_FOLDS,
    MIN_RUNS,
    SEGMENT_GROUPS,
    SEGMENTS,
    cross_validate,
)
from mrrig.offline.training.gru import DEFAULT_HIDDEN as GRU_HIDDEN
from mrrig.offline.training.kind_choice import choose_kind
from mrrig.offline.training.kinds import (
    ENSEMBLE_MEMBERS,
    GREYBOX,
    GRU,
    SEARCH_SHARE,
    TWIN,
    ModelKind,
    kind_result,
    model_kinds,
)
from mrrig.offline.training.report import MetricError, check_finite
from mrrig.offline.training.select import choose_features
from mrrig.offline.training.stream import sample_tests, training_subset

log = logging.getLogger(__name__)

PROGRESS_EVERY_EPOCHS = 10


def _mapping(text: str | None, option: str) -> dict[str, str] | None:
    """`a=b,c=d` -> {"a": "b", "c": "d"}; a one-line DataError on anything else."""
    if text is None:
        return None
    out = {}
    for item in text.split(","):
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise DataError(f"{option}: expected FIELD=NAME[,FIELD=NAME...], got {item!r}")
        out[key.strip()] = value.strip()
    return out


def _history(
    samples: int, signals_text: str | None, default_signals: tuple[str, ...]
) -> tuple[int, tuple[str, ...]]:
    """The history options (flags over the config's `default_signals`), checked; a one-line
    DataError if wrong."""
    if samples < 0:
        raise DataError(f"--history must be >= 0, got {samples}")
    if signals_text is None:
        return samples, default_signals
    if samples == 0:
        raise DataError(
            "--history-signals needs --history N (or features.history_samples) with N >= 1"
        )
    signals = tuple(s.strip() for s in signals_text.split(","))
    try:
        check_history(samples, signals)
    except ValueError as exc:
        raise DataError(f"--history-signals: {exc}") from None
    return samples, signals


def _fraction(text: str) -> float:
    """The hold-out fraction: a number in (0, 0.5)."""
    value = positive(text)
    if not value < 0.5:
        raise argparse.ArgumentTypeError(f"must be < 0.5, got {text}")
    return value


def _progress(epoch: int, train_mse: float, val_mse: float | None, mu: float) -> None:
    if epoch % PROGRESS_EVERY_EPOCHS == 0:
        val = f"{val_mse:.4g}" if val_mse is not None else "-"
        log.info("epoch %4d  train MSE %.4g  val MSE %s  mu %.3g", epoch, train_mse, val, mu)


def _parser(cfg: TrainConfig) -> argparse.ArgumentParser:
    """The flags, their defaults taken from `cfg` (the config file's, or the built-in ones)."""
    f, t = cfg.features, cfg.training
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter,
        prog="mrrig train",
        description=__doc__.splitlines()[0],
        epilog="With --config FILE the file's [features], [training] and [csv] tables give the "
        "defaults (`--config FILE --help` shows them); a flag given on the command line wins "
        "over the file.",
    )
    ap.add_argument("data", nargs="+", type=Path, help="tidy CSV, .rrd recording or CSV")
    ap.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="training config (TOML, e.g. configs/train.toml): the defaults of the options",
    )
    ap.add_argument(
        "--out",
        type=output_file,
        default="models/forward.json",
        help="the forward model file (default models/forward.json)",
    )
    ap.add_argument(
        "--columns",
        help="CSV column map, e.g. x=Pos,force=F,current=I,t=time (replaces the config's "
        "[csv] columns)",
    )
    ap.add_argument(
        "--units",
        help="CSV units, e.g. x=cm,xd=cm/s,force=kN,current=mA,t=ms (replaces the config's "
        "[csv] units)",
    )
    ap.add_argument(
        "--features",
        choices=("auto", "manual", "gru"),
        default=f.mode,
        help="auto: choose the command input (lag fitted), history and hidden size by blocked "
        "cross-validation on the training blocks, then the kind of model (static MLP, history "
        "MLP, Bouc-Wen twin, GRU) by its other-test Et (tests left out; on one test, segments "
        "of different character) within --budget-s; manual: the flags below. Default: auto, "
        "manual where --current-input or --history is given; gru: a GRU forward model "
        "(--gru-hidden units, --current-input, --lag-tau-s)",
    )
    ap.add_argument(
        "--budget-s",
        type=positive,
        default=t.choice_budget_s,
        help="features auto: the time of the structure search and the kinds' other-test folds,"
        " s (a kind whose folds would not end within it is not tried, with why;"
        " default %(default)g)",
    )
    ap.add_argument(
        "--gru-hidden",
        type=COUNT,
        help=f"--features gru: hidden units (default {GRU_HIDDEN})",
    )
    ap.add_argument(
        "--current-input",
        choices=CURRENT_INPUTS,
        default=None,
        help=f"current input of the network: as commanded, or through the coil lag "
        f"(manual; default {f.current_input})",
    )
    ap.add_argument(
        "--lag-tau-s",
        type=positive,
        default=f.lag_tau_s,
        help="coil lag time constant for --current-input lagged (default %(default).6g s)",
    )
    ap.add_argument(
        "--history",
        type=int,
        default=None,
        metavar="N",
        help=f"history inputs: N earlier samples of --history-signals (manual; default "
        f"{f.history_samples}; 0: none)",
    )
    ap.add_argument(
        "--history-stride",
        type=COUNT,
        default=f.history_stride,
        help="samples between the history taps (default %(default)s)",
    )
    ap.add_argument(
        "--hidden",
        type=COUNT,
        default=f.hidden,
        help="hidden neurons (manual; default %(default)s)",
    )
    ap.add_argument(
        "--split",
        choices=SPLITS,
        default=t.split,
        help="hold-out: blocks (the last --holdout-fraction of each run, default) or random "
        "(the paper's --n-train / --n-val random samples: optimistic, neighbours of held-out "
        "samples are trained on)",
    )
    ap.add_argument(
        "--holdout-fraction",
        type=_fraction,
        default=t.holdout_fraction,
        help="the end of each run held out by the blocks split (default %(default)g)",
    )
    ap.add_argument(
        "--keep-all",
        action="store_true",
        help="keep the bad stretches (saturation, idle, transients) that are excluded by default",
    )
    ap.add_argument(
        "--history-signals",
        metavar="S[,S...]",
        help=f"signals of the history inputs, of {', '.join(HISTORY_SIGNALS)} (default "
        f"{','.join(f.history_signals)}; past currents only where the data varies the "
        "current within a run)",
    )
    ap.add_argument(
        "--epochs", type=COUNT, default=t.epochs, help="LM epoch limit (default %(default)s)"
    )
    ap.add_argument(
        "--seed", type=SEED, default=t.seed, help="split and initial weights (default %(default)s)"
    )
    ap.add_argument(
        "--restarts",
        type=COUNT,
        default=t.restarts,
        help="forward-network starts from different initial weights; the one with the best "
        "on-line inverse on the training rows is kept (default %(default)s); with --features "
        f"auto on several tests, {ENSEMBLE_MEMBERS} of them (at most) are averaged into one "
        "network instead, as each fold fit of the kind choice averages as many",
    )
    ap.add_argument(
        "--n-train",
        type=COUNT,
        default=t.n_train,
        help="training samples (default %(default)s; 90/10 of all samples where fewer)",
    )
    ap.add_argument(
        "--n-val", type=COUNT, default=t.n_val, help="validation samples (default %(default)s)"
    )
    ap.add_argument(
        "--i-max",
        type=positive,
        default=t.i_max_a,
        help="inversion bound, A (default: "
        + ("the data's largest" if t.i_max_a is None else f"{t.i_max_a:g}")
        + ")",
    )
    ap.add_argument(
        "--supervised-out", type=output_file, help="also write the supervised inverse MLP"
    )
    ap.add_argument(
        "--supervised",
        action=argparse.BooleanOptionalAction,
        default=t.supervised,
        help="train the supervised inverse MLP (--no-supervised: skip it, faster)",
    )
    ap.add_argument("--report", type=output_file, help="write the validation report as JSON")
    ap.add_argument(
        "--validate",
        nargs="+",
        type=Path,
        metavar="FILE",
        help="tests kept out of training and of every choice, the model scored on each (Et per"
        " test and overall): how it holds on tests it never saw",
    )
    ap.add_argument(
        "--cv-folds",
        type=_folds,
        default=MAX_FOLDS,
        metavar="K",
        help="the other-test estimate: leave-one-test-out over the tests (files) given, up to"
        " K tests; K folds of tests beyond (default %(default)s; 0: none). One test: its"
        f" {SEGMENTS} segments dealt by character into {SEGMENT_GROUPS} groups, each left out in"
        f" turn, its neighbours not trained on; one test of {MIN_RUNS} runs or more (a"
        " characterization matrix): its runs, each scored and named by its condition, dealt"
        f" by character into {SEGMENT_GROUPS} folds (the same test: optimistic)",
    )
    return ap


def _folds(text: str) -> int:
    value = int(text) if text.lstrip("-").isdigit() else -1
    if value != 0 and value < 2:
        raise argparse.ArgumentTypeError(f"must be 0 (none) or >= 2, got {text}")
    return value


def _check_files(data: list[Path], validate: list[Path] | None) -> None:
    """A one-line DataError for a data file given twice or a validation test trained on."""
    seen: dict[Path, Path] = {}
    for p in data:
        key = p.resolve()
        if key in seen:
            raise DataError(f"{p}: given twice as training data")
        seen[key] = p
    for p in validate or []:
        if p.resolve() in seen:
            raise DataError(
                f"--validate {p}: also given as training data (a validation test is kept out)"
            )


def _write_kind(
    args: argparse.Namespace,
    kind: ModelKind,
    series: Series,
    excluded: dict[str, Any],
    search: dict[str, Any],
    kinds_report: dict[str, Any],
    columns: dict[str, str] | None,
    units: dict[str, str] | None,
) -> int:
    """The chosen twin or GRU: fitted to the training rows and written as the forward model
    network inversion inverts (`[controller] model` = the file): a twin as its plant file
    (which firmware_sim runs too), a GRU as its `mrrig-gru/1` file."""
    validate = [
        (str(p), training_subset([p], columns or None, units or None, args.keep_all)[0])
        for p in args.validate or []
    ]
    model, result = kind_result(kind, series, args.holdout_fraction, validate)
    kept = {
        "kinds": kinds_report,
        **result,
        "data_files": [str(p) for p in args.data],
        "excluded": excluded,
        "features_search": search,
    }
    if kind.name == TWIN:
        save_plant(replace(model, identified=json_text.plain(kept)), args.out)
    elif kind.name == GREYBOX:
        replace(model, identified=json_text.plain({**model.identified, **kept})).save(args.out)
    else:
        model.meta.update(json_text.plain(kept))
        model.save(args.out)
    if args.report:
        args.report.write_text(json_text.dumps(kept, indent=2), encoding="utf-8")
    b = result["block_holdout"]
    lines = [
        *format_excluded(excluded),
        *format_search(search),
        *format_kinds(kinds_report),
        f"{kind.name} Et on the block hold-out (the last {args.holdout_fraction:.0%} of each"
        f" run): {b['et']:.4f} (RMSE {b['rmse_n']:.2f} N)  [optimistic: beside the rows fitted]",
    ]
    v = result["validate"]
    if v is not None:
        lines.append("validation tests (--validate: never fitted nor chosen by):")
        lines += [f"  {t['file']}: Et {t['et']:.4f} ({t['n']} rows)" for t in v["per_test"]]
        lines.append(f"  overall Et {v['forward']['et']:.4f}")
    if kind.name == TWIN:
        p = model.params
        lines += [
            "parameters: "
            + ", ".join(f"{k} {getattr(p, k):.5g}" for k in PARAM_NAMES)
            + f", offset_n {model.offset_n:.5g}, command in {model.command_unit}",
            f"wrote {args.out}: a plant file, the forward model network inversion inverts"
            f' ([controller] model = "{args.out}"; a twin in V: mrrig identify --map-model)'
            " and firmware_sim runs ([plant] file)",
        ]
    elif kind.name == GREYBOX:
        lines.append(
            f"wrote {args.out}: a grey-box forward model (the twin and a network on its"
            f' residual), the model network inversion inverts ([controller] model = "{args.out}")'
        )
    else:
        lines.append(
            f"wrote {args.out}: a GRU forward model, the model network inversion inverts"
            f' ([controller] model = "{args.out}")'
        )
    print("\n".join(lines))
    return 0


def main(argv: list[str] | None = None) -> int:
    # the config first: its values become the flags' defaults, so a flag given wins over it
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--config", type=Path)
    config_path = pre.parse_known_args(argv)[0].config
    cfg = TrainConfig() if config_path is None else load_train_config(config_path)
    args = _parser(cfg).parse_args(argv)
    if not args.supervised and args.supervised_out:
        raise DataError(
            "--supervised-out needs the supervised model: drop --no-supervised "
            "(or training.supervised = false in the config)"
        )
    manual_flags = args.current_input is not None or args.history is not None
    current_input = args.current_input or cfg.features.current_input
    history_samples, history_signals = _history(
        cfg.features.history_samples if args.history is None else args.history,
        args.history_signals,
        cfg.features.history_signals,
    )
    history_stride, hidden = args.history_stride, args.hidden
    columns = _mapping(args.columns, "--columns") if args.columns else dict(cfg.csv.columns)
    units = _mapping(args.units, "--units") if args.units else dict(cfg.csv.units)
    _check_files(args.data, args.validate)
    series, excluded = training_subset(
        args.data, columns or None, units or None, args.keep_all, seed=args.seed
    )
    tests = sample_tests(excluded)
    test_names = [t["file"] for t in excluded["tests"]]
    log.info("training on %d samples from %d file(s)", len(series), len(args.data))
    files = ", ".join(map(str, args.data))
    for name in ("x", "xd", "xdd", "current", "force"):
        spread = float(np.std(getattr(series, name)))
        if not spread >= MIN_SCALE:
            raise DataError(
                f"{files}: {name} does not vary over the {len(series)} samples trained on"
                f" (standard deviation {spread:.3g}): no model can be fitted to it"
            )
    mode = args.features or ("manual" if manual_flags else "auto")
    if mode == "gru":
        return write_gru(
            args, series, excluded, tests, test_names, columns, units, format_other_tests
        )
    search = kinds_report = cv = None
    # where several tests are given, the MLP kinds' fold fits (stopped on whole tests) and the
    # final model average as many fits (`training.ensemble`): ENSEMBLE_MEMBERS, at most --restarts
    several = mode == "auto" and len(test_names) >= 2
    members = min(args.restarts, ENSEMBLE_MEMBERS) if several else 1
    if mode == "auto":
        started = time.perf_counter()
        deadline = started + args.budget_s
        cand, search = choose_features(
            series,
            args.seed,
            args.holdout_fraction,
            budget_s=SEARCH_SHARE * args.budget_s,
            tests=tests,
        )
        i_max = args.i_max or max(float(np.max(series.current)), MIN_SCALE)
        kinds, cands, left_out = model_kinds(
            series,
            search,
            seed=args.seed,
            max_epochs=args.epochs,
            holdout_fraction=args.holdout_fraction,
            i_max=i_max,
            members=members,
        )
        best, kinds_report = choose_kind(
            series,
            tests,
            test_names,
            kinds,
            holdout_fraction=args.holdout_fraction,
            max_folds=args.cv_folds or MAX_FOLDS,
            seed=args.seed,
            deadline=deadline,
            started=started,
            not_built=left_out,
        )
        if best.name in (TWIN, GRU, GREYBOX):
            kind = next(k for k in kinds if k.name == best.name)
            return _write_kind(args, kind, series, excluded, search, kinds_report, columns, units)
        cand = cands[best.name]
        if args.cv_folds and args.split == "blocks":
            cv = best.other_tests  # the other-test estimate of the chosen kind, as computed
        current_input, lag_tau_s = cand.current_input, cand.lag_tau_s
        history_samples, history_signals = cand.history_samples, cand.history_signals
        history_stride, hidden = cand.history_stride, cand.hidden
    else:
        lag_tau_s = args.lag_tau_s
    try:
        fwd, sup, report = train_and_validate(
            series,
            n_train=args.n_train,
            n_val=args.n_val,
            seed=args.seed,
            progress=_progress,
            current_input=current_input,
            lag_tau_s=lag_tau_s,
            max_epochs=args.epochs,
            i_max=args.i_max,
            supervised=args.supervised,
            history_samples=history_samples,
            history_signals=history_signals,
            restarts=members if members > 1 else args.restarts,
            split=args.split,
            holdout_fraction=args.holdout_fraction,
            history_stride=history_stride,
            hidden=hidden,
            average_starts=members > 1,  # as each fold fit of the kind choice averaged
        )
    except ModelError as exc:  # the data gave a network no file could hold
        raise DataError(f"{files}: training gave no usable model: {exc}") from None
    try:
        check_finite(
            {k: report[k] for k in ("forward", "network_inversion", "network_inversion_online")},
            f"{args.out} not written: its hold-out",
            "the held-out force does not vary, or the model's force overflows",
        )
    except MetricError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if args.cv_folds and cv is None:
        options = dict(
            current_input=current_input,
            lag_tau_s=lag_tau_s,
            history_samples=history_samples,
            history_signals=history_signals,
            history_stride=history_stride,
            hidden=hidden,
            split=args.split,
            holdout_fraction=args.holdout_fraction,
        )
        log.info("the other-test estimate: cross-validation over %d test(s)", len(test_names))
        cv = cross_validate(
            series,
            tests,
            test_names,
            options,
            max_folds=args.cv_folds,
            seed=args.seed,
            max_epochs=args.epochs,
        )
    if cv is not None:
        report["other_tests"] = cv
        fwd.meta["other_tests"] = {k: v for k, v in cv.items() if k != "per_group"} | {
            "et": {r[cv["kind"]]: r["et"] for r in cv["per_group"]}
        }
        fwd.metrics["other_test_et"] = cv["overall"]["et"]
    report["excluded"] = excluded
    report["features_mode"] = mode
    report["features_search"] = search
    report["kinds"] = kinds_report
    fwd.meta["excluded"] = excluded
    fwd.meta["features_mode"] = mode
    if search is not None:
        fwd.meta["features_search"] = search
        fwd.meta["kinds"] = kinds_report
    fwd.meta["data_files"] = [str(p) for p in args.data]
    if config_path is not None:
        fwd.meta["train_config"] = str(config_path)
    if args.validate:
        numbers, _ = evaluate(
            fwd, args.out, args.validate, columns or None, units or None, args.keep_all
        )
        report["validate"] = numbers
        fwd.meta["validate"] = {
            "files": [str(p) for p in args.validate],
            "et": numbers["forward"]["et"],
            "et_per_test": {t["file"]: t["et"] for t in numbers["per_test"]},
        }
        fwd.metrics["validate_et"] = numbers["forward"]["et"]
    fwd.save(args.out)
    log.info("wrote %s", args.out)
    if sup is not None and args.supervised_out:
        sup.save(args.supervised_out)
        log.info("wrote %s", args.supervised_out)
    if args.report:
        args.report.write_text(json_text.dumps(report, indent=2), encoding="utf-8")
        log.info("wrote %s", args.report)
    print(format_report(report))
    return 0


if __name__ == "__main__":
    from mrrig.cli.main import main as mrrig_main

    raise SystemExit(mrrig_main(["train", *sys.argv[1:]]))
