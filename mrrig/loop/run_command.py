"""`mrrig run --config configs/rig.toml`: the daemon config with the command line's overrides,
the stop signals, the run, its summary and its exit code (`mrrig.loop.exit_codes`)."""

from __future__ import annotations

import argparse
import logging
import signal
from pathlib import Path

from mrrig import json_text
from mrrig.cli_args import HelpFormatter, add_bus_options, output_file, positive
from mrrig.config import NUMERICS, load_config
from mrrig.loop.daemon import Daemon
from mrrig.loop.exit_codes import Exit
from mrrig.loop.summary import format_summary
from mrrig.rigio.zenoh_config import check_secure, load_zenoh_config

log = logging.getLogger(__name__)

# each ends a run as SIGTERM does (SAFE, the actuator stopped, the summary, the recording
# closed): SIGHUP is an ssh session that dropped, SIGQUIT a Ctrl-\\, SIGUSR1/2 a stray kill;
# their default actions killed the daemon with its last command ACTIVE. SIGPIPE stays ignored
# (Python's choice): a reader that went away is an error on that write, not a stop
STOP_SIGNALS = (
    signal.SIGINT,
    signal.SIGTERM,
    signal.SIGHUP,
    signal.SIGQUIT,
    signal.SIGUSR1,
    signal.SIGUSR2,
)
# a stop is honoured within the spec's sensor timeout (3 periods) whatever the config's: the


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="mrrig run", description="Run the rig daemon.", formatter_class=HelpFormatter
    )
    ap.add_argument("--config", required=True, type=Path, help="daemon config (TOML)")
    ap.add_argument("--duration", type=positive, help="stop after this many seconds (s)")
    ap.add_argument("--arm", action="store_true", help="arm at start (commands ACTIVE)")
    ap.add_argument(
        "--record", type=Path, help="recording file (default: recordings/<rig>-<UTC>.rrd)"
    )
    ap.add_argument("--no-record", action="store_true", help="no Rerun recording")
    ap.add_argument(
        "--can-log",
        type=Path,
        help="also write every frame to this bus log (.blf, .asc, .log candump, .trc, .csv,"
        " .mf4 with asammdf; overrides recording.can_log)",
    )
    ap.add_argument("--summary-json", type=output_file, help="also write the summary to this file")
    add_bus_options(ap)
    ap.add_argument("--no-telemetry", action="store_true", help="no Zenoh telemetry")
    ap.add_argument(
        "--zenoh-config", type=Path, help="the sidecar's Zenoh config (overrides the config's)"
    )
    ap.add_argument(
        "--adaptation",
        choices=("on", "off"),
        help="override adaptation.enabled: on-line gain and offset of the model's force",
    )
    ap.add_argument(
        "--numerics",
        choices=NUMERICS,
        help="override loop.numerics: the frame's numerics compiled, or on the Python path",
    )
    ap.add_argument(
        "--insecure",
        action="store_true",
        help="allow a Zenoh config off loopback without authentication and access control "
        "(a closed lab network only); warned in every status and recording",
    )
    ap.add_argument(
        "--hil", help="a hybrid simulation: this scenario (configs/hil/*.toml, or a stroke CSV)"
    )
    ap.add_argument("--hil-law", help="--hil: this law in place of the scenario's")
    ap.add_argument(
        "--hil-compensation",
        choices=("none", "polynomial", "adaptive", "model"),
        help="--hil: this delay compensation in place of the scenario's",
    )
    ap.add_argument("--hil-duration", type=positive, help="--hil: seconds, for the scenario's")
    ap.add_argument("--specimen", help="the damper under test (its serial number), for the catalog")
    ap.add_argument("--operator", help="who runs the test (default: the local user)")
    ap.add_argument("--tag", action="append", default=[], help="a free-text tag (repeatable)")
    ap.add_argument("--catalog", help="register the run in this catalog (file or database URL)")
    args = ap.parse_args(argv)
    overrides: dict[str, dict] = {}
    rig = {k: v for k, v in (("specimen", args.specimen), ("operator", args.operator)) if v}
    if args.tag:
        rig["tags"] = args.tag
    if rig:
        overrides["rig"] = rig
    if args.catalog:
        overrides["catalog"] = {"url": args.catalog}
    bus = {k: v for k, v in (("interface", args.bus_interface), ("channel", args.bus_channel)) if v}
    if bus:
        overrides["bus"] = bus
    if args.no_telemetry:
        overrides["telemetry"] = {"enabled": False}
    if args.can_log is not None:
        overrides["recording"] = {"can_log": str(args.can_log)}
    if args.adaptation:
        overrides["adaptation"] = {"enabled": args.adaptation == "on"}
    if args.insecure:
        overrides.setdefault("telemetry", {})["insecure"] = True
    if args.zenoh_config is not None:
        overrides.setdefault("telemetry", {})["zenoh_config"] = str(args.zenoh_config)
    hil = {k: v for k, v in (("scenario", args.hil), ("law", args.hil_law),
                             ("compensation", args.hil_compensation),
                             ("duration_s", args.hil_duration)) if v is not None}  # fmt: skip
    if hil:
        overrides["hil"] = hil
    loop = {}
    if args.duration is not None:
        loop["duration_s"] = args.duration
    if args.arm:
        loop["arm_on_start"] = True
    if args.numerics:
        loop["numerics"] = args.numerics
    if loop:
        overrides["loop"] = loop
    cfg = load_config(args.config, overrides)
    if cfg.telemetry.enabled:  # the sidecar checks it too; refused here before the bus opens
        check_secure(
            load_zenoh_config(cfg.telemetry.zenoh_config),
            str(cfg.telemetry.zenoh_config),
            cfg.telemetry.insecure,
        )
    record = args.record
    if args.no_record:
        record = None
    elif record is None and cfg.recording.enabled:
        # imports rerun (its threads, its libraries locked with the loop's memory): only when
        # this run records
        from mrrig.rigio.recording import recording_path

        record = recording_path(cfg.recording.directory, cfg.rig.name)
    daemon = Daemon(cfg, record_path=record)
    for sig in STOP_SIGNALS:
        signal.signal(sig, lambda s, _f: daemon.request_stop(signal.Signals(s).name))
    log.info(
        "rig %s: %s on %s/%s",
        cfg.rig.name,
        daemon.controller.name,
        cfg.bus.interface,
        cfg.bus.channel,
    )
    summary = daemon.run()
    print(format_summary(summary))
    for path in daemon.sidecar.record_paths:
        print(f"recording: {path}")
    if cfg.recording.can_log is not None:
        print(f"bus log: {cfg.recording.can_log}")
    if args.summary_json:
        args.summary_json.write_text(json_text.dumps(summary, indent=2))
    if daemon.exit_code != Exit.OK:
        log.warning("exit code %d: %s", daemon.exit_code, summary["stop_reason"] or "a fault")
    return daemon.exit_code
