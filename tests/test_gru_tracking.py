"""Issue 36, item 4: the daemon inverting a GRU trained on the simulated matrix tracks the
simulator's force (a process module: the GRU's numerics are tests/test_gru.py's, which hold
the machine shared)."""

from __future__ import annotations

import subprocess
import sys
import tomllib

import pytest

from tests.conftest import REPO, _toml, zenoh_configs
from tests.stall_proof import demo_files, explain

# the process test's answered Et at most: the demo with this model measured 0.0095 over 20 s
# here (the network's 0.0087-0.0088), margin for a loaded machine
BOUND = 0.015


@pytest.mark.process
@pytest.mark.long
def test_the_daemon_inverting_a_gru_tracks_the_simulators_force(tmp_path, sim_gru):
    """The demo's rig (configs/rig.toml, configs/sim.toml) with a GRU of 12 units trained on
    the simulated matrix (the demo network's data) as network inversion's model (`sim_gru`:
    trained before this module holds the machine alone)."""
    path = sim_gru
    zdaemon, zclient, _ = zenoh_configs(tmp_path)
    rig = tomllib.loads((REPO / "configs/rig.toml").read_text())
    rig["rig"]["name"] = "gru-inversion-test"
    rig["controller"]["model"] = str(path)
    rig["telemetry"].update(enabled=True, zenoh_config=str(zdaemon))
    rig["recording"]["enabled"] = False
    (tmp_path / "rig.toml").write_text(_toml(rig))
    proc = subprocess.run(
        [sys.executable, "-m", "mrrig", "demo", "--config", str(tmp_path / "rig.toml")]
        + ["--model", str(path), "--zenoh-config", str(zclient), "--duration", "20"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    out = proc.stdout + proc.stderr
    summary, stats = demo_files(out)
    work = summary["latency_split_us"]["work"]
    print(
        f"answered Et {summary['et_answered']:.4f}, faults {len(summary['faults'])},"
        f" work p99 {work['p99']:.0f} us"
    )
    explain(stats, summary["faults"], summary["clock_t0_s"], summary["kernel_stalls"])
    assert summary["controller"] == "network_inversion"
    assert summary["et_answered"] <= BOUND
