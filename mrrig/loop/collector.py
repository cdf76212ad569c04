"""The cyclic garbage collector kept off the armed frames: the daemon collects and freezes the
heap before its loop (`Daemon.run`); this turns automatic collection off while the rig is
armed (a collection triggered by allocations adds its time to whichever frame made it) and, at
each disarm, back on, after one collection of what the armed run left (between runs). The
loop allocates few containers per frame and reference counting frees them: what waits for
the collection is the rare cycle (an exception's traceback)."""

from __future__ import annotations

import gc


class CollectorOffWhileArmed:
    """`after_pass(armed)` once a pass of the loop, after the frame's command; `close()` when
    the loop ends (collection on again)."""

    def __init__(self) -> None:
        self._armed = False

    def after_pass(self, armed: bool) -> None:
        if armed == self._armed:
            return
        self._armed = armed
        if armed:
            gc.disable()
        else:
            gc.enable()
            gc.collect(0)  # with collection off, everything since the arm is still young

    def close(self) -> None:
        self._armed = False
        gc.enable()
