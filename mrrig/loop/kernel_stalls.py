"""The daemon's own stalls as the kernel measured them: how long the loop thread waited on a
run queue, how long the process's other Python threads did, and how much time the hypervisor
stole from this VM, between two passes of the loop.

- Run-queue delay: `/proc/self/task/TID/schedstat` of the loop thread, its second field: the
  nanoseconds the thread has waited runnable while another task had its CPU.
- The other Python threads' run-queue delay (the control thread, a tool's pipe server): the
  loop needs the GIL for each frame, and a thread that holds it while it waits on a run queue
  holds the loop up as long (the loop's own schedstat shows a sleep). The largest of their
  delays since the previous such read, credited at most the pass's length, read with the steal.
- Steal: `/proc/stat`'s `cpu` line (all CPUs), its 8th value: the time the hypervisor ran
  something else while this VM's vCPUs were runnable, in USER_HZ ticks (10 ms at 100 Hz). A
  pass is credited at most its own length of it: one tick can fall into a 2 ms pass.

The loop reads them after each frame's command is sent (off the latency path), with `os.pread`
on descriptors kept open (no open or close per frame): the schedstat every pass (about 2 us),
/proc/stat (7-13 us here: the kernel formats every CPU's line and the interrupt counts) only
after a late pass (one period plus `WINDOW_MIN_MS` or longer: what steal that held the loop
up makes) and every `STEAL_EVERY` passes, so that a late pass is credited the steal since
that read at most (the other threads' delay likewise). `KernelStalls` keeps in fixed memory
the totals, the largest pass and the passes in which the three together reach `WINDOW_MIN_MS`:
`[t_start, t_end, runq_ms, steal_ms, others_ms]` on the daemon's clock (the previous read, this
read), the `MAX_WINDOWS` largest listed and all of them counted (recordings made before the
other threads were measured list four values).
"""

from __future__ import annotations

import heapq
import logging
import math
import os
import threading
from typing import Any

log = logging.getLogger(__name__)

# a pass of the loop that lost this much to the run queue and steal together is a window
WINDOW_MIN_MS = 2.0
# the summary lists this many windows (the largest); the count is of all of them
MAX_WINDOWS = 256
# /proc/stat is read at least once in this many passes (0.1 s at 500 Hz)
STEAL_EVERY = 50
_STEAL_FIELD = 8  # in the `cpu` line, after the name


def schedstat_path(tid: int | None = None) -> str:
    """The schedstat file of thread `tid` of this process (the calling thread by default)."""
    return f"/proc/self/task/{threading.get_native_id() if tid is None else tid}/schedstat"


def parse_run_delay_ns(raw: bytes) -> int:
    """The second field of a schedstat line: ns waited on a run queue."""
    return int(raw.split(None, 2)[1])


def parse_steal_ticks(raw: bytes) -> int:
    """The 8th value of /proc/stat's first line (`cpu  user nice system idle iowait irq
    softirq steal ...`): USER_HZ ticks stolen from all CPUs."""
    return int(raw.split(None, _STEAL_FIELD + 1)[_STEAL_FIELD])


class ProcReader:
    """The calling thread's run-queue delay and the machine's steal, read through descriptors
    kept open. Raises OSError where the files are not there (no Linux /proc, no schedstat)."""

    def __init__(self, tid: int | None = None) -> None:
        self.tid = threading.get_native_id() if tid is None else tid
        self._others: dict[int, int] = {}  # the other threads' schedstat descriptors
        self._sched = os.open(schedstat_path(tid), os.O_RDONLY)
        try:
            self._stat = os.open("/proc/stat", os.O_RDONLY)
        except OSError:
            os.close(self._sched)
            raise
        self.tick_ms = 1e3 / os.sysconf("SC_CLK_TCK")
        self.run_delay_ns(), self.steal_ticks()  # both parse here, not first in the loop

    def run_delay_ns(self) -> int:
        """The thread's cumulative run-queue delay."""
        return parse_run_delay_ns(os.pread(self._sched, 128, 0))

    def steal_ticks(self) -> int:
        """The machine's cumulative steal."""
        return parse_steal_ticks(os.pread(self._stat, 256, 0))

    def others_run_delay_ns(self) -> dict[int, int]:
        """The cumulative run-queue delay of this process's other Python threads (by native
        id; a thread that ended in between is left out, and its descriptor closed)."""
        out: dict[int, int] = {}
        for t in threading.enumerate():
            tid = t.native_id
            if tid is None or tid == self.tid:
                continue
            fd = self._others.get(tid)
            try:
                if fd is None:
                    fd = self._others[tid] = os.open(schedstat_path(tid), os.O_RDONLY)
                out[tid] = parse_run_delay_ns(os.pread(fd, 128, 0))
            except (OSError, ValueError, IndexError):
                continue
        for tid in set(self._others) - set(out):
            os.close(self._others.pop(tid))
        return out

    def close(self) -> None:
        os.close(self._sched)
        os.close(self._stat)
        for fd in self._others.values():
            os.close(fd)
        self._others.clear()


