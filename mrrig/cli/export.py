"""`mrrig export RECORDING --to parquet|csv|mf4 [--out FILE]`: a run's samples in a lab's
format, columns named with their units (`t_s`, `x_m`, `force_n`, ...), an absolute UTC time
column, the units and the run's identity, summary and events in the file's metadata.
`--run ID` exports one run of the catalog (a plan step's): its recording, its rows only;
`--from S` / `--until S` a time window on the recording's clock (t_s).
`mrrig review` and `mrrig evaluate` read the Parquet and MDF4 files back. An --out that is
there already is replaced only with --force; a symbolic link, a run catalog or a recording
never."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from mrrig.api.catalog import check_recording, default_catalog, get_run
from mrrig.cli_args import HelpFormatter, output_file
from mrrig.export import FORMATS, default_out, export, read_any
from mrrig.export.target import check_target
from mrrig.export.window import run_window, window

log = logging.getLogger("mrrig.export")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig export", description=__doc__
    )
    ap.add_argument(
        "recording",
        type=Path,
        nargs="?",
        help="a recording (.rrd) written by the daemon (or --run)",
    )
    ap.add_argument(
        "--run", help="a run id of the catalog (4+ leading hex digits): that run's rows only"
    )
    ap.add_argument(
        "--catalog",
        help="the catalog of --run (default: $MRRIG_CATALOG, else recordings/catalog.sqlite)",
    )
    ap.add_argument("--from", dest="from_s", type=float, help="from this t_s on (s)")
    ap.add_argument("--until", dest="until_s", type=float, help="up to this t_s (s)")
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
    run = None
    if args.run is not None:
        if args.recording is not None:
            ap.error("give a recording or --run, not both (a run names its recording)")
        run = get_run(args.run, args.catalog)
        if not run.recording_path:
            ap.error(f"run {run.run_id} has no recording registered")
        recording = Path(run.recording_path)
        if not recording.is_file():
            ap.error(f"run {run.run_id}: its recording {recording} is not there")
        check = check_recording(run)
        if check != "unchanged":
            log.warning("run %s: recording %s", run.run_id, check)
    elif args.recording is None:
        ap.error("give a recording, or --run ID")
    else:
        recording = args.recording
    if run is not None and (args.from_s is not None or args.until_s is not None):
        ap.error("--run exports the run's own stretch: --from/--until are for a recording")
    out = args.out or default_out(recording, args.to)
    if run is not None and args.out is None:
        out = recording.with_name(f"{recording.stem}-run-{str(run.run_id)[:8]}.{args.to}")
    if out.resolve() == recording.resolve():
        ap.error(f"{out} is the recording itself: give another --out")
    # before the recording is read: a refused --out is refused at once
    check_target(out, args.force, protected=(Path(args.catalog or default_catalog()),))
    rec = read_any(recording)
    if run is not None:
        rec = window(rec, *run_window(rec, run), run=run.to_json())
    elif args.from_s is not None or args.until_s is not None:
        rec = window(rec, args.from_s, args.until_s)
    export(rec, args.to, out, force=args.force)
    print(f"{out}: {rec.samples.size} samples, {len(rec.events)} events ({args.to})")
    return 0
