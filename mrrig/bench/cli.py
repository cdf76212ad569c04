"""`mrrig bench NAME`: benchmarks that print numbers (medians, percentiles, ratios)."""

from __future__ import annotations

import argparse
import importlib

BENCHES = {
    "paper": "mrrig.bench.paper",
    "estimation": "mrrig.bench.estimation",
    "inversion": "mrrig.bench.inversion",
    "loop": "mrrig.bench.loop",
    "matrix": "mrrig.bench.matrix",
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="mrrig bench")
    ap.add_argument("name", choices=sorted(BENCHES))
    args, rest = ap.parse_known_args(argv)
    return int(importlib.import_module(BENCHES[args.name]).main(rest) or 0)
