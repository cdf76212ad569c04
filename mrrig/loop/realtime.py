"""Real-time settings for the 500 Hz processes (daemon, simulator, bridge), where permitted.

SCHED_FIFO, CPU affinity, locked memory (no page fault stalls when the kernel drops file
pages), 1 ns timer slack (select/sleep wake on time) and a CPU wake-up latency held through
the kernel's PM QoS (idle CPUs poll rather than halt; see `hold_wakeup_latency`). Each is
tried on its own; where one is not permitted the process runs on with a warning.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import struct
import threading

from mrrig.loop import memory

log = logging.getLogger(__name__)

_PR_SET_TIMERSLACK = 29
_MCL_CURRENT, _MCL_FUTURE, _MCL_ONFAULT = 1, 2, 4
_EINVAL = 22
# PM QoS: while a process holds this open with a value written, no CPU enters an idle state
# whose exit latency exceeds that many microseconds; closing it (or exiting) releases it
WAKEUP_LATENCY_DEVICE = "/dev/cpu_dma_latency"
_wakeup_hold: int | None = None  # this process's open descriptor on the device


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    return ctypes.CDLL(name, use_errno=True) if name else None


def make_realtime(
    priority: int,
    cpu: int | None = None,
    lock_memory: bool = True,
    who: str = "process",
    wakeup_latency_us: int | None = None,
) -> None:
    """Apply what is permitted; `priority` 0 keeps normal scheduling, `wakeup_latency_us`
    None leaves the CPUs' idle states alone."""
    if wakeup_latency_us is not None:
        hold_wakeup_latency(wakeup_latency_us, who)
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


def favour_thread(nice: int, who: str) -> bool:
    """The calling thread (only) at `nice` (below 0: more of a busy CPU than the processes
    beside it, and sooner): for a thread that takes the GIL the loop needs. Preempted while it
    holds the GIL, it holds the loop up as long (a CFS slice of a busy CPU: ms). Where not
    permitted, a warning and the thread runs on as it was."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
    except (OSError, AttributeError) as exc:
        log.warning("%s: nice %d not permitted (%s)", who, nice, exc)
        return False
    return True


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


def hold_wakeup_latency(us: int, who: str = "process") -> bool:
    """Hold every CPU's wake-up latency at `us` microseconds until `leave_realtime` or exit
    (PM QoS, as cyclictest does). With 0 an idle CPU polls instead of halting. On a virtual
    machine a halted vCPU waits for the host to run it again when its timer or a frame
    wakes it: on a busy host that took 5-100 ms, the stalls that faulted the loop, and
    a polling vCPU does not wait. It costs an idle CPU's power. True where held."""
    global _wakeup_hold
    if _wakeup_hold is not None:
        os.close(_wakeup_hold)
        _wakeup_hold = None
    try:
        fd = os.open(WAKEUP_LATENCY_DEVICE, os.O_WRONLY)
    except OSError as exc:
        log.warning(
            "%s: CPU wake-up latency not held (%s: %s): idle CPUs may halt and wake late",
            who,
            WAKEUP_LATENCY_DEVICE,
            exc.strerror,
        )
        return False
    try:
        os.write(fd, struct.pack("i", us))
    except OSError as exc:
        os.close(fd)
        log.warning("%s: CPU wake-up latency %d us not held: %s", who, us, exc.strerror)
        return False
    _wakeup_hold = fd
    log.info("%s: CPU wake-up latency held at %d us (idle CPUs poll)", who, us)
    return True


def wakeup_latency_us() -> int:
    """The wake-up latency the kernel keeps now (the least any holder asked for), in us."""
    fd = os.open(WAKEUP_LATENCY_DEVICE, os.O_RDONLY)
    try:
        return struct.unpack("i", os.read(fd, 4))[0]
    finally:
        os.close(fd)


def leave_realtime(who: str = "process") -> None:
    """Back to normal scheduling and idle states: the work of a process that has stopped its
    loop (summary, exit, the interpreter's teardown) must not starve another rig's loop on
    the same CPU."""
    global _wakeup_hold
    if _wakeup_hold is not None:
        os.close(_wakeup_hold)
        _wakeup_hold = None
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError) as exc:
        log.warning("%s: could not return to normal scheduling: %s", who, exc)
