"""The loop's CPU: other processes of the rig are kept off it."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from mrrig.loop.realtime import keep_off_cpu


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
