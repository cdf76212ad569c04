"""The test run's use of the machine (tests/conftest.py): a module of pure numerics in
BESIDE_RIGS runs at SCHED_IDLE, every thread of its worker with it, and waits for no rig."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest

from tests.conftest import BESIDE_RIGS, _Machine

HERE = Path(__file__).parent


@pytest.mark.skipif(os.geteuid() != 0, reason="SCHED_IDLE is left only by root: not used")
def test_a_module_beside_the_rigs_runs_at_sched_idle_with_every_thread():
    assert __name__.rsplit(".", 1)[-1] in BESIDE_RIGS
    assert _Machine.held == "beside"
    assert os.sched_getscheduler(0) == os.SCHED_IDLE
    got = []
    t = threading.Thread(target=lambda: got.append(os.sched_getscheduler(0)))
    t.start()
    t.join(5)
    assert got == [os.SCHED_IDLE]  # what it starts inherits it
    for tid in map(int, os.listdir("/proc/self/task")):
        assert os.sched_getscheduler(tid) == os.SCHED_IDLE, tid


def test_every_module_beside_the_rigs_is_there_and_starts_no_process_or_thread():
    words = ("subprocess", "threading", "zenoh", "procs", "bridge", "ThreadRig", "ScriptedRig")
    for name in BESIDE_RIGS - {"test_beside_rigs"}:  # this one: a thread, to see it inherit
        text = (HERE / f"{name}.py").read_text()
        for word in (*words, "Daemon("):
            assert word not in text, (name, word)
