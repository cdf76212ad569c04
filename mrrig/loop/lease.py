"""The arm lease (issue 40): an arm over the control plane holds the rig only while its client
renews it; the loop disarms and stops the actuator once it lapses.

Pure bookkeeping on the loop's clock (`time.perf_counter`): the loop compares `deadline` with
its frame time once a pass (one float comparison); nothing here sends or waits.
"""

from __future__ import annotations

import math
import secrets

# the telemetry process carries the renewals: silent longer than this (its heartbeat comes
# every 0.2 s), a lapse waits for it
PATH_QUIET_S = 0.5


class ArmLease:
    """At most one lease: granted by a remote `arm`, renewed by `renew` with its id, ended by
    a disarm, a fault or its lapse. `deadline` is +inf while none is held."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.lease_id = ""
        self.deadline = math.inf

    @property
    def held(self) -> bool:
        return bool(self.lease_id)

    def grant(self, now: float) -> str:
        """The lease of an arm at `now`: the one held already (a second arm while armed holds
        the same rig) renewed, or a new one."""
        if not self.lease_id:
            self.lease_id = secrets.token_hex(8)
        self.deadline = now + self.timeout_s
        return self.lease_id

    def renew(self, lease_id: str, now: float) -> bool:
        """Extend the lease `lease_id` to `now` + timeout; False when it is not the one held
        (lapsed, ended by a disarm or fault, or never granted)."""
        if not self.lease_id or lease_id != self.lease_id:
            return False
        self.deadline = now + self.timeout_s
        return True

    def end(self) -> None:
        self.lease_id = ""
        self.deadline = math.inf

    def reply(self) -> dict[str, float | str]:
        """What a client needs to keep the lease: its id and how long a renewal lasts."""
        return {"lease": self.lease_id, "lease_timeout_s": self.timeout_s}
