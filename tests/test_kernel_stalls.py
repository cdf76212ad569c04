"""The daemon's own stalls as the kernel measures them (mrrig/loop/kernel_stalls.py): the
windows from made-up readings, the reader on a thread that really waits on a run queue, and
the daemon's summary read back against the loop thread's schedstat."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from mrrig.loop.kernel_stalls import (
    KernelStalls,
    ProcReader,
    format_stalls,
    parse_run_delay_ns,
    parse_steal_ticks,
    schedstat_path,
    stall_event,
)
from mrrig.loop.samples import SAMPLE_DTYPE
from mrrig.loop.summary import format_summary, summarize
from mrrig.rigio.rig_session import RigSession
from tests.rig_harness import ThreadRig

MS = 1_000_000  # ns


def test_the_fields_are_the_run_queue_delay_and_the_steal():
    assert parse_run_delay_ns(b"22017158 52281352 9\n") == 52281352
    assert parse_steal_ticks(b"cpu  31913 3 5725 37531 462 0 161 35 0 0\ncpu0 1 2 3\n") == 35


def test_a_pass_that_lost_two_ms_or_more_is_a_window_and_the_totals_span_the_run():
    k = KernelStalls(period_s=0.002)
    k.add(0.000, 50 * MS, 7)
    assert k.add(0.002, 50 * MS + 300_000, None) is None  # 0.3 ms: no window
    assert k.add(0.018, 64 * MS + 500_000, 7) == [0.002, 0.018, pytest.approx(14.2), 0.0, 0.0]
    assert k.add(0.020, 65 * MS, None) is None
    r = k.result()
    assert r["windows"] == [[0.002, 0.018, pytest.approx(14.2), 0.0, 0.0]]
    assert r["runq_total_ms"] == pytest.approx(15.0) and r["runq_max_ms"] == pytest.approx(14.2)
    assert r["run_delay_ns_first_last"] == [50 * MS, 65 * MS] and r["span_s"] == [0.0, 0.020]
    assert "the largest 14.2 ms in [0.002, 0.018] s" in format_summary(
        summarize(_no_samples(), [], {}) | {"kernel_stalls": r}
    )
    assert "14.2 ms on the run queue" in stall_event(r["windows"][0])["text"]


def test_steal_is_credited_at_most_the_length_of_its_pass():
    """A 10 ms tick that falls into a 2 ms pass is not a 10 ms stall."""
    k = KernelStalls(period_s=0.002)
    k.add(1.000, 0, 100)
    w = k.add(1.002, 0, 101)
    assert w == [1.000, 1.002, 0.0, pytest.approx(2.0), 0.0]
    assert k.add(1.016, 0, 102) == [1.002, 1.016, 0.0, pytest.approx(10.0), 0.0]
    assert k.result()["steal_total_ms"] == pytest.approx(20.0)  # the counter's own total


def test_another_python_threads_run_queue_delay_is_credited_at_most_its_pass():
    """The loop needs the GIL: another thread that waited on a run queue (holding it, maybe)
    held the loop up as long. The largest of their delays since the previous read, at most
    the pass's length; a thread new since then counts from its first reading."""
    k = KernelStalls(period_s=0.002)
    k.add(1.000, 0, 0, {11: 5 * MS})
    assert k.add(1.002, 0, None) is None  # not read this pass
    w = k.add(1.014, 0, 0, {11: 14 * MS, 12: 900 * MS})  # 12: new, no delay credited
    assert w == [1.002, 1.014, 0.0, 0.0, pytest.approx(9.0)]
    w = k.add(1.017, 0, 0, {11: 30 * MS, 12: 901 * MS})  # 16 ms waited, a 3 ms pass
    assert w == [1.014, 1.017, 0.0, 0.0, pytest.approx(3.0)]
    assert k.add(1.019, 0, 0, {12: 901 * MS}) is None  # 11 ended
    r = k.result()
    assert r["others_total_ms"] == pytest.approx(12.0) and r["others_max_ms"] == pytest.approx(9)
    line = format_summary(summarize(_no_samples(), [], {}) | {"kernel_stalls": r})
    assert "other threads 12.0 ms (max 9.0 ms)" in line and "the largest 9.0 ms" in line
    assert (
        "another of its threads (the GIL's holder?) 9.0 ms" in stall_event(r["windows"][0])["text"]
    )


def test_a_recording_made_before_the_other_threads_were_measured_still_reads():
    old = {
        "measured": True, "runq_total_ms": 14.2, "runq_max_ms": 14.2, "steal_total_ms": 0.0,
        "steal_max_ms": 0.0, "window_min_ms": 2.0, "windows_count": 1,
        "windows": [[0.002, 0.018, 14.2, 0.0]],
    }  # fmt: skip
    assert "the largest 14.2 ms in [0.002, 0.018] s" in format_stalls(old)
    assert "14.2 ms on the run queue and lost 0 ms" in stall_event(old["windows"][0])["text"]


