"""`mrrig bench NAME`: benchmarks that print numbers (medians, percentiles, ratios)."""

from __future__ import annotations

import argparse
import importlib
import sys

from mrrig.cli_args import HelpFormatter

BENCHES = {
    "paper": "mrrig.offline.bench.paper",
    "estimation": "mrrig.offline.bench.estimation",
    "inversion": "mrrig.offline.bench.inversion",
    "loop": "mrrig.offline.bench.loop",
    "matrix": "mrrig.offline.bench.matrix",
    "drift": "mrrig.offline.bench.drift",
    "train": "mrrig.offline.bench.train",
    "fuzz": "mrrig.offline.bench.fuzz",
    "catalog": "mrrig.offline.bench.catalog",
    "soak": "mrrig.offline.bench.soak",
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in BENCHES:  # the rest, --help included, is the benchmark's own
        return int(importlib.import_module(BENCHES[argv[0]]).main(argv[1:]) or 0)
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig bench", description=__doc__
    )
    ap.add_argument(
        "name", choices=sorted(BENCHES), help="then its own options (mrrig bench NAME --help)"
    )
    ap.parse_args(argv)  # no benchmark named: help, or the error and exit code 2
    return 2