class KernelStalls:
    """The loop's stalls from cumulative readings taken once per pass (`add`, pure), or from
    a `ProcReader` of the loop thread (`start` in that thread, `read` per pass, `stop`)."""

    def __init__(
        self,
        period_s: float = 0.002,
        min_ms: float = WINDOW_MIN_MS,
        max_windows: int = MAX_WINDOWS,
    ) -> None:
        self.min_ms, self.max_windows = min_ms, max_windows
        self.late_s = period_s + min_ms * 1e-3  # a pass this long reads the steal
        self.tick_ms = 10.0
        self.unavailable = ""  # why nothing was measured, where nothing was
        self._reader: ProcReader | None = None
        self._first: tuple[float, int, int] | None = None  # t, run delay ns, steal ticks
        self._last_t, self._runq_ns = math.nan, 0  # the previous pass
        self._steal, self._passes_unread = 0, 0  # the latest steal read, passes since
        self._others_ns: dict[int, int] = {}  # the other threads' delay at the latest read
        self.others_total_ms = 0.0
        self.runq_max_ms = self.steal_max_ms = self.others_max_ms = 0.0  # of one pass
        self.windows = 0
        self._largest: list[tuple[float, int, list[float]]] = []  # a min-heap by stall ms

    # ---- I/O: the loop thread's readings ---------------------------------------------------
    def start(self, t_s: float) -> None:
        """Open the calling thread's files (the loop thread's) and take the first reading."""
        try:
            self._reader = ProcReader()
        except (OSError, ValueError, IndexError) as exc:
            self.unavailable = f"{schedstat_path()} or /proc/stat: {exc}"
            log.warning("the loop's stalls are not measured (%s)", self.unavailable)
            return
        self.tick_ms = self._reader.tick_ms
        r = self._reader
        self.add(t_s, r.run_delay_ns(), r.steal_ticks(), r.others_run_delay_ns())

    def read(self, t_s: float, last: bool = False) -> list[float] | None:
        """One pass's reading at daemon time `t_s`; the window it closes, if it was one."""
        r = self._reader
        if r is None:
            return None
        runq_ns = r.run_delay_ns()
        self._passes_unread += 1
        read_steal = last or t_s - self._last_t >= self.late_s
        if not (read_steal or self._passes_unread >= STEAL_EVERY):
            return self.add(t_s, runq_ns, None)
        return self.add(t_s, runq_ns, r.steal_ticks(), r.others_run_delay_ns())

    def stop(self, t_s: float) -> None:
        """The last reading; the files closed."""
        if self._reader is not None:
            self.read(t_s, last=True)
            self._reader.close()
            self._reader = None

    # ---- pure: the readings ---------------------------------------------------------------
    def add(
        self,
        t_s: float,
        runq_ns: int,
        steal_ticks: int | None,
        others_ns: dict[int, int] | None = None,
    ) -> list[float] | None:
        """Cumulative readings at `t_s` (`steal_ticks`, `others_ns` None: not read this pass);
        returns `[t_start, t_end, runq_ms, steal_ms, others_ms]` where the pass since the
        previous reading lost `min_ms` or more. Steal and the other threads' delay (the largest
        of theirs since the previous read) are credited where read, at most the pass's length."""
        if self._first is None:
            self._first = (t_s, runq_ns, 0 if steal_ticks is None else steal_ticks)
            self._last_t, self._runq_ns, self._steal = self._first
            self._others_ns = dict(others_ns or {})
            return None
        t_prev, self._last_t = self._last_t, t_s
        pass_ms = max(t_s - t_prev, 0) * 1e3
        runq_ms = (runq_ns - self._runq_ns) * 1e-6
        self._runq_ns = runq_ns
        steal_ms = others_ms = 0.0
        if steal_ticks is not None:
            steal_ms = min((steal_ticks - self._steal) * self.tick_ms, pass_ms)
            self._steal, self._passes_unread = steal_ticks, 0
        if others_ns is not None:
            # a thread new since the last read (or a reused id) counts from now
            waited = [ns - self._others_ns.get(tid, ns) for tid, ns in others_ns.items()]
            others_ms = min(max([0, *waited]) * 1e-6, pass_ms)
            self._others_ns = dict(others_ns)
            self.others_total_ms += others_ms
        self.runq_max_ms = max(self.runq_max_ms, runq_ms)
        self.steal_max_ms = max(self.steal_max_ms, steal_ms)
        self.others_max_ms = max(self.others_max_ms, others_ms)
        if runq_ms + steal_ms + others_ms < self.min_ms:
            return None
        window = [t_prev, t_s, runq_ms, steal_ms, others_ms]
        item = (runq_ms + steal_ms + others_ms, self.windows, window)
        self.windows += 1
        if len(self._largest) < self.max_windows:
            heapq.heappush(self._largest, item)
        else:
            heapq.heappushpop(self._largest, item)
        return window

    def result(self) -> dict[str, Any]:
        """For the summary: totals over the loop's run, the largest pass, the windows (by
        time), and the thread's cumulative run-queue delay at the first and last reading."""
        if self._first is None:
            return {"measured": False, "why": self.unavailable or "the loop never ran"}
        t0, runq0, steal0 = self._first
        # a copy first: a tool asks for this while the loop runs (RigSession.kernel_stalls)
        listed = sorted((w for _, _, w in list(self._largest)), key=lambda w: w[0])
        return {
            "measured": True,
            "span_s": [t0, self._last_t],
            "runq_total_ms": (self._runq_ns - runq0) * 1e-6,
            "runq_max_ms": self.runq_max_ms,
            "steal_total_ms": (self._steal - steal0) * self.tick_ms,
            "steal_max_ms": self.steal_max_ms,
            "others_total_ms": self.others_total_ms,
            "others_max_ms": self.others_max_ms,
            "window_min_ms": self.min_ms,
            "windows_count": self.windows,
            "windows": listed,
            "windows_not_listed": self.windows - len(listed),
            "run_delay_ns_first_last": [runq0, self._runq_ns],
        }


