"""Opening python-can buses, and the python-can-remote bridge for kernels without CAN.

The bridge is a `python -m can_remote` server process that serves one `virtual` channel over
a WebSocket on 127.0.0.1; each process opens it with `open_bus("remote", "ws://127.0.0.1:<port>/")`.
Every client gets its own virtual bus on the server, so clients see each other's frames but,
with `receive_own_messages=False` (the default here), not their own.

can_remote does not report a dead server as a CAN error: `recv` raises `WebsocketClosed` and
`send` then silently drops frames. The remote buses opened here raise `BusError` instead.
"""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import tempfile
import time
from typing import Any

from can_remote.client import RemoteBus
from can_remote.websocket import WebsocketClosed

from mrrig.errors import MrrigError
from mrrig.pycan import can

logger = logging.getLogger(__name__)

BRIDGE_START_TIMEOUT_S = 10.0
BRIDGE_STOP_TIMEOUT_S = 3.0


class BusError(MrrigError, can.CanError):
    """A CAN bus could not be opened, or its connection was lost."""


class BusOpenError(BusError, OSError):
    """A bus that cannot be opened or served: an ordinary error of the set-up (one line, with
    what to check), not a fault of the program."""


def open_hint(interface: str, channel: str, exc: BaseException) -> str:
    """What to check when `interface`/`channel` cannot be opened."""
    if interface == "remote":
        port = channel.rstrip("/").rpartition(":")[2]
        return f"is the CAN bridge running? start it: mrrig bridge --port {port}"
    if interface == "socketcan":
        if isinstance(exc, OSError) and exc.errno == 97:  # EAFNOSUPPORT
            return (
                "this kernel has no SocketCAN: use the python-can-remote bridge"
                " (mrrig bridge, interface remote; see README)"
            )
        return (
            f"is {channel} up? sudo ip link set {channel} type can bitrate 1000000"
            f" && sudo ip link set up {channel} (ip -details link show {channel})"
        )
    return f"check the bus settings for python-can's {interface!r} interface"


class CheckedRemoteBus(RemoteBus):
    """can_remote client that raises `BusError` when the server connection is gone.

    Once `recv` has seen the connection drop, every later `send` raises too. A `send` before
    that can still vanish silently: TCP reports a dead peer only on the write after it.
    """

    def __init__(self, channel: str, **config: Any) -> None:
        self.lost_reason: str | None = None
        super().__init__(channel, **config)

    def _lost(self, exc: Exception) -> BusError:
        self.lost_reason = self.lost_reason or f"{type(exc).__name__}: {exc}"
        return BusError(f"remote CAN bus {self.channel} lost: {self.lost_reason}")

    def recv(self, timeout: float | None = None) -> can.Message | None:
        try:
            return super().recv(timeout)
        except (WebsocketClosed, OSError) as exc:
            raise self._lost(exc) from exc

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.lost_reason is not None or self.remote_protocol._ws.closed:
            raise BusError(f"remote CAN bus {self.channel} lost: {self.lost_reason or 'closed'}")
        try:
            super().send(msg, timeout)
        except OSError as exc:
            raise self._lost(exc) from exc

    def shutdown(self) -> None:
        try:
            super().shutdown()
        except (WebsocketClosed, OSError) as exc:
            # The server is already gone: there is nothing left to close politely.
            logger.debug("remote CAN bus %s closed without handshake: %s", self.channel, exc)
            can.BusABC.shutdown(self)


def open_bus(interface: str, channel: str, **kwargs: Any) -> can.BusABC:
    """Open a python-can bus; `receive_own_messages` defaults to False.

    `interface="remote"` opens a `CheckedRemoteBus`. Raises `BusError` naming the interface
    and channel if the bus cannot be opened.
    """
    kwargs.setdefault("receive_own_messages", False)
    try:
        if interface == "remote":
            return CheckedRemoteBus(channel, **kwargs)
        return can.Bus(interface=interface, channel=channel, **kwargs)
    except Exception as exc:  # python-can backends raise anything from OSError to ImportError
        raise BusOpenError(
            f"cannot open CAN bus interface={interface!r} channel={channel!r}: "
            f"{type(exc).__name__}: {exc}; {open_hint(interface, channel, exc)}"
        ) from exc


def find_free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on `host` that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]


def _port_in_use(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        try:
            sock.bind((host, port))
        except OSError:
            return True
    return False


def _accepts_connections(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


def start_bridge(
    port: int,
    channel: str = "rig",
    host: str = "127.0.0.1",
    timeout_s: float = BRIDGE_START_TIMEOUT_S,
    realtime_priority: int = 30,
) -> subprocess.Popen[bytes]:
    """Start a can_remote server serving virtual channel `channel` on ws://host:port/.

    The bridge is on the path of every frame, so it runs SCHED_FIFO `realtime_priority`
    where permitted (0: normal scheduling; a warning where not permitted). Returns once the
    server accepts connections. Raises `BusError` if the port is taken, the server exits,
    or it does not listen within `timeout_s`.
    """
    if _port_in_use(host, port):
        raise BusOpenError(
            f"CAN bridge: port {host}:{port} already in use (another bridge? pick a free one:"
            " mrrig bridge --port N)"
        )
    cmd = [
        sys.executable,
        "-m",
        "mrrig.rigio.canbus.bridge",
        "--channel",
        channel,
        "--host",
        host,
        "--port",
        str(port),
    ]
    # The server logs every connection at DEBUG: a file, never an unread pipe that fills up.
    with tempfile.TemporaryFile() as log:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=log)
        if realtime_priority:
            try:
                os.sched_setscheduler(proc.pid, os.SCHED_FIFO, os.sched_param(realtime_priority))
            except (OSError, AttributeError) as exc:
                logger.warning("CAN bridge: SCHED_FIFO not permitted (%s): normal priority", exc)
        deadline = time.monotonic() + timeout_s
        while True:
            if proc.poll() is not None:
                log.seek(0)
                tail = log.read().decode(errors="replace").strip().splitlines()[-1:]
                raise BusError(
                    f"CAN bridge on {host}:{port} exited with code {proc.returncode}: "
                    f"{tail[0] if tail else 'no output'}"
                )
            if _accepts_connections(host, port):
                break
            if time.monotonic() > deadline:
                stop_bridge(proc)
                raise BusError(f"CAN bridge on {host}:{port} not listening after {timeout_s} s")
            time.sleep(0.02)
    logger.info(
        "CAN bridge pid %d serving virtual channel %r on ws://%s:%d/", proc.pid, channel, host, port
    )
    return proc


def stop_bridge(proc: subprocess.Popen[bytes], timeout_s: float = BRIDGE_STOP_TIMEOUT_S) -> None:
    """Terminate a bridge started by `start_bridge` (kill it if it does not exit in time)."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            logger.warning("CAN bridge pid %d ignored SIGTERM, killing it", proc.pid)
            proc.kill()
            proc.wait()
