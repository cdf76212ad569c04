"""`mrrig bridge`: a virtual CAN channel served to other processes on 127.0.0.1.

The python-can-remote server (one thread per client direction in one interpreter), with its
memory locked and garbage collection frozen after start-up, and a clean exit on SIGTERM.
"""

from __future__ import annotations

import argparse
import errno
import gc
import logging
import signal
import sys

from mrrig.cli_args import HelpFormatter, port

log = logging.getLogger(__name__)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="mrrig bridge", description=__doc__.splitlines()[0], formatter_class=HelpFormatter
    )
    ap.add_argument("--port", type=port, default=54701, help="TCP port of ws://HOST:PORT/")
    ap.add_argument("-c", "--channel", default="rig", help="virtual channel name")
    ap.add_argument("--host", default="127.0.0.1", help="listen address (loopback only)")
    args = ap.parse_args(argv)
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        raise ValueError(f"--host {args.host}: the bridge serves loopback only")
    from can_remote.server import RemoteServer

    from mrrig.loop.realtime import leave_realtime, make_realtime

    logging.getLogger("can").setLevel(logging.WARNING)
    try:
        server = RemoteServer(args.host, args.port, channel=args.channel, bustype="virtual")
    except OSError as exc:
        hint = ""
        if exc.errno == errno.EADDRINUSE:
            hint = " (another bridge there? pick a free port: mrrig bridge --port N)"
        raise OSError(
            f"cannot serve ws://{args.host}:{args.port}/: {exc.strerror or exc}{hint}"
        ) from exc
    # client threads must not hold the exit: server_close() would join them
    server.daemon_threads = True
    server.block_on_close = False
    signal.signal(signal.SIGTERM, _interrupt)
    make_realtime(0, who="bridge")  # locked memory; start_bridge sets its priority
    gc.collect()
    gc.freeze()
    log.info("bridge: virtual channel %r on ws://%s:%d/", args.channel, args.host, args.port)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
        leave_realtime("bridge")  # its exit must not starve another rig's bridge
    return 0


if __name__ == "__main__":
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    sys.exit(main())
