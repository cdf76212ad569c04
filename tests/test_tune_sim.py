"""`mrrig tune --sim`: the trials on the simulated rig, the table, the choice written; a trial
aborted by a transport fault runs again and a faulted trial is never chosen (a process module:
tune's other checks are tests/test_tune.py's, which hold the machine shared)."""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
import sys
import time
from dataclasses import replace

import pytest

from mrrig.loop.mlp import MLP
from mrrig.tune import Candidate
from mrrig.tune.trials import DEFAULT_PROFILE
from tests.conftest import REPO, rig_config, zenoh_configs
from tests.test_tune import _booted


@pytest.mark.process
def test_tune_sim_runs_the_trials_prints_the_table_and_writes_the_choice(tmp_path):
    """A 2-trial grid on the simulated rig over the bridge: the table printed, kept as JSON and
    CSV, the smallest usable Et chosen, its continuity written into the model file (where the
    daemon reads it: the daemon reports it in force) and the feedback into a config snippet."""
    model = tmp_path / "model.json"
    shutil.copy(REPO / "models/sim-forward.json", model)
    before = MLP.load(model).meta["online_continuity"]
    daemon_z, client_z, _ = zenoh_configs(tmp_path)
    cfg = rig_config(
        tmp_path,
        "ws://127.0.0.1:1/",  # --sim gives the daemon its bridge's channel
        model,
        rig={"name": "tune-sim"},
        telemetry={"enabled": True, "zenoh_config": str(daemon_z)},
    )
    args = ["--sim", "--config", str(cfg), "--zenoh-config", str(client_z)]
    grid_args = ["--continuity", "0,1", "--feedback-tau-s", "0", "--duration", "3", "--settle", "1"]
    out = subprocess.run(
        [sys.executable, "-m", "mrrig", "tune", *args, *grid_args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=90,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert "trial 1/2: mu 0, feedback tau 0 ms" in out.stdout  # progress
    record = json.loads(model.with_suffix(".tune.json").read_text())
    trials = record["trials"]
    assert [t["continuity"] for t in trials] == [0.0, 1.0]
    usable = [t for t in trials if t["usable"]]
    best = min(usable, key=lambda t: t["et"])
    assert record["chosen"]["continuity"] == best["continuity"]
    assert model.with_suffix(".tune.csv").read_text().startswith("continuity,feedback_tau_s")
    rows = re.findall(r"^ ?\d+\s+(\S+)\s+\S+\s+(\S+).*$", out.stdout, re.M)
    assert [float(mu) for mu, _ in rows] == [0.0, 1.0]
    assert "<- chosen" in out.stdout
    written = MLP.load(model).meta["online_continuity"]
    assert written == best["continuity"] != before
    assert f"in force on rig tune-sim now: continuity {float(written)}" in out.stdout
    snippet = model.with_suffix(".tune.toml").read_text()
    assert "[controller]" in snippet and "feedback_tau_s = 0.0" in snippet


@pytest.mark.process
def test_a_trial_aborted_by_a_transport_fault_runs_again_and_a_faulted_trial_is_never_chosen(
    tmp_path,
):
    """firmware_sim goes silent for 0.1 s in the middle of the trial's first attempt (the
    daemon's sensor_timeout, a transport fault): the trial runs once more after a reset and
    says why. Should the second attempt fault too (a stall of the loaded machine), the trial
    is not chosen; else it is."""
    from mrrig.api import Rig
    from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge
    from mrrig.tune.trials import run_trials
    from tests.conftest import start, stop
    from tests.live_rig import wait_status

    silent_s = 25.0  # since the simulator's clock started: after the daemon is up
    model = tmp_path / "model.json"
    shutil.copy(REPO / "models/sim-forward.json", model)
    port = find_free_port()
    bridge = start_bridge(port)
    channel = f"ws://127.0.0.1:{port}/"
    daemon_z, client_z, _ = zenoh_configs(tmp_path)
    cfg = rig_config(
        tmp_path,
        channel,
        model,
        rig={"name": "tune-fault"},
        telemetry={"enabled": True, "zenoh_config": str(daemon_z)},
    )
    fault = f"silent@{silent_s:g}:0.1"
    args = ["-m", "firmware_sim", "--config", "configs/sim.toml", "-c", channel, "--fault", fault]
    sim = start(args, stderr=subprocess.PIPE, text=True)
    daemon = None
    try:
        t_boot = _booted(sim)
        daemon = start(["-m", "mrrig", "run", "--config", str(cfg), "--no-record"])
        wait_status(client_z, timeout_s=silent_s - 8.0, rig="tune-fault")
        profile = replace(DEFAULT_PROFILE, settle_s=1.0, duration_s=5.0)
        # the first attempt arms about 2 s before the silence and runs 4 s past it
        time.sleep(max(0.0, t_boot + silent_s - 2.0 - time.monotonic()))
        lines: list[str] = []
        with Rig("tune-fault", zenoh_config=client_z) as rig:
            result = run_trials(rig, [Candidate(0.03, 0.0)], profile, lines.append)
    finally:
        if daemon is not None:
            stop(daemon)
        stop(sim)
        stop_bridge(bridge)
    (trial,) = result.trials
    text = "\n".join(lines)
    assert trial.attempts == 2, text
    assert "attempt 1: transport fault sensor_timeout" in trial.note, text
    if trial.faults:  # the second attempt stalled too: marked, never chosen
        assert result.chosen is None and "no usable trial" in result.why
    else:
        assert result.chosen is trial and math.isfinite(trial.et)
