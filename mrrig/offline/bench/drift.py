"""`mrrig bench drift`: force tracking on a damper that heats, with and without adaptation.

The simulated rig with the `heating` preset (configs/sim-heating.toml: the MR fluid warms from
the power the damper dissipates, and its force at a given current falls with the
temperature) runs a force-tracking test as `mrrig demo` does (the CAN bridge, `firmware_sim`
and the daemon as separate processes; the desired force from the reference Bouc-Wen damper of
configs/rig.toml, a damper that stays cold), twice: the daemon's default controller without
on-line adaptation, then with it. Each run's recording gives Et per minute, the temperature
and the adaptation's state; the simulator's heating coefficients give the force drop the
temperature caused. A transport fault (a stall of this machine) is re-armed as the demo does.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mrrig import json_text
from mrrig.cli.demo import SIM_MODEL, RearmLimit, _stop, ensure_sim_model, watch_and_rearm
from mrrig.cli_args import output_file, positive
from mrrig.config import load_config
from mrrig.loop.realtime import keep_off_cpu
from mrrig.loop.samples import RigState
from mrrig.offline.metrics import error_norm
from mrrig.rigio import client
from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge
from mrrig.rigio.run_identity import CATALOG_ENV
from mrrig.typed_config import load_toml

log = logging.getLogger(__name__)

HEATING_SIM = Path("configs/sim-heating.toml")
MINUTE_S = 60.0
ACCEPT_RATIO = 1.5  # with adaptation: last-minute Et at most this times the first's
STALL_GAP_S = 0.005  # a gap between sensor frames this long is a stall of this machine
AFTER_STALL_S = 0.5  # the frames this long after a stall or an arming are set aside too


def _one_run(
    adaptation: bool, duration_s: float, sim_config: Path, rig_config: Path, work: Path
) -> dict:
    """One force-tracking run; its recording's numbers per minute (`analyse`)."""
    tag = "with" if adaptation else "without"
    port = find_free_port()
    channel = f"ws://127.0.0.1:{port}/"
    record = work / f"drift-{tag}.rrd"
    sim_stats = work / f"sim-{tag}.json"
    summary_json = work / f"daemon-{tag}.json"
    cfg = load_config(rig_config)
    bridge = start_bridge(port)
    sim = daemon = None
    try:
        sim = subprocess.Popen(
            [sys.executable, "-m", "firmware_sim", "--config", str(sim_config)]
            + ["--rig-config", str(rig_config), "--bus-channel", channel, "--stats", str(sim_stats)]
        )
        keep_off_cpu(bridge.pid, cfg.loop.cpu, "CAN bridge")
        keep_off_cpu(sim.pid, cfg.loop.cpu, "firmware_sim")
        time.sleep(1.0)
        if sim.poll() is not None:
            raise RuntimeError(f"firmware_sim exited at start (code {sim.returncode})")
        cmd = [sys.executable, "-m", "mrrig", "run", "--config", str(rig_config)]
        cmd += ["--bus-channel", channel, "--duration", str(duration_s), "--arm"]
        cmd += ["--adaptation", "on" if adaptation else "off", "--record", str(record)]
        cmd += ["--summary-json", str(summary_json)]
        log.info("drift, %s adaptation: %s", tag, " ".join(cmd[2:]))
        daemon = subprocess.Popen(cmd)
        keep_off_cpu(os.getpid(), cfg.loop.cpu, "bench drift")
        rc, rearmed = watch_and_rearm(
            daemon, cfg.rig.name, client.DEFAULT_CONFIG, RearmLimit(3, 10.0), duration_s + 120
        )
        if rc != 0:
            raise RuntimeError(f"the daemon exited with code {rc}")
        _stop(sim, "firmware_sim")
    finally:
        for proc, name in ((daemon, "daemon"), (sim, "firmware_sim")):
            if proc is not None:
                _stop(proc, name)
        stop_bridge(bridge)
    summary = json.loads(summary_json.read_text())
    return analyse(record, summary, len(rearmed), adaptation, duration_s, sim_config)


