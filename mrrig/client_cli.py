"""`mrrig status | arm | disarm | control | watch | send-force`: a person at a terminal.

Each opens a Zenoh session (client mode, 127.0.0.1, multicast off: configs/zenoh-client.json5
by default), talks to the daemon's keys `mrrig/<rig>/...` and closes the session.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from mrrig import client, json_text
from mrrig.cli_args import HelpFormatter, finite, positive


def _common(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--rig", default="sim", help="rig name (the Zenoh key prefix mrrig/<rig>)")
    ap.add_argument("--zenoh-config", type=Path, default=client.DEFAULT_CONFIG)
    ap.add_argument("--timeout", type=positive, default=2.0, help="seconds to wait for the daemon")


def _print_reply(reply: dict) -> int:
    print(json_text.dumps(reply, indent=2, sort_keys=True))
    return 0 if reply.get("ok") else 1


def main(argv: list[str]) -> int:
    command, rest = argv[0], argv[1:]
    ap = argparse.ArgumentParser(formatter_class=HelpFormatter, prog=f"mrrig {command}")
    _common(ap)
    if command == "control":
        ap.add_argument("request", help='a JSON request, e.g. \'{"cmd": "status"}\'')
    elif command == "watch":
        ap.add_argument("--duration", type=positive, help="seconds (default: until Ctrl-C)")
        ap.add_argument("--all", action="store_true", help="one line per live rig (a fleet)")
    elif command == "send-force":
        src = ap.add_mutually_exclusive_group(required=True)
        src.add_argument("--csv", type=Path, help="profile file with columns t_s,force_n")
        src.add_argument("--sine", nargs=3, type=finite, metavar=("OFFSET_N", "AMP_N", "FREQ_HZ"))
        ap.add_argument("--rate", type=positive, default=100.0, help="puts per second")
        ap.add_argument("--duration", type=positive, help="seconds (default: the CSV's length)")
    args = ap.parse_args(rest)
    zc = args.zenoh_config
    if command == "status":
        return _print_reply(client.status(args.rig, zc, args.timeout))
    if command == "arm":
        return _print_reply(client.arm(args.rig, zc, args.timeout))
    if command == "disarm":
        return _print_reply(client.disarm(args.rig, zc, args.timeout))
    if command == "control":
        try:
            payload = json.loads(args.request)
        except json.JSONDecodeError as exc:
            raise ValueError(f"request: not valid JSON: {exc}") from None
        return _print_reply(client.request(args.rig, payload, zc, args.timeout))
    if command == "watch":
        if args.all:
            from mrrig.fleet import watch_all

            return 0 if watch_all(zc, args.duration, out=sys.stdout) else 1
        n = client.watch(args.rig, zc, args.duration, out=sys.stdout)
        return 0 if n else 1
    if args.csv is not None:
        profile = args.csv
    else:
        offset, amp, freq = args.sine

        def profile(t: float) -> float:
            return offset + amp * math.sin(2 * math.pi * freq * t)

        if args.duration is None:
            raise ValueError("--duration is needed with --sine")
    sent = client.send_force(args.rig, zc, profile, args.rate, args.duration)
    print(f"sent {sent} force references to mrrig/{args.rig}/force_ref")
    return 0
