"""`mrrig export RECORDING --to parquet|csv|mf4 [--out FILE]`: a run's samples in a lab's
format, columns named with their units (`t_s`, `x_m`, `force_n`, ...), an absolute UTC time
column, the units and the run's identity, summary and events in the file's metadata.
`mrrig review` and `mrrig evaluate` read the Parquet and MDF4 files back."""

from __future__ import annotations

import argparse
from pathlib import Path

from mrrig.cli_args import HelpFormatter, output_file
from mrrig.export import FORMATS, default_out, export, read_any


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig export", description=__doc__
    )
    ap.add_argument("recording", type=Path, help="a recording (.rrd) written by the daemon")
    ap.add_argument("--to", required=True, choices=FORMATS, help="the format to write")
    ap.add_argument(
        "--out", type=output_file, help="the file to write (default: the recording's name)"
    )
    args = ap.parse_args(argv)
    out = args.out or default_out(args.recording, args.to)
    if out.resolve() == args.recording.resolve():
        ap.error(f"{out} is the recording itself: give another --out")
    rec = read_any(args.recording)
    export(rec, args.to, out)
    print(f"{out}: {rec.samples.size} samples, {len(rec.events)} events ({args.to})")
    return 0
