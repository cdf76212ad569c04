"""`mrrig review FILE.rrd`: the metrics of a recorded run, read back with Rerun's reader;
optionally a figure, a one-file HTML report and the check of a bus log of the same run.

A recording without the summary the daemon writes at its end is truncated (the recording
failed, or the run was killed): review says so and exits 1, unless `--partial`. A recording
without a single sensor frame has nothing to review: one line, exit 1.

An .rrd is read in one streaming pass, its metrics accumulated as it goes: memory does not
grow with the run's length, except for the samples a figure (`--plot`, `--html`) draws, and
the whole run's samples that `--can-log` checks.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from mrrig import json_text
from mrrig.cli_args import HelpFormatter, finite, output_file
from mrrig.export import read_any
from mrrig.loop.summary import format_summary
from mrrig.offline.review import BlockSummary, review_recording, verify_rrd

_EXPORTS = (".parquet", ".mf4")  # read whole by `read_any`; an .rrd is streamed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig review", description=__doc__
    )
    ap.add_argument(
        "file", type=Path, help="a recording (.rrd) written by the daemon, or its .parquet or .mf4"
    )
    ap.add_argument("--from", dest="t_from", type=finite, help="window start, sensor time (s)")
    ap.add_argument("--to", dest="t_to", type=finite, help="window end, sensor time (s)")
    ap.add_argument("--plot", type=output_file, help="also write a figure (PNG) of the window")
    ap.add_argument(
        "--html",
        type=output_file,
        help="also write a one-file HTML report (figure embedded, summary table, faults)",
    )
    ap.add_argument("--json", type=output_file, help="also write the metrics as JSON")
    ap.add_argument(
        "--can-log",
        type=Path,
        help="a bus log of the same run (.blf, .asc, .log, ...): check its frames and counters"
        " against the recording (exit 1 on a mismatch)",
    )
    ap.add_argument(
        "--config",
        type=Path,
        help="--can-log: the daemon config of the run, whose [can] rig profile (the lab's DBC"
        " and roles) decodes the log (default: the CAN contract's)",
    )
    ap.add_argument("--verify", action="store_true", help="run `rerun rrd verify` first")
    ap.add_argument("--partial", action="store_true", help="review a truncated recording (exit 0)")
    args = ap.parse_args(argv)
    if args.config is not None and args.can_log is None:
        ap.error("--config: the rig profile decodes a --can-log; give one")
    if args.verify:
        verify_rrd(args.file)
    windowed = args.t_from is not None or args.t_to is not None
    window_text = None
    if windowed:
        window_text = f"{_bound(args.t_from)} to {_bound(args.t_to)} s of sensor time"
    streamed = args.can_log is None and args.file.suffix.lower() not in _EXPORTS
    acc = None
    if streamed:  # one pass in bounded memory: the samples kept only for a figure
        rec, acc = review_recording(
            args.file, args.t_from, args.t_to, keep_samples=bool(args.plot or args.html)
        )
    else:
        rec = read_any(args.file)  # a Parquet or MDF4 export, or for the bus log's check
    # a streamed review holds no samples without a figure: its count is the accumulator's (the
    # whole recording's, unless a window: one without a frame of a recording with some raised)
    if (acc.frames if acc is not None else rec.samples.size) == 0:
        logging.getLogger("mrrig.offline.review").error(
            "%s: no frames: the recording holds no sensor frame (the rig sent none, or the run"
            " ended before its first); nothing to review",
            args.file,
        )
        return 1
    if rec.summary is None:
        logging.getLogger("mrrig.offline.review").error(
            "%s: truncated: no end-of-run summary (the recording failed or the run was killed); %s",
            args.file,
            "reviewing what is there" if args.partial else "--partial reviews what is there",
        )
        if not args.partial:
            return 1
    bus_log = None
    if args.can_log is not None:
        from mrrig.rigio.canlog import check_bus_log

        profile = None
        if args.config is not None:
            from mrrig.config import load_config
            from mrrig.rigio.canbus.profile import load_profile

            cfg = load_config(args.config)
            profile = load_profile(cfg.can.dbc, cfg.can.signals, cfg.loop.period_s, cfg.source)
        bus_log = check_bus_log(args.can_log, rec.samples, rec.summary, profile)
    if windowed and not streamed:
        from mrrig.offline.review_report import window

        rec = window(rec, args.t_from, args.t_to)
    # the run's counters describe the whole run, not a window of it
    counters = {} if windowed else rec.summary or {}
    keep = {k: v for k, v in counters.items() if not isinstance(v, dict | list)}
    # the loop's work per frame, which the latency budget is for: the daemon measured it (the
    # frames hold the latency from the bus's receive only), so the verdict is the daemon's
    if "latency_split_us" in counters:
        keep["latency_split_us"] = counters["latency_split_us"]
    if "kernel_stalls" in counters:  # the loop's own stalls, which the kernel measured
        keep["kernel_stalls"] = counters["kernel_stalls"]
    if acc is None:  # in the blocks a streamed .rrd adds up in: the same numbers, bit for bit
        acc = BlockSummary()
        acc.add(rec.samples)
    metrics = acc.result(rec.events, keep)
    # the files first: output cut short by a closed pipe (`| head`) must not lose them
    if args.plot or args.html:
        from mrrig.offline import review_report

        if args.plot:
            review_report.plot(rec, metrics, args.plot)
        if args.html:
            bus_text = bus_log.text() if bus_log is not None else None
            review_report.write_html(rec, metrics, args.html, bus_text, window_text)
    if args.json:
        args.json.write_text(json_text.dumps(metrics, indent=2))
    if window_text:
        print(f"window        {window_text}")
    print(format_summary(metrics))
    for label, path in (("figure", args.plot), ("report", args.html)):
        if path:
            print(f"{label}: {path}")
    if bus_log is not None:
        print(bus_log.text())
        return 0 if bus_log.ok else 1
    return 0


def _bound(t: float | None) -> str:
    return "start" if t is None else f"{t:g}"
