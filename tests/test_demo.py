"""`mrrig demo` as a person runs it: a transport stall faults the daemon, which stays in
FAULT; the demo re-arms it over Zenoh as the rig's operator would, and only when allowed."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import REPO, OutputWatch, rig_config, stall, zenoh_configs

pytestmark = pytest.mark.slow
STALL_S = 0.1  # the simulator stopped this long: 50 periods without a sensor frame
DURATION_S = 6.0


def _simulator_of(demo_pid: int) -> int:
    children = Path(f"/proc/{demo_pid}/task/{demo_pid}/children").read_text().split()
    for pid in children:
        if b"firmware_sim" in Path(f"/proc/{pid}/cmdline").read_bytes():
            return int(pid)
    raise AssertionError(f"no firmware_sim among the demo's children {children}")


def _demo_with_a_stall(tmp_path: Path, sim_model: Path, max_rearms: int) -> tuple[int, str]:
    """Run the demo; 1 s after the daemon armed, stop the simulator for STALL_S."""
    zdaemon, zclient, _ = zenoh_configs(tmp_path)
    cfg = rig_config(
        tmp_path,
        "ws://127.0.0.1:1/",  # the demo's own bridge replaces it
        sim_model,
        rig={"name": "demo-test"},
        telemetry={"enabled": True, "zenoh_config": str(zdaemon), "rate_hz": 50.0},
    )
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mrrig",
            "demo",
            "--config",
            str(cfg),
            "--model",
            str(sim_model),
            "--zenoh-config",
            str(zclient),
            "--duration",
            str(DURATION_S),
            "--max-rearms",
            str(max_rearms),
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    out = OutputWatch(proc, "state: armed (was IDLE)")
    try:
        assert out.seen.wait(120), out.text()
        time.sleep(1.0)
        stall(_simulator_of(proc.pid), STALL_S)
        rc = proc.wait(DURATION_S + 120)
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(15)
    out.join()
    return rc, out.text()


def _armed_share(out: str) -> float:
    m = re.search(r"^duration .* (\d+) frames \((\d+) armed\)$", out, re.MULTILINE)
    assert m, out
    return int(m.group(2)) / int(m.group(1))


def test_the_demo_rearms_the_daemon_after_a_transport_fault(tmp_path, sim_model):
    # room for the VM's own stalls besides the one made here (CI's bridge stalls up to 35 ms)
    rc, out = _demo_with_a_stall(tmp_path, sim_model, max_rearms=10)
    print(out[-3000:])
    assert rc == 0, out
    assert "mrrig.daemon: fault: " in out  # ours, or an earlier stall of the VM
    assert "state: armed (was FAULT)" in out
    m = re.search(r"^demo: re-armed the daemon (\d+) times", out, re.MULTILINE)
    assert m and 1 <= int(m.group(1)) <= 10, out
    # the stall costs a few hundred ms of a 6 s run, not the rest of it
    assert _armed_share(out) > 0.6


def test_without_rearming_the_daemon_stays_in_fault(tmp_path, sim_model):
    rc, out = _demo_with_a_stall(tmp_path, sim_model, max_rearms=0)
    print(out[-3000:])
    assert rc == 0, out
    assert "mrrig.daemon: fault: " in out  # ours, or an earlier stall of the VM
    assert "state: armed (was FAULT)" not in out
    assert "demo: re-armed the daemon 0 times" in out
    # armed from about 1 s to the stall at about 2 s of the 6 s run
    assert _armed_share(out) < 0.5
