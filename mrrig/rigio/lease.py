"""A client's hold on an armed rig (issue 40): the lease an `arm` answered, renewed in the
background while the client holds the rig.

The daemon disarms and stops the actuator when a lease goes unrenewed for its
`lease_timeout_s` (`mrrig.loop.lease`): a client killed while armed leaves no rig stroking.
Every client that arms over Zenoh (`mrrig test`, `mrrig tune`, `mrrig.api.Rig`,
`mrrig send-force`, `mrrig demo`, `mrrig arm --hold`) keeps its lease with one `Lease`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

# renewals a lease's timeout: three may be lost or late before it lapses
RENEWALS_PER_TIMEOUT = 4
# a request that asks for a reply: (payload, timeout_s) -> the daemon's reply
Ask = Callable[[dict[str, Any], float], dict[str, Any]]


class Lease:
    """Renews the lease of an arm's `reply` every timeout / RENEWALS_PER_TIMEOUT in a daemon
    thread, until `release` or until the daemon refuses a renewal (then `lost` says why: the
    rig faulted or was disarmed, or the lease lapsed). A renewal that gets no answer is tried
    again at the next period."""

    def __init__(self, ask: Ask, reply: dict[str, Any], rig: str = "") -> None:
        self.lease_id = str(reply["lease"])
        self.timeout_s = float(reply["lease_timeout_s"])
        self.rig = rig
        self.lost = ""
        self.renewals = 0
        self._ask = ask
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"mrrig-lease-{rig}", daemon=True)
        self._thread.start()

    @classmethod
    def of(cls, ask: Ask, reply: dict[str, Any], rig: str = "") -> Lease | None:
        """The lease of an arm's reply, held; None when the reply names none (a refused arm,
        an in-process daemon)."""
        if not reply.get("ok") or "lease" not in reply:
            return None
        return cls(ask, reply, rig)

    @property
    def held(self) -> bool:
        return not self._stop.is_set() and not self.lost

    def _run(self) -> None:
        period_s = self.timeout_s / RENEWALS_PER_TIMEOUT
        while not self._stop.wait(period_s):
            try:
                reply = self._ask({"cmd": "renew", "lease": self.lease_id}, self.timeout_s / 2)
            except Exception as exc:  # noqa: BLE001 - no answer now: renewed at the next period
                log.warning("rig %s: lease renewal unanswered (trying again): %s", self.rig, exc)
                continue
            if not reply.get("ok"):
                if not self._stop.is_set():
                    self.lost = str(reply.get("error"))
                    log.warning("rig %s: lease no longer held: %s", self.rig, self.lost)
                return
            self.renewals += 1

    def release(self) -> None:
        """Stop renewing (after a disarm, or at the client's end: the daemon then disarms
        and stops the actuator once the lease lapses)."""
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=self.timeout_s)