def test_the_reader_reads_the_other_python_threads_of_its_process():
    """Each other thread of the process that runs Python is read by its native id (the
    reader's own thread left out); a thread that ended is dropped."""
    go, done = threading.Event(), threading.Event()
    t = threading.Thread(target=lambda: (go.set(), done.wait(5)), daemon=True)
    t.start()
    go.wait(5)
    r = ProcReader()
    try:
        got = r.others_run_delay_ns()
        assert t.native_id in got and threading.get_native_id() not in got
        assert 0 <= got[t.native_id] <= _run_delay_ns(t.native_id)  # its own count, cumulative
        done.set()
        t.join(5)
        assert t.native_id not in r.others_run_delay_ns()
    finally:
        done.set()
        r.close()


def test_the_summary_lists_the_largest_windows_and_counts_all():
    k = KernelStalls(period_s=0.002, max_windows=3)
    k.add(0.0, 0, 0)
    runq = 0
    for i, ms in enumerate([3, 9, 2, 7, 4, 8]):
        runq += ms * MS
        k.add(0.01 * (i + 1), runq, None)
    r = k.result()
    assert [round(w[2]) for w in r["windows"]] == [9, 7, 8]  # by time
    assert r["windows_count"] == 6 and r["windows_not_listed"] == 3


def test_the_steal_is_read_after_a_late_pass_and_every_so_many_passes(monkeypatch):
    reads = []
    k = KernelStalls(period_s=0.002)
    k.start(0.0)
    monkeypatch.setattr(k._reader, "steal_ticks", lambda: reads.append(1) or 0)
    for i in range(1, 10):
        k.read(0.002 * i)
    assert not reads
    k.read(0.002 * 9 + 0.005)  # a late pass
    assert len(reads) == 1
    for i in range(50):
        k.read(0.1 + 0.002 * i)
    assert len(reads) == 2
    k.stop(0.3)
    assert len(reads) == 3


@pytest.mark.process
def test_the_reader_sees_its_thread_wait_on_a_run_queue(tmp_path):
    """This thread and a busy process on one CPU: the kernel counts the time this thread
    waited for it, and the reader reads this thread's count (not the process's)."""
    cpu = min(os.sched_getaffinity(0))
    old = os.sched_getaffinity(0)
    spin = f"import os, time\nos.sched_setaffinity(0, {{{cpu}}})\ne = time.time() + 1.5\n"
    busy = subprocess.Popen([sys.executable, "-c", spin + "while time.time() < e: pass"])
    try:
        time.sleep(0.2)
        os.sched_setaffinity(0, {cpu})  # this thread only
        k = KernelStalls()
        k.start(0.0)
        before = _run_delay_ns(threading.get_native_id())
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            sum(range(1000))
            k.read(time.monotonic())
        after = _run_delay_ns(threading.get_native_id())
        k.stop(time.monotonic())
    finally:
        os.sched_setaffinity(0, old)
        busy.wait()
    r = k.result()
    first, last = r["run_delay_ns_first_last"]
    assert first <= before < after <= last, (first, before, after, last)
    assert r["runq_total_ms"] >= (after - before) * 1e-6 > 0
    print(f"waited {r['runq_total_ms']:.1f} ms on the run queue in 0.5 s beside a busy process")


@pytest.mark.process
def test_the_daemons_summary_carries_its_loop_threads_run_queue_delay(tmp_path):
    """A real loop (in-process, on the simulator's virtual bus): the loop thread's schedstat,
    read by this test while it runs, lies between the summary's first and last readings, and
    the summary's total is their difference."""
    with ThreadRig() as rig:
        cfg = rig.daemon_config(tmp_path, controller={"name": "constant", "current_a": 0.5})
        with RigSession(cfg) as session:
            tid = session.loop._thread.native_id
            before = _run_delay_ns(tid)
            session.request(cmd="arm")
            time.sleep(1.0)
            after = _run_delay_ns(tid)
        k = session.loop.daemon.summary["kernel_stalls"]
    print(format_summary(session.loop.daemon.summary).splitlines()[-2:])
    assert k["measured"], k
    first, last = k["run_delay_ns_first_last"]
    assert 0 <= first <= before <= after <= last, (first, before, after, last)
    assert k["runq_total_ms"] == pytest.approx((last - first) * 1e-6, abs=1e-6)
    assert k["runq_total_ms"] >= (after - before) * 1e-6
    assert k["steal_total_ms"] >= 0 and k["runq_max_ms"] >= 0 and k["steal_max_ms"] >= 0
    t0, t1 = k["span_s"]
    for a, b, runq, steal, others in k["windows"]:
        assert t0 <= a < b <= t1 and min(runq, steal, others) >= 0
        assert runq + steal + others >= 2.0
    assert sum(w[2] for w in k["windows"]) <= k["runq_total_ms"] + 1e-6


def _run_delay_ns(tid: int) -> int:
    with open(schedstat_path(tid), "rb") as f:
        return parse_run_delay_ns(f.read())


def _no_samples() -> np.ndarray:
    return np.zeros(0, dtype=SAMPLE_DTYPE)


def test_the_reader_refuses_a_thread_that_is_not_there():
    with pytest.raises(OSError):
        ProcReader(tid=2**31 - 1)