def analyse(
    record: Path,
    summary: dict,
    rearmed: int,
    adaptation: bool,
    duration_s: float,
    sim_config: Path,
) -> dict:
    """A run's numbers per minute from its recording and the daemon's summary."""
    from mrrig.offline.review import read_recording

    s = read_recording(record).samples
    armed = s["state"] == RigState.ARMED
    # the force of an armed frame that follows an armed one answers an armed command
    answered = armed & np.concatenate([[False], armed[:-1]])
    calm = answered & ~_after_stalls(s["t"], armed)
    t0 = s["t"][armed][0] if armed.any() else 0.0

    def et(w: np.ndarray) -> float:
        return error_norm(s["f_des"][w], s["f_meas"][w]) if w.sum() > 1 else float("nan")

    minutes = []
    for m in range(int(np.ceil(duration_s / MINUTE_S))):
        minute = (s["t"] >= t0 + m * MINUTE_S) & (s["t"] < t0 + (m + 1) * MINUTE_S)
        w = answered & minute
        temps = s["temp_degc"][minute]
        minutes.append(
            {
                "et": et(w),
                "frames": int(w.sum()),
                "et_calm": et(calm & minute),
                "frames_set_aside": int(w.sum() - (calm & minute).sum()),
                "temp_degc_end": float(temps[np.isfinite(temps)][-1])
                if np.isfinite(temps).any()
                else float("nan"),
                "gain_end": float(s["adapt_gain"][w][-1]) if w.any() else float("nan"),
            }
        )
    # the simulator's heating coefficients, from its config file (mrrig never imports the
    # simulator: it runs as its own process)
    th = load_toml(sim_config).get("thermal", {})
    finite = s["temp_degc"][np.isfinite(s["temp_degc"])]
    t_start, t_end = (float(finite[0]), float(finite[-1])) if finite.size else (np.nan, np.nan)
    rise = t_end - float(th.get("ambient_degc", t_start))
    # every force parameter times (1 + coefficient * rise): with one coefficient, the force
    # at a fixed current and motion falls by that share (damper.plant.params_at_temperature)
    keys = ("viscous_per_k", "yield_per_k", "stiffness_per_k")
    factors = [1.0 + float(th.get(k, np.nan)) * rise for k in keys]
    return {
        "adaptation": adaptation,
        "minutes": minutes,
        "temperature_start_degc": t_start,
        "temperature_end_degc": t_end,
        "force_drop_percent": 100.0 * (1.0 - float(np.mean(factors))),
        "et_answered": summary.get("et_answered"),
        "et": summary.get("et"),
        "faults": len(summary.get("faults", [])),
        "rearmed": rearmed,
        "adaptation_state": summary.get("adaptation"),
        "latency_us": summary.get("latency_us"),
        "recording": str(record),
    }


def _after_stalls(t: np.ndarray, armed: np.ndarray) -> np.ndarray:
    """The frames within AFTER_STALL_S after a gap of STALL_GAP_S between sensor frames (a
    stall of this machine: the daemon's commands came late, or it faulted and was re-armed)
    or after an arming."""
    gap = np.diff(t, prepend=t[:1])
    start = np.flatnonzero((gap > STALL_GAP_S) | (armed & ~np.concatenate([[False], armed[:-1]])))
    marks = np.zeros(len(t) + 1)
    ends = np.searchsorted(t, t[start] + AFTER_STALL_S)
    np.add.at(marks, start, 1)
    np.add.at(marks, ends, -1)
    return np.cumsum(marks)[:-1] > 0


def run(duration_s: float, sim_config: Path, rig_config: Path, work: Path) -> dict:
    ensure_sim_model(SIM_MODEL)
    runs = {}
    for adaptation in (False, True):
        runs["with" if adaptation else "without"] = _one_run(
            adaptation, duration_s, sim_config, rig_config, work
        )
    return {"duration_s": duration_s, "sim_config": str(sim_config), "runs": runs}


