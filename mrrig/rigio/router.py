"""`mrrig router --config configs/zenoh/router.json5`: the lab's Zenoh router, where the rigs'
sidecars and the desks' clients meet (a fleet: `mrrig rigs`, `--rig NAME`, `watch --all`).

A Zenoh session in router mode, open until SIGINT or SIGTERM. The `zenohd` binary does the same
from the same file (`zenohd -c configs/zenoh/router.json5`) where a lab has it. The rule of
`mrrig.rigio.zenoh_config.check_secure` holds here too: off loopback, only with authentication and
access control (or `--insecure`).
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import threading
from pathlib import Path

import zenoh

from mrrig.cli_args import HelpFormatter
from mrrig.rigio import sdnotify
from mrrig.rigio.zenoh_config import ZenohConfigError, check_secure, endpoints, load_zenoh_config

log = logging.getLogger(__name__)

DEFAULT_CONFIG = Path("configs/zenoh/router.json5")


def open_router(path: Path, insecure: bool = False) -> zenoh.Session:
    """A router-mode session from `path`, checked; one-line errors."""
    conf = load_zenoh_config(path)
    mode = json.loads(conf.get_json("mode"))
    if mode != "router":
        raise ZenohConfigError(f'{path}: mode: a router needs "router", got {mode!r}')
    for warning in check_secure(conf, str(path), insecure):
        log.warning("%s", warning)
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        raise ZenohConfigError(
            f"{path}: cannot open the router: {str(exc).splitlines()[0]}"
        ) from None
    log.info("router %s listening on %s", session.info.zid(), ", ".join(endpoints(conf)))
    return session


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="mrrig router", description=__doc__.splitlines()[0], formatter_class=HelpFormatter
    )
    ap.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="Zenoh router config")
    ap.add_argument(
        "--insecure",
        action="store_true",
        help="allow a config off loopback without authentication and access control",
    )
    args = ap.parse_args(argv)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    session = open_router(args.config, args.insecure)
    try:
        notifier = sdnotify.Notifier.from_env()
        notifier.ready()
        period = notifier.watchdog_period_s
        while not stop.wait(period if period else None):
            notifier.pet()
        notifier.stopping()
    finally:
        session.close()
    log.info("router stopped")
    return 0
