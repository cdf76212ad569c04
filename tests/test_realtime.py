"""The loop's CPU: other processes of the rig are kept off it; idle CPUs poll while it runs."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from mrrig.loop.realtime import (
    WAKEUP_LATENCY_DEVICE,
    hold_wakeup_latency,
    keep_off_cpu,
    leave_realtime,
    wakeup_latency_us,
)
from tests.conftest import holds_wakeup_latency


def test_keep_off_cpu_moves_a_process_to_the_other_cpus():
    cpus = os.sched_getaffinity(0)
    if len(cpus) < 2:
        pytest.skip("needs two CPUs")
    loop_cpu = max(cpus)
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        assert loop_cpu in os.sched_getaffinity(proc.pid)
        keep_off_cpu(proc.pid, loop_cpu, "test")
        assert os.sched_getaffinity(proc.pid) == cpus - {loop_cpu}
        keep_off_cpu(proc.pid, None, "test")  # no loop CPU: nothing changes
        assert os.sched_getaffinity(proc.pid) == cpus - {loop_cpu}
    finally:
        proc.kill()
        proc.wait()


def test_the_wakeup_latency_is_held_until_the_loop_is_left():
    if not os.access(WAKEUP_LATENCY_DEVICE, os.W_OK):
        pytest.skip(f"{WAKEUP_LATENCY_DEVICE}: not writable here (root only)")
    assert not holds_wakeup_latency(os.getpid())
    assert hold_wakeup_latency(0, "test")
    try:
        assert holds_wakeup_latency(os.getpid())
        assert wakeup_latency_us() == 0  # the least of all holders: ours
        assert hold_wakeup_latency(0, "test")  # again: still one descriptor
        assert holds_wakeup_latency(os.getpid()) == 1
    finally:
        leave_realtime("test")
    assert not holds_wakeup_latency(os.getpid())


def test_without_the_device_the_process_runs_on_with_a_warning(monkeypatch, caplog):
    from mrrig.loop import realtime

    monkeypatch.setattr(realtime, "WAKEUP_LATENCY_DEVICE", "/nonexistent/cpu_dma_latency")
    assert not hold_wakeup_latency(0, "test")
    assert "test: CPU wake-up latency not held (/nonexistent/cpu_dma_latency" in caplog.text
    assert not holds_wakeup_latency(os.getpid())
