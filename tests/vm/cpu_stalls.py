"""A CPU's stalls, measured inside the VM (tests/vm/rig_on_vcan.sh): a SCHED_FIFO thread pinned
to the CPU sleeps 1 ms at a time and records each wake-up later than LATE_S as a window
[when it should have woken, when it did] on CLOCK_MONOTONIC. Nothing of the guest's own keeps
a thread of that priority off its CPU that long; under software emulation the host stops a
virtual CPU now and then (its thread descheduled), and a process on that CPU stands still for
as long without waiting on the guest kernel's run queue, so the daemon's kernel-measured
stalls do not show it. Writes `{"clock_t0_s": 0, "stall_windows": [...]}` at SIGTERM.

    python tests/vm/cpu_stalls.py CPU OUT_JSON
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time

PERIOD_S = 0.001
LATE_S = 0.005  # the simulator's RunStats.LATE_S: a window opens at this lateness
PRIORITY = 90  # above the daemon's loop (50) and the simulator (20)


def main(cpu: int, out: str) -> int:
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(PRIORITY))
    windows: list[dict] = []
    stop = []
    signal.signal(signal.SIGTERM, lambda _s, _f: stop.append(1))
    due = time.monotonic() + PERIOD_S
    while not stop:
        time.sleep(max(due - time.monotonic(), 0.0))
        now = time.monotonic()
        if now - due >= LATE_S:
            windows.append({"kind": f"cpu{cpu}", "start_s": due, "end_s": now})
        due = max(due + PERIOD_S, now + PERIOD_S / 2)
    with open(out, "w") as fh:
        json.dump({"clock_t0_s": 0.0, "stall_windows": windows}, fh)
    print(f"cpu_stalls: CPU {cpu}: {len(windows)} stalls of {LATE_S * 1e3:g} ms or more")
    return 0


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]), sys.argv[2]))