def lost_ms(window: list[float]) -> float:
    """What a window's pass lost: run queue, steal and the other threads' run queue (four
    values in recordings made before the other threads were measured)."""
    return sum(window[2:5])


def shortened(k: dict[str, Any], n: int) -> dict[str, Any]:
    """A summary's `kernel_stalls` listing only its `n` largest windows (by time)."""
    ws = sorted(k["windows"], key=lost_ms)[max(len(k["windows"]) - n, 0) :]
    ws.sort(key=lambda w: w[0])
    return {**k, "windows": ws, "windows_not_listed": k["windows_count"] - len(ws)}


def stall_event(window: list[float]) -> dict[str, Any]:
    """A window as an event of the recording (kind `kernel_stall`)."""
    a, b, runq_ms, steal_ms = window[:4]
    others = (
        f", another of its threads (the GIL's holder?) {window[4]:.1f} ms"
        if len(window) > 4 and window[4]
        else ""
    )
    return {
        "t": b,
        "level": "info",
        "text": (
            f"the loop waited {runq_ms:.1f} ms on the run queue{others} and lost"
            f" {steal_ms:.0f} ms to the VM's steal in [{a:.3f}, {b:.3f}] s"
        ),
        "kind": "kernel_stall",
        "window": window,
    }


def format_stalls(k: dict[str, Any]) -> str:
    """One line for the printed summary."""
    if not k.get("measured"):
        return f"not measured ({k.get('why', '')})"
    others = (
        f", other threads {k['others_total_ms']:.1f} ms (max {k['others_max_ms']:.1f} ms)"
        if "others_total_ms" in k
        else ""
    )
    line = (
        f"run queue {k['runq_total_ms']:.1f} ms (max {k['runq_max_ms']:.1f} ms a pass),"
        f" steal {k['steal_total_ms']:.0f} ms (max {k['steal_max_ms']:.1f} ms){others};"
        f" {k['windows_count']} passes over {k['window_min_ms']:g} ms"
    )
    if k["windows"]:
        w = max(k["windows"], key=lost_ms)
        line += f", the largest {lost_ms(w):.1f} ms in [{w[0]:.3f}, {w[1]:.3f}] s"
    return line
