"""`mrrig export RECORDING --to parquet|csv|mf4 [--out FILE]`: a run's samples in a lab's
format, columns named with their units (`t_s`, `x_m`, `force_n`, ...), an absolute UTC time
column, the units and the run's identity, summary and events in the file's metadata.
`mrrig review` and `mrrig evaluate` read the Parquet and MDF4 files back. An --out that is
there already is replaced only with --force; a symbolic link, a run catalog or a recording
never."""

from __future__ import annotations

import argparse
from pathlib import Path

from mrrig.api.catalog import default_catalog
from mrrig.cli_args import HelpFormatter, output_file
from mrrig.export import FORMATS, default_out, export, read_any
from mrrig.export.target import check_target


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig export", description=__doc__
    )
    ap.add_argument("recording", type=Path, help="a recording (.rrd) written by the daemon")
    ap.add_argument("--to", required=True, choices=FORMATS, help="the format to write")
    ap.add_argument(
        "--out", type=output_file, help="the file to write (default: the recording's name)"
    )
    ap.add_argument(
        "--force",
        action="store_true",
        help="replace the file if it is there (never a link, a catalog or a recording)",
    )
    args = ap.parse_args(argv)
    out = args.out or default_out(args.recording, args.to)
    if out.resolve() == args.recording.resolve():
        ap.error(f"{out} is the recording itself: give another --out")
    # before the recording is read: a refused --out is refused at once
    check_target(out, args.force, protected=(Path(default_catalog()),))
    rec = read_any(args.recording)
    export(rec, args.to, out, force=args.force)
    print(f"{out}: {rec.samples.size} samples, {len(rec.events)} events ({args.to})")
    return 0
