"""Stop signals during a test plan (`mrrig test`): Ctrl-C, SIGTERM, SIGHUP.

The first one interrupts the step that is running (KeyboardInterrupt inside it: the step is
aborted, the rig disarmed, the rest of the plan skipped). Nothing else is interruptible: a
signal that comes while a step ends (disarm, its mark, its catalog row), between steps or
while the reports are written is only counted, and a second one (a double Ctrl-C, 50 ms
apart) is counted too, so the step's ending, the catalog rows and the JUnit and HTML reports
are always written. A signal counted outside a step interrupts the next step as it starts.

    with PlanSignals().installed() as stops:     # mrrig test, around the plan and reports
        ...
        with interruptible():                     # the runner, around the step itself
            run_step()
        if stops.received: ...

Signal handlers are the process's: so is the one PlanSignals installed (`interruptible`
without one installed interrupts as Python does by default).
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from mrrig.interruption import STOPS, Interrupted

STOP_SIGNALS = STOPS
_installed: list[PlanSignals] = []  # the one whose handlers are on, if any
_NOTE = b"\nstopping: the step's end, the catalog rows and the reports are still written\n"


class PlanSignals:
    """The plan's stop signals: `received` counts them, `first` names the first one."""

    def __init__(self) -> None:
        self.received = 0
        self.first: int | None = None  # the first signal's number
        self._interruptible = False

    def _handle(self, signum: int, _frame: Any) -> None:
        self.received += 1
        if self.first is None:
            self.first = signum
        if self.received == 1 and self._interruptible:
            self._interruptible = False  # one interruption, and only in the step
            raise Interrupted(signum)  # a KeyboardInterrupt that names its signal
        if self.received == 2:
            os.write(2, _NOTE)  # not print(): this may run inside another write to stderr

    @contextmanager
    def installed(self) -> Iterator[PlanSignals]:
        """The handlers on STOP_SIGNALS (also where this process was started with SIGINT
        ignored: a background job), the previous ones back at the end."""
        old = {sig: signal.signal(sig, self._handle) for sig in STOP_SIGNALS}
        _installed.append(self)
        try:
            yield self
        finally:
            _installed.remove(self)
            for sig, handler in old.items():
                signal.signal(sig, handler)

    @contextmanager
    def interruptible(self) -> Iterator[None]:
        """The block that the first signal interrupts (KeyboardInterrupt), at once where one
        came before it."""
        if self.first is not None:
            raise Interrupted(self.first)
        self._interruptible = True
        try:
            yield
        finally:
            self._interruptible = False


@contextmanager
def interruptible() -> Iterator[None]:
    """`PlanSignals.interruptible` of the installed PlanSignals (none: nothing changes)."""
    if not _installed:
        yield
        return
    with _installed[-1].interruptible():
        yield
