"""The cap on re-arming after transport faults (issue 40), for every client that re-arms: plans
and tune (`mrrig.plans.runner`), the Python API (`mrrig.api.Rig.rearm`), the demo and the drift
bench.

A transport fault (`mrrig.loop.safety.TRANSPORT_FAULTS`: a stall of a process or of the bus)
may be acknowledged and re-armed; faults that come close together are a faulty bus, not a
stall, and re-arming them would let a step run (and pass) on a rig reset every second. At most
REARM_COUNT re-arms in any REARM_WINDOW_S seconds; one more fault ends the re-arming.
"""

from __future__ import annotations

REARM_COUNT = 3
REARM_WINDOW_S = 10.0


class RearmLimit:
    """At most `count` re-arms in any `window_s` seconds. A transport fault beyond it ends the
    re-arming for good (`ended`); `refusal` says why, as a step's abort reason."""

    def __init__(self, count: int = REARM_COUNT, window_s: float = REARM_WINDOW_S) -> None:
        self.count, self.window_s = count, window_s
        self.times: list[float] = []
        self.ended = count == 0
        self._refused_at: float | None = None

    def allows(self, now: float) -> bool:
        """Whether a transport fault at `now` (monotonic s) may be re-armed; ends it if not."""
        recent = sum(now - t < self.window_s for t in self.times)
        if not self.ended and recent >= self.count:
            self.ended, self._refused_at = True, now
        return not self.ended

    def rearmed(self, now: float) -> None:
        self.times.append(now)

    def refusal(self) -> str:
        """The reason re-arming ended: `faulty bus: N faults in S s`."""
        if self._refused_at is None:
            return f"faulty bus: re-arming is off (at most {self.count} in {self.window_s:g} s)"
        recent = [t for t in self.times if self._refused_at - t < self.window_s]
        span = self._refused_at - min(recent)
        return (
            f"faulty bus: {len(recent) + 1} faults in {span:.1f} s (re-armed at most"
            f" {self.count} times in any {self.window_s:g} s)"
        )
