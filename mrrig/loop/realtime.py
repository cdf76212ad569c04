"""Real-time settings for the 500 Hz processes (daemon, simulator, bridge), where permitted.

SCHED_FIFO, CPU affinity, locked memory (no page fault stalls when the kernel drops file
pages) and 1 ns timer slack (select/sleep wake on time). Each is tried on its own; where one
is not permitted the process runs on with a warning.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

from mrrig.loop import memory

log = logging.getLogger(__name__)

_PR_SET_TIMERSLACK = 29
_MCL_CURRENT, _MCL_FUTURE, _MCL_ONFAULT = 1, 2, 4
_EINVAL = 22


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    return ctypes.CDLL(name, use_errno=True) if name else None


def make_realtime(
    priority: int, cpu: int | None = None, lock_memory: bool = True, who: str = "process"
) -> None:
    """Apply what is permitted; `priority` 0 keeps normal scheduling."""
    libc = _libc()
    if libc is not None:
        if libc.prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0) != 0:
            log.warning("%s: cannot set timer slack (errno %d)", who, ctypes.get_errno())
        if lock_memory and not _lock_memory(libc):
            log.warning(
                "%s: memory not locked (errno %d): page faults may stall it",
                who,
                ctypes.get_errno(),
            )
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})
        except (OSError, AttributeError) as exc:
            log.warning("%s: CPU affinity %d not set: %s", who, cpu, exc)
    if priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            log.info("%s: SCHED_FIFO priority %d", who, priority)
        except (OSError, AttributeError) as exc:
            log.warning(
                "%s: SCHED_FIFO priority %d not permitted (%s): normal scheduling",
                who,
                priority,
                exc,
            )


def _lock_memory(libc: ctypes.CDLL) -> bool:
    """Every page the process touches stays resident: locked when first touched (ONFAULT, so
    the libraries' unused pages are not), or where the kernel has no ONFAULT, all at once."""
    memory.before_locking(libc)
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE | _MCL_ONFAULT) == 0:
        return True
    return ctypes.get_errno() == _EINVAL and libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0


def keep_off_cpu(pid: int, cpu: int | None, who: str) -> None:
    """Keep process `pid` off `cpu` (the control loop's own CPU): its affinity becomes every
    other CPU this process may use. Nothing where `cpu` is None or no other CPU is left."""
    if cpu is None:
        return
    try:
        others = os.sched_getaffinity(0) - {cpu}
        if others:
            os.sched_setaffinity(pid, others)
    except (OSError, AttributeError) as exc:
        log.warning("%s: could not keep it off CPU %d: %s", who, cpu, exc)


def leave_realtime(who: str = "process") -> None:
    """Back to normal scheduling: the work of a process that has stopped its loop (summary,
    exit, the interpreter's teardown) must not starve another rig's loop on the same CPU."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError) as exc:
        log.warning("%s: could not return to normal scheduling: %s", who, exc)
