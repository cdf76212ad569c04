"""`mrrig hil SCENARIO --sim`: the quarter car with the simulated rig's damper in its loop (the
bridge, firmware_sim's servo-hydraulic actuator following the daemon's ActuatorSetpoints, the
daemon's network inversion), judged against the all-numerical reference. 10 s of rig time."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.process
def test_mrrig_hil_sim_runs_the_quarter_car_and_prints_j1_to_j3(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "mrrig", "hil", "configs/hil/quarter-car.toml", "--sim",
         "--duration", "10", "--tries", "1"],  # a fault fails it: no rerun
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    out = done.stdout
    print(out)
    assert done.returncode == 0, out[-3000:] + done.stderr[-3000:]
    j = re.search(r"J1 (\S+) ms\s+J2 (\S+) %\s+J3 (\S+) %", out)
    assert j is not None, out
    assert all(math.isfinite(float(v)) for v in j.groups())
    # every model frame's setpoint went out, the scenario played out, every frame answered;
    # one run (--tries 1): a fault of any kind fails the test
    run = re.search(r"run: (\d+) model frames, (\d+) setpoints sent;", out)
    # the last frame ends the run: its setpoint (for a frame past the record) is not sent
    assert run is not None and int(run[1]) == 5000 and int(run[2]) == 4999, out
    assert "ended: the scenario is played out" in out
    counts = re.search(r"sensor frames (\d+), commands (\d+)", out)
    assert counts[1] == counts[2]
    assert "fault none" in out
    for name in ("suspension_travel_m", "body_acceleration_m_s2", "tyre_load_n"):
        line = re.search(rf"^{name} .*RMS error (\S+) %", out, re.M)
        assert line is not None and math.isfinite(float(line[1])), out
