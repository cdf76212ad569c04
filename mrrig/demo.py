"""`mrrig demo`: the simulated rig end to end, as separate processes.

1. a forward model trained from the simulator (once; reused from models/ afterwards),
2. the python-can-remote bridge on 127.0.0.1 (this machine's kernel has no CAN),
3. `firmware_sim` (the simulated rig firmware) as its own process,
4. the rig daemon as its own process: a 20 s force-tracking run with network inversion,
   telemetry on Zenoh (127.0.0.1) and a Rerun recording,
then the daemon's summary and the simulator's view of the same run, and everything stopped.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mrrig.canbus.bus import find_free_port, start_bridge, stop_bridge
from mrrig.cli_args import positive
from mrrig.config import load_config
from mrrig.realtime import keep_off_cpu

log = logging.getLogger(__name__)

SIM_MODEL = Path("models/sim-forward.json")


def ensure_sim_model(path: Path, seed: int = 0) -> Path:
    """Train the forward network on the simulated characterization matrix if `path` is absent."""
    if path.is_file():
        log.info("using the forward model %s", path)
        return path
    from mrrig.training import simulated_matrix_model

    log.info("no %s yet: training one on the simulated characterization matrix", path)
    simulated_matrix_model(path, seed=seed)
    return path


def _stop(proc: subprocess.Popen, name: str, timeout_s: float = 10.0) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            log.error("%s did not stop in %.0f s: killing it", name, timeout_s)
            proc.kill()
            proc.wait()
    return proc.returncode


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="mrrig demo", description=__doc__)
    ap.add_argument("--config", type=Path, default=Path("configs/rig.toml"))
    ap.add_argument("--sim-config", type=Path, default=Path("configs/sim.toml"))
    ap.add_argument("--duration", type=positive, default=20.0, help="force-tracking time, s")
    ap.add_argument("--model", type=Path, default=SIM_MODEL)
    ap.add_argument(
        "--record", type=Path, help="recording path (default recordings/<rig>-<UTC>.rrd)"
    )
    args = ap.parse_args(argv)

    ensure_sim_model(args.model)
    port = find_free_port()
    work = Path(tempfile.mkdtemp(prefix="mrrig-demo-"))
    channel = f"ws://127.0.0.1:{port}/"
    bridge = start_bridge(port)
    sim = daemon = None
    try:
        sim_stats = work / "sim-stats.json"
        sim = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "firmware_sim",
                "--config",
                str(args.sim_config),
                "--bus-channel",
                channel,
                "--stats",
                str(sim_stats),
            ],
        )
        # the daemon's loop gets its CPU (loop.cpu) to itself
        loop_cpu = load_config(args.config).loop.cpu
        keep_off_cpu(bridge.pid, loop_cpu, "CAN bridge")
        keep_off_cpu(sim.pid, loop_cpu, "firmware_sim")
        time.sleep(1.0)  # the simulator connects and starts streaming
        if sim.poll() is not None:
            raise RuntimeError(f"firmware_sim exited at start (code {sim.returncode})")
        summary_json = work / "daemon-summary.json"
        cmd = [
            sys.executable,
            "-m",
            "mrrig",
            "run",
            "--config",
            str(args.config),
            "--bus-channel",
            channel,
            "--duration",
            str(args.duration),
            "--arm",
            "--summary-json",
            str(summary_json),
        ]
        if args.record:
            cmd += ["--record", str(args.record)]
        log.info("daemon: %s", " ".join(cmd[2:]))
        daemon = subprocess.Popen(cmd)
        rc = daemon.wait(timeout=args.duration + 120)
        if rc != 0:
            raise RuntimeError(f"the daemon exited with code {rc}")
        _stop(sim, "firmware_sim")
        stats = json.loads(sim_stats.read_text())
        print(_sim_report(stats))
        return 0
    finally:
        for proc, name in ((daemon, "daemon"), (sim, "firmware_sim")):
            if proc is not None:
                _stop(proc, name)
        stop_bridge(bridge)


def _sim_report(stats: dict) -> str:
    """The simulator's own count of what it sent and what came back."""
    a = stats["answers"]
    parts = [
        f"sensor frames sent {stats['sensor_frames_sent']}",
        f"answered once {a['answered_once']}",
        f"unanswered {a['unanswered']}",
        f"answered twice {a['answered_more_than_once']}",
        f"unmatched {a['unmatched']}",
        f"daemon's own SAFE after a timeout {a['safe_repeats']}",
        f"watchdog trips {stats['watchdog_trips']}",
        f"max commanded current {stats['max_commanded_current_a']:.3f} A",
    ]
    return (
        "firmware_sim: "
        + ", ".join(parts)
        + "\n  (it streams before the daemon starts and after it stops: frames then go"
        " unanswered, and its watchdog trips once the daemon has stopped)"
    )
