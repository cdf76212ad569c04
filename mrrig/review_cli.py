"""`mrrig review FILE.rrd`: the metrics of a recorded run, read back with Rerun's reader."""

from __future__ import annotations

import argparse
from pathlib import Path

from mrrig import json_text
from mrrig.cli_args import HelpFormatter, output_file
from mrrig.review import plot_recording, read_recording, verify_rrd
from mrrig.summary import format_summary, summarize


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig review", description=__doc__
    )
    ap.add_argument("file", type=Path, help="a recording (.rrd) written by the daemon")
    ap.add_argument("--plot", type=output_file, help="also write a figure (PNG) of the run")
    ap.add_argument("--json", type=output_file, help="also write the metrics as JSON")
    ap.add_argument("--verify", action="store_true", help="run `rerun rrd verify` first")
    args = ap.parse_args(argv)
    if args.verify:
        verify_rrd(args.file)
    rec = read_recording(args.file)
    counters = rec.summary or {}
    keep = {k: v for k, v in counters.items() if not isinstance(v, dict | list)}
    metrics = summarize(rec.samples, rec.events, keep)
    # the files first: output cut short by a closed pipe (`| head`) must not lose them
    if args.plot:
        plot_recording(rec, args.plot)
    if args.json:
        args.json.write_text(json_text.dumps(metrics, indent=2))
    print(format_summary(metrics))
    if args.plot:
        print(f"figure: {args.plot}")
    return 0
