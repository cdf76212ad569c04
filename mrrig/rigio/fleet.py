"""A fleet of rigs behind one Zenoh router: `mrrig rigs` and `mrrig watch --all`.

A rig is live while its sidecar holds its liveliness token `mrrig/<rig>/alive/<session id>`
(gone within milliseconds of its session closing, or of its process dying); two tokens of one
name are two daemons that both obey that rig's requests, shown as such. Its state, controller
and fault come from its latest status, which the sidecar answers on `mrrig/<rig>/status` (an
observer's read, not a control request).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import zenoh

from mrrig import json_text
from mrrig.cli_args import HelpFormatter, positive
from mrrig.rigio import client

ALIVE = "mrrig/*/alive/*"
STATUS = "mrrig/*/status"
TELEMETRY = "mrrig/*/telemetry"


def rig_of(key: str) -> str:
    """'mrrig/rig2/alive/<id>' -> 'rig2'."""
    return str(key).split("/")[1]


@dataclass(frozen=True)
class RigInfo:
    name: str
    status: dict[str, Any] | None  # None: alive, but no status yet (starting)
    daemons: int = 1  # liveliness tokens of this name: more than one is a duplicate

    def row(self) -> dict[str, Any]:
        s = self.status or {}
        return {
            "rig": self.name,
            "state": s.get("state"),
            "controller": s.get("controller"),
            "fault": s.get("fault"),
            "daemons": self.daemons,
        }


def live_rigs(session: zenoh.Session, timeout_s: float = 1.0) -> list[RigInfo]:
    """The rigs whose liveliness token is up, with their latest status, sorted by name."""
    names = Counter(
        rig_of(r.ok.key_expr)
        for r in session.liveliness().get(ALIVE, timeout=timeout_s)
        if r.ok is not None
    )
    statuses: dict[str, dict[str, Any]] = {}
    if names:
        for reply in session.get(STATUS, timeout=timeout_s):
            if reply.ok is not None:
                try:
                    statuses[rig_of(reply.ok.key_expr)] = json.loads(reply.ok.payload.to_bytes())
                except ValueError:
                    continue
    return [RigInfo(name, statuses.get(name), names[name]) for name in sorted(names)]


def duplicates_text(rigs: list[RigInfo]) -> str:
    """One line per rig name that more than one daemon serves ("" where none)."""
    return "\n".join(
        f"error: rig {r.name!r} is served by {r.daemons} daemons on this network: both obey"
        " every request for it; stop one, or give it another [rig] name"
        for r in rigs
        if r.daemons > 1
    )


def format_rigs(rigs: list[RigInfo]) -> str:
    if not rigs:
        return "no live rigs"
    rows = [r.row() for r in rigs]
    header = {"rig": "RIG", "state": "STATE", "controller": "CONTROLLER", "fault": "FAULT"}
    cells = [header] + [{k: "-" if row[k] is None else str(row[k]) for k in header} for row in rows]
    for cell, rig in zip(cells[1:], rigs, strict=True):
        if rig.daemons > 1:
            cell["rig"] += f" (x{rig.daemons} DUPLICATE)"
    widths = {k: max(len(c[k]) for c in cells) for k in header}
    return "\n".join("  ".join(c[k].ljust(widths[k]) for k in header).rstrip() for c in cells)


def _telemetry(sub: zenoh.Subscriber) -> Iterator[tuple[str, dict[str, list[Any]]]]:
    while (sample := sub.try_recv()) is not None:
        try:
            yield rig_of(sample.key_expr), json.loads(sample.payload.to_bytes())["fields"]
        except (ValueError, KeyError, TypeError):
            continue


def watch_all(
    zenoh_config: client.ZenohConfigLike,
    duration_s: float | None = None,
    out: TextIO = sys.stdout,
) -> int:
    """One line per live rig every second, from `mrrig/*/telemetry`; a rig whose token is
    gone is dropped. Returns the number of samples received."""
    total = 0
    with client.open_session(zenoh_config) as session:
        sub = session.declare_subscriber(TELEMETRY)
        alive = session.liveliness().declare_subscriber(ALIVE, history=True)
        tokens: set[str] = set()  # a rig is live while one of its daemons' tokens is
        t0 = window_start = time.monotonic()
        window: dict[str, dict[str, list[Any]]] = {}
        try:
            while duration_s is None or time.monotonic() - t0 < duration_s:
                while (token := alive.try_recv()) is not None:
                    if token.kind == zenoh.SampleKind.PUT:
                        tokens.add(str(token.key_expr))
                    else:
                        tokens.discard(str(token.key_expr))
                live = {rig_of(t) for t in tokens}
                got = False
                for name, fields in _telemetry(sub):
                    got = True
                    for field, values in fields.items():
                        window.setdefault(name, {}).setdefault(field, []).extend(values)
                now = time.monotonic()
                if now - window_start >= 1.0:
                    for name in sorted(live | set(window)):
                        fields = window.get(name, {})
                        n = len(fields.get("t", []))
                        total += n
                        text = (
                            client.format_watch_line(n / (now - window_start), fields)
                            if n
                            else "no telemetry"
                        )
                        print(f"{name:<12} {text}", file=out)
                    if not (live or window):
                        print("no live rigs", file=out)
                    out.flush()
                    window, window_start = {}, now
                elif not got:
                    time.sleep(0.01)
        except KeyboardInterrupt:
            pass
        finally:
            alive.undeclare()
            sub.undeclare()
    return total


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="mrrig rigs", description="List the live rigs.", formatter_class=HelpFormatter
    )
    ap.add_argument(
        "--zenoh-config",
        type=Path,
        default=client.DEFAULT_CONFIG,
        help="Zenoh config reaching the rigs or their router (JSON5)",
    )
    ap.add_argument("--timeout", type=positive, default=1.0, help="seconds to wait for answers")
    ap.add_argument("--json", action="store_true", help="a JSON list instead of a table")
    args = ap.parse_args(argv)
    with client.open_session(args.zenoh_config) as session:
        rigs = live_rigs(session, args.timeout)
    if args.json:
        print(json_text.dumps([r.row() for r in rigs], indent=2))
    else:
        print(format_rigs(rigs))
    duplicates = duplicates_text(rigs)
    if duplicates:
        print(duplicates, file=sys.stderr)
        return 1
    return 0
