"""`mrrig status | arm | disarm | reset | control | watch | send-force`: a person at a terminal.

Each opens a Zenoh session (client mode, 127.0.0.1, multicast off: configs/zenoh-client.json5
by default), talks to the daemon's keys `mrrig/<rig>/...` and closes the session: through the
Python API's `mrrig.api.Rig` (what a script calls), `watch` through its terminal printer.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from mrrig import json_text
from mrrig.cli_args import HelpFormatter, controllers_epilog, finite, non_negative, positive
from mrrig.rigio import client


def _common(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--rig", default="sim", help="rig name (the Zenoh key prefix mrrig/<rig>)")
    ap.add_argument(
        "--zenoh-config",
        type=Path,
        default=client.DEFAULT_CONFIG,
        help="Zenoh config reaching the daemon (JSON5)",
    )
    ap.add_argument(
        "--timeout", type=positive, default=2.0, help="seconds to wait for the daemon's answer"
    )


def _print_reply(reply: dict) -> int:
    print(json_text.dumps(reply, indent=2, sort_keys=True))
    return 0 if reply.get("ok") else 1


_STATUS_HEAD = (
    "rig", "state", "armed", "controller", "reference", "fault", "fault_reason", "t", "identity",
)  # fmt: skip


def format_status(status: dict[str, Any]) -> str:
    """`mrrig status` for a person: state, controller, reference, fault, then the counters."""
    state = status.get("state", "?")
    mode = {"ARMED": "commands ACTIVE", "IDLE": "commands SAFE 0 A", "FAULT": "SAFE 0 A"}
    lines = [
        f"rig {status.get('rig')}: {state} ({mode.get(state, '?')}), up {status.get('t', 0):.1f} s",
        f"  controller {status.get('controller')}, force reference {status.get('reference')}",
    ]
    ident = status.get("identity") or {}
    if ident:
        sha = ident.get("model_sha256")
        model = f"{ident['model_path']} (sha256 {sha[:12] if sha else 'unreadable'})"
        lines.append(
            f"  model {model if ident.get('model_path') else 'none'}, specimen"
            f" {ident.get('specimen') or 'not set'}, run {ident.get('run_id')}"
        )
    if status.get("fault"):
        lines.append(f"  fault {status['fault']}: {status.get('fault_reason')}")
        rig = status.get("rig")
        lines.append(
            f"  after checking the rig: mrrig reset --rig {rig} (acknowledge), then mrrig arm"
        )
    counters = {k: v for k, v in status.items() if k not in _STATUS_HEAD}
    width = max((len(k) for k in counters), default=0)
    lines += [f"  {k:<{width}}  {_value(v)}" for k, v in counters.items()]
    return "\n".join(lines)


def _value(v: Any) -> str:
    if isinstance(v, dict) and "path" in v and "bytes" in v:  # the recording being written
        return f"{v['path']} ({v['bytes']} bytes, {v.get('frames')} samples)"
    return f"{v:.3f}" if isinstance(v, float) else str(v)


def main(argv: list[str]) -> int:
    command, rest = argv[0], argv[1:]
    ap = argparse.ArgumentParser(formatter_class=HelpFormatter, prog=f"mrrig {command}")
    _common(ap)
    if command == "status":
        ap.add_argument("--json", action="store_true", help="the daemon's JSON reply, for scripts")
    elif command == "arm":
        ap.add_argument(
            "--hold",
            action="store_true",
            help="hold the rig armed, renewing the arm's lease, until Ctrl-C (then disarm and"
            " stop the actuator); without it the arm lasts for the lease's timeout only"
            " (control.lease_timeout_s): a client that holds the rig must renew it",
        )
    elif command == "control":
        ap.add_argument("request", help='a JSON request, e.g. \'{"cmd": "status"}\'')
        ap.epilog = controllers_epilog().replace("controller.name", 'set_controller\'s "name"')
    elif command == "watch":
        ap.add_argument("--duration", type=positive, help="seconds (default: until Ctrl-C)")
        ap.add_argument("--all", action="store_true", help="one line per live rig (a fleet)")
    elif command == "send-force":
        src = ap.add_mutually_exclusive_group(required=True)
        src.add_argument(
            "--csv", type=Path, help="profile file: a header with columns t_s (s) and force_n (N)"
        )
        src.add_argument(
            "--sine",
            nargs=3,
            type=finite,
            metavar=("OFFSET_N", "AMP_N", "FREQ_HZ"),
            help="offset + amplitude sin(2 pi f t): N, N, Hz",
        )
        ap.add_argument("--rate", type=positive, default=100.0, help="samples per second (Hz)")
        ap.add_argument("--duration", type=positive, help="seconds (default: the CSV's length)")
        ap.add_argument(
            "--arm", action="store_true", help="arm the daemon once it has the first sample"
        )
        ap.add_argument(
            "--no-disarm",
            action="store_true",
            help="leave the daemon armed after the ramp (another source must follow, or it"
            " faults stale_reference)",
        )
        ap.add_argument(
            "--ramp", type=non_negative, default=0.5, help="ramp to 0 N after the profile (s)"
        )
    args = ap.parse_args(rest)
    zc = args.zenoh_config
    if command == "watch":
        if args.all:
            from mrrig.rigio.fleet import watch_all

            return 0 if watch_all(zc, args.duration, out=sys.stdout) else 1
        n = client.watch(args.rig, zc, args.duration, out=sys.stdout)
        return 0 if n else 1
    if command == "send-force":
        return _send_force(args)
    from mrrig.api import Rig

    with Rig(args.rig, zc, args.timeout) as rig:
        if command == "control":
            try:
                payload = json.loads(args.request)
            except json.JSONDecodeError as exc:
                raise ValueError(f"request: not valid JSON: {exc}") from None
        else:
            payload = {"cmd": command}  # status, arm, disarm, reset
        reply = rig.ask(payload)
        if rig.lease is not None:
            if command == "arm" and args.hold:
                _print_reply(reply)
                return _hold(rig)
            rig.let_go()
            renew = json.dumps({"cmd": "renew", "lease": reply["lease"]})
            print(
                f"note: armed for the lease only: unless a client renews it ({renew}), the"
                f" daemon disarms and stops the actuator after {reply['lease_timeout_s']:g} s"
                " (control.lease_timeout_s); mrrig arm --hold holds the rig until Ctrl-C",
                file=sys.stderr,
            )
    if command == "status" and not args.json and reply.get("ok"):
        print(format_status(reply["status"]))
        return 0
    return _print_reply(reply)


def _hold(rig: Any) -> int:
    """`mrrig arm --hold`: renew the arm's lease until Ctrl-C (0: the rig disarmed and its
    actuator stopped by the Rig's close) or until the daemon ends it (1: why)."""
    print(
        f"holding rig {rig.name} armed (lease renewed every {rig.lease.timeout_s / 4:g} s);"
        " Ctrl-C disarms and stops the actuator",
        file=sys.stderr,
        flush=True,
    )
    try:
        while rig.lease.held:
            time.sleep(0.1)
    except KeyboardInterrupt:
        return 0
    print(f"the rig is no longer held: {rig.lease.lost}", file=sys.stderr)
    return 1


