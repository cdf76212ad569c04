"""How long a received frame waited before the loop read it, by its bus receive timestamp (the
kernel's on SocketCAN, the bridge's on the Python bridge; both time.time()), and the backlog
queued while the daemon started, dropped before its loop runs."""

from __future__ import annotations

import logging
import time

log = logging.getLogger(__name__)

CLOCK_SANE_S = 60.0  # a frame timestamp further off than this is not on this machine's clock


class FrameAge:
    """`queued_s(msg)`: a frame's wait at the bus; a timestamp on another clock is warned of
    once, and counts as no wait."""

    def __init__(self) -> None:
        self._clock_warned = False

    def queued_s(self, msg) -> float:
        """How long ago the bus received `msg` (its timestamp: the kernel's on SocketCAN, the
        bridge's on the Python bridge; both time.time())."""
        q = time.time() - msg.timestamp
        if 0.0 <= q < CLOCK_SANE_S:
            return q
        if -CLOCK_SANE_S < q < 0.0:
            return 0.0  # stamped a hair in our future: the two clocks' reads, not an age
        if not self._clock_warned:
            self._clock_warned = True
            log.warning(
                "frame timestamps are not on this machine's clock (%.0f s off): frame age "
                "is measured from the loop's read only",
                q,
            )
        return 0.0

    def discard_backlog(self, bus, limit_s: float) -> None:
        """Drop the frames queued while the daemon started: the rig has moved on. Up to the
        first one that is no older than `limit_s` (`max_frame_age_s`): a bridge that delivers
        a long backlog barely faster than the rig sends would otherwise keep this going for as
        long again."""
        stale = 0
        while (msg := bus.recv(timeout=0)) is not None:
            stale += 1
            if self.queued_s(msg) <= limit_s:
                break
        if stale:
            log.info("discarded %d frames queued before the loop started", stale)
