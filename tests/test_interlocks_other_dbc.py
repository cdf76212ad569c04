"""Issue 40, finding 14, against processes: firmware_sim on another DBC ends the daemon's armed run
in a fault (a process module: the interlocks' other findings, in a scripted rig, are
tests/test_interlocks.py's, which hold the machine shared)."""

from __future__ import annotations

import re
import subprocess

import pytest

from tests.conftest import REPO, OutputWatch, rig_config


@pytest.mark.process
def test_finding14_process_the_simulator_on_another_dbc_ends_the_armed_run_in_fault(
    tmp_path, bridge, procs
):
    """The issue's reproduction: the simulator on a DBC with other IDs, the daemon on ours
    with --arm. It ran 'fine': exit 0, faults 0. Now exit 1, no_sensor_frames naming them."""
    dbc = (REPO / "configs/mrrig.dbc").read_text()
    other = re.sub(r"\b272\b", "1296", re.sub(r"\b273\b", "1297", dbc))  # 0x510, 0x511
    (tmp_path / "other.dbc").write_text(other)
    sim_cfg = (REPO / "configs/sim.toml").read_text()
    sim_cfg += f'\n[can]\ndbc = "{tmp_path / "other.dbc"}"\n'
    (tmp_path / "sim.toml").write_text(sim_cfg)
    sim = procs(
        ["-m", "firmware_sim", "--config", str(tmp_path / "sim.toml"), "--bus-channel", bridge],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    assert OutputWatch(sim, "rig firmware on").seen.wait(30)
    cfg = rig_config(tmp_path, bridge, None, controller={"name": "constant", "current_a": 0.5})
    daemon = procs(
        ["-m", "mrrig", "run", "--config", str(cfg), "--arm", "--duration", "3", "--no-record"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    out, _ = daemon.communicate(timeout=90)
    print(out[-3000:])
    assert daemon.returncode == 1, out[-2000:]
    line = next(x for x in out.splitlines() if "no valid RigSensors frame" in x)
    # the foreign RigSensors (0x510, every 2 ms); its RigStatus (0x511) comes every 100 ms
    assert re.search(r"the bus carried \d+ other frames: 0x510 x\d+", line), line
