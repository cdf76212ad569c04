"""`mrrig train --features gru`: the recurrent forward model (mrrig/offline/training/gru.py),
written as a `mrrig-gru/1` file that network inversion takes as its model."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mrrig import json_text
from mrrig.offline.datasets import Series
from mrrig.offline.training.gru import DEFAULT_HIDDEN, gru_result
from mrrig.offline.training.stream import training_subset

log = logging.getLogger(__name__)


def write_gru(
    args: argparse.Namespace,
    series: Series,
    excluded: dict[str, Any],
    tests: np.ndarray,
    test_names: list[str],
    columns: dict[str, str] | None,
    units: dict[str, str] | None,
    format_other_tests: Callable[[dict[str, Any] | None], list[str]],
) -> int:
    """Fit, report (block hold-out, other tests, validation tests) and write the GRU."""
    validate = [
        (str(p), training_subset([p], columns or None, units or None, args.keep_all)[0])
        for p in args.validate or []
    ]
    hidden = args.gru_hidden or DEFAULT_HIDDEN
    model, report = gru_result(
        series,
        tests=tests,
        test_names=test_names,
        validate=validate,
        max_folds=args.cv_folds,
        seed=args.seed,
        hidden=hidden,
        holdout_fraction=args.holdout_fraction,
        current_input=args.current_input or "lagged",
        lag_tau_s=args.lag_tau_s,
    )
    model.meta["data_files"] = [str(p) for p in args.data]
    model.meta["excluded"] = excluded
    model.save(args.out)
    if args.report:
        args.report.write_text(json_text.dumps(report, indent=2), encoding="utf-8")
    lines = [
        f"GRU forward model, {hidden} units ({model.meta['current_input']} current"
        + (f", lag tau {model.lag_tau_s * 1e3:.2f} ms" if model.lag_tau_s else "")
        + f"): {report['windows']} windows of {model.meta['burn_in_s']:g} s burn-in +"
        f" {model.meta['window_s']:g} s, best epoch {report['best_epoch']} of"
        f" {report['epochs']}, {report['seconds']:.1f} s",
        f"  split: {report['split']['rule']}",
        f"GRU Et on the block hold-out (the last {args.holdout_fraction:.0%} of each run):"
        f" {report['holdout_et']:.4f}  [optimistic: the same tests, later in time]",
        *format_other_tests(report.get("other_tests")),
    ]
    v = report["validate"]
    if v is not None:
        lines.append("validation tests (--validate: never trained on nor chosen by):")
        lines += [f"  {t['file']}: Et {t['et']:.4f} ({t['n']} rows)" for t in v["per_test"]]
        lines.append(f"  overall Et {v['forward']['et']:.4f}")
    lines.append(
        f"wrote {Path(args.out)}: a GRU forward model, the model network inversion inverts"
        f' ([controller] model = "{args.out}")'
    )
    print("\n".join(lines))
    return 0