def _send_force(args: argparse.Namespace) -> int:
    """The profile (a bad one refused before any session opens), then `Rig.stream_force`."""
    from mrrig.api import Rig
    from mrrig.rigio import force_stream

    if args.csv is not None:
        fn, length_s = force_stream.csv_profile(args.csv)
        duration_s = args.duration or length_s
    else:
        if args.duration is None:
            raise ValueError("--duration is needed with --sine")
        offset, amp, freq = args.sine

        def fn(t: float) -> float:
            return offset + amp * math.sin(2 * math.pi * freq * t)

        duration_s = args.duration
    n_profile = math.floor(duration_s * args.rate) + 1  # t = 0, 1/rate, ..., duration_s
    with Rig(args.rig, args.zenoh_config, args.timeout) as rig:
        result = rig.stream_force(
            (fn(k / args.rate) for k in range(n_profile)),
            args.rate,
            arm=args.arm,
            disarm=not args.no_disarm,
            ramp_s=args.ramp,
            duration_s=duration_s,
            out=sys.stdout,
        )
    end = "disarmed" if result.disarmed else "left armed" if args.no_disarm else "not armed"
    held = f"{result.hold_samples} while arming, " if result.hold_samples else ""
    print(
        f"sent {result.hold_samples + result.sent} force references to"
        f" mrrig/{args.rig}/force_ref ({held}{result.sent - result.ramp_samples} of the profile,"
        f" {result.ramp_samples} of the ramp to 0 N); {end}"
    )
    if result.faults:
        print(f"the daemon faulted while streaming: {'; '.join(result.faults)}")
        return 1
    return 130 if result.interrupted else 0