def _ratio(r: dict, key: str = "et") -> float:
    ets = [m[key] for m in r["minutes"] if np.isfinite(m[key])]
    return ets[-1] / ets[0] if len(ets) > 1 else float("nan")


def format_report(result: dict) -> str:
    runs = result["runs"]
    a, b = runs["without"], runs["with"]
    lines = [
        f"bench drift: {result['sim_config']} (a damper that heats), {result['duration_s']:g} s"
        " of force tracking per run, the desired force from the reference Bouc-Wen damper;",
        "Et per minute over the armed frames whose force answers an armed command; beside it",
        f"(calm) without the {AFTER_STALL_S:g} s after each stall of this machine (a gap over"
        f" {STALL_GAP_S * 1e3:g} ms between sensor frames) or arming, and the frames so set aside",
        f"{'minute':>6} {'Et without':>11} {'(calm)':>8} {'Et with':>9} {'(calm)':>8}"
        f" {'set aside':>11} {'T without':>10} {'T with':>8} {'gain (with)':>12}",
    ]
    for k, (ma, mb) in enumerate(zip(a["minutes"], b["minutes"], strict=True), 1):
        lines.append(
            f"{k:>6} {ma['et']:>11.4f} {ma['et_calm']:>8.4f} {mb['et']:>9.4f}"
            f" {mb['et_calm']:>8.4f} {ma['frames_set_aside']:>5}/{mb['frames_set_aside']:<5}"
            f" {ma['temp_degc_end']:>8.1f} C {mb['temp_degc_end']:>6.1f} C {mb['gain_end']:>12.4f}"
        )
    lines += [
        f"last minute / first: without adaptation {_ratio(a):.2f}x (calm"
        f" {_ratio(a, 'et_calm'):.2f}x), with {_ratio(b):.2f}x (calm {_ratio(b, 'et_calm'):.2f}x)",
        f"temperature: {a['temperature_start_degc']:.1f} -> {a['temperature_end_degc']:.1f} degC"
        f" without, {b['temperature_start_degc']:.1f} -> {b['temperature_end_degc']:.1f} degC"
        " with adaptation;",
        f"  the force at a fixed current and motion down {a['force_drop_percent']:.1f} % /"
        f" {b['force_drop_percent']:.1f} % (the simulator's heating coefficients)",
        f"whole run Et: without {a['et_answered']:.4f}, with {b['et_answered']:.4f}"
        f" (all armed frames: {a['et']:.4f}, {b['et']:.4f});"
        f" faults {a['faults']} / {b['faults']}, re-arms {a['rearmed']} / {b['rearmed']}",
    ]
    st = b["adaptation_state"] or {}
    if st:
        lines.append(
            f"adaptation at the end: gain {st['gain']:.4f}, offset {st['offset_n']:.1f} N,"
            f" {st['updates']} updates, {st['skipped']} skipped (implausible residual)"
        )
    verdict = {key: _ratio(b, key) <= ACCEPT_RATIO for key in ("et", "et_calm")}
    lines.append(
        f"with adaptation, last-minute Et <= {ACCEPT_RATIO:g} x the first: "
        + ("met" if verdict["et"] else "NOT met")
        + "; without the frames after stalls: "
        + ("met" if verdict["et_calm"] else "NOT met")
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="mrrig bench drift", description=__doc__)
    ap.add_argument("--duration", type=positive, default=300.0, help="per run, s (default 300)")
    ap.add_argument("--sim-config", type=Path, default=HEATING_SIM)
    ap.add_argument("--config", type=Path, default=Path("configs/rig.toml"))
    ap.add_argument("--json", type=output_file, help="also write the numbers to this JSON file")
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="mrrig-drift-"))
    # the benchmark's daemon runs go into a catalog of their own, not the lab's
    os.environ[CATALOG_ENV] = str(work / "catalog.sqlite")
    result = run(args.duration, args.sim_config, args.config, work)
    print(format_report(result))
    print(f"recordings: {work}")
    if args.json:
        args.json.write_text(json_text.dumps(result, indent=2))
    return 0
