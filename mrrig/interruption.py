"""Which signal ended a run: Ctrl-C (SIGINT), a kill or a service manager's stop (SIGTERM), a
dropped ssh session (SIGHUP). `stops_interrupt()` turns each into an `Interrupted` (a
KeyboardInterrupt, so that whatever ends a step on Ctrl-C ends it on the others too) that
names its signal: a SIGTERM was reported as "interrupted (Ctrl-C)"."""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator

STOPS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_SAID = {
    signal.SIGINT: "Ctrl-C (SIGINT)",
    signal.SIGTERM: "SIGTERM",
    signal.SIGHUP: "SIGHUP (the terminal or ssh session closed)",
}


class Interrupted(KeyboardInterrupt):
    """A stop signal, raised where the main thread is."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(said(signum))


def said(signum: int) -> str:
    sig = signal.Signals(signum)
    return _SAID.get(sig, sig.name)


def what(exc: BaseException) -> str:
    """The signal an interruption came by, in words (a bare KeyboardInterrupt: Ctrl-C)."""
    return said(exc.signum) if isinstance(exc, Interrupted) else said(signal.SIGINT)


def _raise(signum: int, frame: object) -> None:
    raise Interrupted(signum)


@contextlib.contextmanager
def stops_interrupt() -> Iterator[None]:
    """Within: SIGINT, SIGTERM and SIGHUP raise `Interrupted`, even where this process was
    started with SIGINT ignored (a background job); the handlers before are put back after."""
    old = {sig: signal.signal(sig, _raise) for sig in STOPS}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
