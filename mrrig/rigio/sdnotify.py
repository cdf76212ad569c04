"""systemd's notify protocol, plainly: datagrams to $NOTIFY_SOCKET (`Type=notify` units).

`READY=1` once the service serves, `WATCHDOG=1` at half of `WatchdogSec` (systemd passes it as
$WATCHDOG_USEC) from the loop that must stay alive, `STOPPING=1` on the way out. Every send is
non-blocking and never raises: a full or absent socket costs a dropped message, never a stalled
loop. Without $NOTIFY_SOCKET (not under systemd) every call does nothing.
"""

from __future__ import annotations

import logging
import os
import socket
import time

log = logging.getLogger(__name__)


class Notifier:
    """One process's notifications; `pet(now)` is cheap enough to call every loop turn."""

    def __init__(self, address: str | None, watchdog_usec: int | None = None) -> None:
        self._sock: socket.socket | None = None
        self._address = ""
        if address:
            # "@name" is Linux's abstract namespace: a leading NUL byte
            self._address = "\0" + address[1:] if address.startswith("@") else address
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)
        # systemd's advice: pet at half the watchdog interval
        self.watchdog_period_s = watchdog_usec / 2e6 if watchdog_usec and self._sock else None
        self._next_pet = -float("inf")
        self.dropped = 0

    @classmethod
    def from_env(cls) -> Notifier:
        """From $NOTIFY_SOCKET, $WATCHDOG_USEC and $WATCHDOG_PID (the watchdog is this
        process's only when WATCHDOG_PID is absent or its pid)."""
        address = os.environ.get("NOTIFY_SOCKET")
        usec_text = os.environ.get("WATCHDOG_USEC", "")
        pid_text = os.environ.get("WATCHDOG_PID", "")
        usec = int(usec_text) if usec_text.isdigit() and int(usec_text) > 0 else None
        if pid_text and pid_text != str(os.getpid()):
            usec = None
        return cls(address, usec)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def send(self, message: str) -> bool:
        if self._sock is None:
            return False
        try:
            self._sock.sendto(message.encode(), self._address)
            return True
        except OSError as exc:  # BlockingIOError (full), ENOENT/ECONNREFUSED (no listener)
            self.dropped += 1
            if self.dropped == 1:
                log.warning("systemd notification %r not sent: %s", message, exc)
            return False

    def ready(self, status: str | None = None) -> None:
        self.send("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def stopping(self) -> None:
        self.send("STOPPING=1")

    def status(self, text: str) -> None:
        self.send(f"STATUS={text}")

    def pet(self, now: float | None = None) -> None:
        """WATCHDOG=1 when half the watchdog interval has passed since the last one; `now`
        on any monotonic clock in s (the loop's own, to save a clock read)."""
        if self.watchdog_period_s is None:
            return
        now = time.monotonic() if now is None else now
        if now >= self._next_pet:
            self._next_pet = now + self.watchdog_period_s
            self.send("WATCHDOG=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
