"""The daemon's locked memory: what it touches, not every library whole; one BLAS thread."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mrrig.loop import memory
from mrrig.offline.bench.loop import _ResidentMemory, format_memory
from tests.conftest import REPO


def test_growth_is_measured_from_the_warm_sample():
    rss = _ResidentMemory(1, settled={"VmRSS": 90_000})
    for t, kib in ((1.0, 100_000), (10.0, 110_000), (300.0, 111_100), (600.0, 112_200)):
        rss.sample_status(t, {"VmRSS": kib, "VmLck": 300_000, "Threads": 1})
    m = rss.result()
    assert (m["settled_kib"], m["first_kib"], m["warm_kib"], m["end_kib"]) == (
        90_000,
        100_000,
        110_000,
        112_200,
    )
    assert m["growth_from_warm_pct"] == pytest.approx(2.0)
    text = format_memory(m)
    assert "at start 87.9 MiB" in text and "after the run 109.6 MiB" in text
    assert "growth from 10 s +2.00 %" in text


def test_status_of_a_process_that_is_gone_is_empty():
    assert memory.status_kib(2**22 + 12345) == {}
    assert memory.status_kib()["VmRSS"] > 0


@pytest.mark.process
def test_the_locked_daemon_keeps_resident_what_it_touches(tmp_path: Path):
    cfg = tmp_path / "rig.toml"
    cfg.write_text(
        """
[rig]
name = "mem"
[bus]
interface = "virtual"
channel = "mem-test"
[loop]
realtime = true
[controller]
name = "constant"
current_a = 0.5
[telemetry]
enabled = false
[recording]
enabled = false
"""
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "mrrig", "run", "--config", str(cfg)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        status: dict[str, int] = {}
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.5)
            status = memory.status_kib(proc.pid)
            if status.get("VmLck"):
                time.sleep(1.0)  # past the lock: the loop waits for frames
                status = memory.status_kib(proc.pid)
                break
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    if not status.get("VmLck"):
        pytest.skip(f"mlockall not permitted here: {err.strip().splitlines()[-1:]}")
    # the loop and its control thread (the mailbox's): no OpenBLAS threads (one per core and
    # library, each with a buffer and a stack locked)
    assert status["Threads"] <= 2, status
    # locked on first touch: the mapped libraries' unused pages stay out
    assert status["VmRSS"] < 0.6 * status["VmLck"], status


def test_growth_per_quarter_tells_a_steady_leak_from_a_warm_up():
    from mrrig.offline.bench.loop import _rates

    leak = [(10.0 + k, {"VmRSS": 100_000 + 10 * k}) for k in range(41)]
    assert _rates(leak) == pytest.approx([600.0] * 4)  # 10 kB/s all along
    warm_up = [(10.0 + k, {"VmRSS": 100_000 + min(k, 10) * 100}) for k in range(41)]
    assert _rates(warm_up)[0] > 0 and _rates(warm_up)[1:] == [0.0, 0.0, 0.0]
