"""The daemon's resident memory: what the loop needs, locked, and measured.

`mlockall(MCL_CURRENT | MCL_FUTURE)` made every page of every mapping resident: every shared
library whole (numpy's and scipy's OpenBLAS, zenoh's), a 32 MB buffer per OpenBLAS instance
and a thread of each per core, each thread's full 8 MB stack. `MCL_ONFAULT` (Linux 4.4) locks
a page when it is first touched instead, so what is locked is what the process uses; one BLAS
thread (the loop's products are 30 x 4: a second thread only adds a buffer, a stack and a
wake-up), two malloc arenas and small thread stacks keep the rest small. Numbers: README,
"Memory".
"""

from __future__ import annotations

import ctypes
import logging
import os
import threading
from pathlib import Path

log = logging.getLogger(__name__)

# read by OpenBLAS when numpy loads it: set before the daemon's process imports numpy
ENVIRONMENT = {"OPENBLAS_NUM_THREADS": "1", "MALLOC_ARENA_MAX": "2"}
THREAD_STACK_BYTES = 512 * 1024
_M_ARENA_MAX = -8  # glibc mallopt
_ARENAS = 2


def set_environment() -> None:
    """ENVIRONMENT for this process (before numpy is imported) and its children; a value the
    user set wins."""
    for key, value in ENVIRONMENT.items():
        os.environ.setdefault(key, value)


def before_locking(libc: ctypes.CDLL | None) -> None:
    """Limit what locking makes resident: malloc arenas, and the stacks of threads started
    from here on."""
    if libc is not None and hasattr(libc, "mallopt"):
        if libc.mallopt(_M_ARENA_MAX, _ARENAS) != 1:
            log.warning("could not limit malloc arenas to %d", _ARENAS)
    threading.stack_size(THREAD_STACK_BYTES)


def status_kib(pid: int | str = "self") -> dict[str, int]:
    """VmRSS, VmLck, VmHWM (kB) and Threads of a process, from /proc (Linux); {} elsewhere."""
    out: dict[str, int] = {}
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return out
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmLck", "VmHWM", "Threads"):
            out[key] = int(value.split()[0])
    return out
