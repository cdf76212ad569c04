"""`mrrig bench loop`: the real-time loop measured end to end, as separate processes.

Starts the bridge, firmware_sim and the daemon (as the demo does) and runs for `--duration`
seconds, once with telemetry (Zenoh) and recording (Rerun) off and once with both on, then
prints per run: receive->send latency p50/p99/p99.9/max (the daemon's own measure, per frame,
from the bus's receive timestamp) split into the wait before the loop read the frame and the
loop's work from its read to the end of send() (the spec's budget), frames without a
command (the simulator's count), the simulator's period jitter, CPU per process, and the on/off
ratio of the latency p99. The "on" run's daemon runs the frame's numerics compiled
(`loop.numerics`, mrrig/loop/compiled.py); a "python" run, the same with them on the Python
path, is printed beside it: the work per frame of both and their ratio. A first run replaces
the daemon by `mrrig.offline.bench.echo`, which answers every frame with a SAFE command and
does nothing else: the floor that the transport (bridge, Python, this machine) sets, measured
the same way in the same session. With `--hil SCENARIO` a last run has the daemon run that
hybrid simulation (`mrrig run --hil`: the numerical substructure and the delay compensation
stepped on every frame, an ActuatorSetpoint after each command; telemetry and recording off
as in the `off` run), so that its work per frame is measured beside the force-tracking loop's
in the same session (`hil_lines`).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mrrig import json_text
from mrrig.cli_args import HelpFormatter, output_file, positive
from mrrig.config import load_config
from mrrig.loop import memory
from mrrig.loop.realtime import keep_off_cpu
from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge
from mrrig.rigio.run_identity import CATALOG_ENV

log = logging.getLogger(__name__)


def _cpu_s(pid: int) -> float:
    """utime + stime of a live process, s (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _wait_for_daemon(proc: subprocess.Popen, timeout_s: float = 60.0) -> None:
    """Until the daemon's process has settled (imports done, bus open), or it died."""
    deadline = time.monotonic() + timeout_s
    cpu = -1.0
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"daemon exited at start with code {proc.returncode}")
        now = _cpu_s(proc.pid)
        if now == cpu:  # idle: waiting for frames
            return
        cpu = now
        time.sleep(0.5)
    raise RuntimeError("daemon did not settle in 60 s")


MODES = ("echo", "off", "on", "python")
BUDGET_P99_US = 300.0  # spec/system.md: the daemon's work per frame
BUDGET_P999_US = 1000.0  # transport floor; daemon without / with telemetry+recording
# issue 44's target for the work per frame (read -> end of send), compiled, telemetry and
# recording on
TARGET_WORK_P99_US = 50.0
TARGET_WORK_P999_US = 150.0


def run_once(
    config: Path,
    sim_config: Path,
    duration_s: float,
    mode: str,
    daemon_args: tuple = (),
    numerics: str = "compiled",
) -> dict:
    """One run; `numerics`: the daemon's (`loop.numerics`) in the off, on and hil runs (the
    python run's is python)."""
    work = Path(tempfile.mkdtemp(prefix="mrrig-bench-loop-"))
    # the benchmark's daemon runs go into a catalog of their own, not the lab's
    os.environ[CATALOG_ENV] = str(work / "catalog.sqlite")
    port = find_free_port()
    channel = f"ws://127.0.0.1:{port}/"
    bridge = start_bridge(port)
    sim = daemon = None
    try:
        t_bridge0 = _cpu_s(bridge.pid)
        # the daemon first, so that every frame the simulator sends has a daemon to answer it
        if mode == "echo":
            cmd = [sys.executable, "-m", "mrrig.offline.bench.echo", "--config", str(config)]
            cmd += ["--bus-channel", channel, "--summary-json", str(work / "daemon.json")]
        else:
            cmd = [
                sys.executable,
                "-m",
                "mrrig",
                "-q",
                "run",
                "--config",
                str(config),
                "--bus-channel",
                channel,
                "--arm",
                "--summary-json",
                str(work / "daemon.json"),
            ]
        if mode in ("on", "python"):
            cmd += ["--record", str(work / "bench.rrd")]
        if mode == "python":
            numerics = "python"
        if mode != "echo":
            cmd += ["--numerics", numerics]
        if mode in ("off", "hil"):
            cmd += ["--no-record", "--no-telemetry"]
        cmd += list(daemon_args)
        daemon = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
        _wait_for_daemon(daemon)
        t0 = time.monotonic()
        sim = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "firmware_sim",
                "--config",
                str(sim_config),
                "--bus-channel",
                channel,
                "--stats",
                str(work / "sim.json"),
                "--duration",
                str(duration_s),
            ]
        )
        # the loop's CPU (loop.cpu) to the daemon (or the echo process) alone
        loop_cpu = load_config(config).loop.cpu
        keep_off_cpu(bridge.pid, loop_cpu, "CAN bridge")
        keep_off_cpu(sim.pid, loop_cpu, "firmware_sim")
        rss = _ResidentMemory(daemon.pid, settled=memory.status_kib(daemon.pid))
        while True:
            try:
                code = sim.wait(timeout=RSS_SAMPLE_S)
                break
            except subprocess.TimeoutExpired:
                if time.monotonic() - t0 > duration_s + 120:
                    raise RuntimeError("firmware_sim did not stop") from None
                rss.sample(time.monotonic() - t0)
        if code != 0:
            raise RuntimeError(f"firmware_sim exited with code {code}")
        wall = time.monotonic() - t0
        bridge_cpu = _cpu_s(bridge.pid) - t_bridge0
        echo_cpu = _cpu_s(daemon.pid)
        daemon.send_signal(signal.SIGTERM)
        # 1: the daemon ended in FAULT, the sensor timeout once the simulator had stopped
        if daemon.wait(timeout=60) not in (0, 1):
            raise RuntimeError(f"daemon exited with code {daemon.returncode}")
        d = json.loads((work / "daemon.json").read_text())
        s = json.loads((work / "sim.json").read_text())
        loop_cpu = (
            100 * echo_cpu / wall if mode == "echo" else 100 * d["cpu_loop_s"] / d["loop_wall_s"]
        )
        return {
            "mode": mode,
            "telemetry_and_recording": mode in ("on", "python"),
            "numerics": None if mode == "echo" else numerics,
            "duration_s": d.get("duration_s", wall),
            "frames": d["frames"],
            "latency_us": d["latency_us"],
            "latency_split_us": d.get("latency_split_us"),
            "frame_gap_ms": d.get("frame_gap_ms"),
            "sensor_frames_sent": s["sensor_frames_sent"],
            "frames_without_command": s["answers"]["unanswered"],
            "frames_answered_more_than_once": s["answers"]["answered_more_than_once"],
            "safe_repeats": s["answers"].get("safe_repeats", 0),
            "watchdog_trips": s["watchdog_trips"],
            "sim_jitter_us": s.get("period_jitter_us"),
            "sim_answer_latency_us": s.get("answer_latency_us"),
            "cpu_pct": {
                "daemon_loop" if mode != "echo" else "echo_process": loop_cpu,
                # the sidecar's whole life, start-up included, over the loop's time
                "telemetry_process": 100 * d.get("cpu_sidecar_s", 0.0) / d.get("loop_wall_s", wall),
                "firmware_sim": 100 * s.get("cpu_fraction", float("nan")),
                "bridge": 100 * bridge_cpu / wall,
            },
            "et": d.get("et"),
            # the simulator stops first: a sensor timeout after its last frame is the end of
            # the run, not a fault of the loop
            "faults": [f for f in d.get("faults") or [] if not f["t"] > d["last_frame_t_s"]],
            "faults_after_the_simulator_stopped": [
                f for f in d.get("faults") or [] if f["t"] > d["last_frame_t_s"]
            ],
            "telemetry_dropped": d.get("telemetry_dropped"),
            # frames whose inversion was prepared ahead / prepared but solved in full
            "solved_ahead": (d.get("commands_solved_ahead"), d.get("commands_ahead_missed")),
            "resident_memory": rss.result(),
        }
    finally:
        for p in (daemon, sim):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
        stop_bridge(bridge)


RSS_SAMPLE_S = 1.0
RSS_WARM_S = 10.0  # the loop has run every path of an ordinary run by then


class _ResidentMemory:
    """The daemon's resident and locked memory (/proc), sampled while the simulator runs."""

    def __init__(self, pid: int, settled: dict[str, int]) -> None:
        self._pid = pid
        self.settled = settled  # before the first frame: imports done, memory locked
        self.samples: list[tuple[float, dict[str, int]]] = []

    def sample(self, t_s: float) -> None:
        self.sample_status(t_s, memory.status_kib(self._pid))

    def sample_status(self, t_s: float, status: dict[str, int]) -> None:
        if status:
            self.samples.append((t_s, status))

    def result(self) -> dict:
        if not self.samples:
            return {}
        rss = [s["VmRSS"] for _, s in self.samples]
        warm = next((s for t, s in self.samples if t >= RSS_WARM_S), self.samples[0][1])
        end = self.samples[-1][1]
        return {
            "settled_kib": self.settled.get("VmRSS"),
            "first_kib": rss[0],
            "warm_kib": warm["VmRSS"],
            "warm_at_s": RSS_WARM_S,
            "end_kib": end["VmRSS"],
            "max_kib": max(rss),
            "locked_end_kib": end.get("VmLck"),
            "threads": end.get("Threads"),
            "growth_from_warm_pct": 100 * (end["VmRSS"] - warm["VmRSS"]) / warm["VmRSS"],
            # a leak grows at a steady rate; pages touched for the first time, less and less
            "growth_kib_per_min": _rates(self.samples),
            "samples": len(rss),
            "series_kib": [(round(t, 1), s["VmRSS"]) for t, s in self.samples[::10]],
        }


def _rates(samples: list[tuple[float, dict[str, int]]]) -> list[float]:
    """RSS growth in kB per minute over each quarter of the run after the warm-up."""
    warm = [(t, s["VmRSS"]) for t, s in samples if t >= RSS_WARM_S]
    if len(warm) < 8:
        return []
    edges = [warm[len(warm) * k // 4] for k in range(4)] + [warm[-1]]
    return [60 * (b[1] - a[1]) / (b[0] - a[0]) for a, b in zip(edges, edges[1:], strict=False)]


def format_memory(m: dict, who: str = "daemon") -> str:
    if not m:
        return "  resident memory: not measured (no /proc)"

    def mib(kib: int | None) -> str:
        return "?" if kib is None else f"{kib / 1024:.1f} MiB"

    return (
        f"  {who} resident memory (RSS): at start {mib(m['settled_kib'])} (settled, before "
        f"the first frame), {mib(m['first_kib'])} at 1 s, {mib(m['warm_kib'])} at "
        f"{m['warm_at_s']:g} s, after the run {mib(m['end_kib'])} (max {mib(m['max_kib'])}; "
        f"growth from {m['warm_at_s']:g} s {m['growth_from_warm_pct']:+.2f} %); locked "
        f"{mib(m['locked_end_kib'])} of address space, {m['threads']} threads"
        + (
            "; growth per quarter of the run, kB/min: "
            + ", ".join(f"{r:.0f}" for r in m["growth_kib_per_min"])
            if m.get("growth_kib_per_min")
            else ""
        )
    )


def format_run(r: dict) -> str:
    lat = r["latency_us"]
    cpu = r["cpu_pct"]
    jit = r["sim_jitter_us"] or {}
    split = r.get("latency_split_us") or {}
    title = {
        "echo": "transport floor (echo process, no daemon)",
        "off": "daemon, telemetry+recording OFF",
        "on": "daemon, telemetry+recording ON",
        "hil": "daemon running the hybrid simulation, telemetry+recording OFF",
        "python": "daemon, telemetry+recording ON, numerics on the Python path",
    }[r["mode"]]
    if r["mode"] in ("off", "on", "hil"):
        title += f", {r['numerics']} numerics"
    return "\n".join(
        [
            f"{title}: simulator sent {r['sensor_frames_sent']} sensor frames, "
            f"answered {r['frames']} in {r['duration_s']:.1f} s; faults while it streamed "
            f"{[f['reason'] for f in r['faults'] or []]} (after it stopped: "
            f"{[f['reason'] for f in r.get('faults_after_the_simulator_stopped') or []]});"
            f" firmware watchdog trips "
            f"{r['watchdog_trips']}; tracking Et {r['et']}",
            f"  receive->send latency us: p50 {lat['p50']:.0f}  p99 {lat['p99']:.0f}  "
            f"p99.9 {lat['p99.9']:.0f}  max {lat['max']:.0f}",
            *(
                f"    {label:<14} p50 {q['p50']:.0f}  p99 {q['p99']:.0f}  "
                f"p99.9 {q['p99.9']:.0f}  max {q['max']:.0f}"
                for label, q in (
                    ("waited:", split.get("waited")),
                    ("work:", split.get("work")),
                    ("  send() call:", split.get("send_call")),
                )
                if q
            ),
            f"  largest gap between sensor frames at the receiver: "
            f"{(r['frame_gap_ms'] or {}).get('max', float('nan')):.1f} ms "
            f"({(r['frame_gap_ms'] or {}).get('over_10_ms')} over 10 ms)",
            f"  frames without a command: {r['frames_without_command']}  "
            f"(answered twice: {r['frames_answered_more_than_once']}; the daemon's own SAFE"
            f" after a sensor timeout: {r['safe_repeats']}); "
            f"telemetry samples dropped: {r['telemetry_dropped']}",
            "  firmware_sim period jitter us: " + "  ".join(f"{k} {v:.0f}" for k, v in jit.items()),
            "  CPU % of one core: " + "  ".join(f"{k} {v:.1f}" for k, v in cpu.items()),
            format_memory(
                r.get("resident_memory") or {}, "echo process" if r["mode"] == "echo" else "daemon"
            ),
            *(
                [
                    f"  commands solved ahead: {r['solved_ahead'][0]} (prepared, then solved"
                    f" in full on the frame: {r['solved_ahead'][1]})",
                    f"  budget: {budget_verdict(r)}",
                ]
                if r["mode"] != "echo"
                else []
            ),
        ]
    )


QUANTILES = ("p50", "p99", "p99.9")


def compiled_beside_python(compiled: dict, python: dict) -> str:
    """The work per frame of the two runs (telemetry and recording on), their ratio, and issue
    44's target for the compiled one."""
    c, p = compiled["latency_split_us"]["work"], python["latency_split_us"]["work"]
    lines = ["work per frame us (read -> end of send), telemetry+recording ON:"]
    for name, q in (("compiled", c), ("python", p)):
        lines.append("  " + f"{name:<9}" + "  ".join(f"{k} {q[k]:.0f}" for k in QUANTILES))
    lines.append("  python / compiled: " + "  ".join(f"{k} {p[k] / c[k]:.2f}" for k in QUANTILES))
    met = c["p99"] <= TARGET_WORK_P99_US and c["p99.9"] <= TARGET_WORK_P999_US
    lines.append(
        f"  target (issue 44, compiled): p99 <= {TARGET_WORK_P99_US:g} us, p99.9 <= "
        f"{TARGET_WORK_P999_US:g} us: {'MET' if met else 'MISSED'} (send() call p50 "
        f"{compiled['latency_split_us']['send_call']['p50']:.0f} us of it)"
    )
    return "\n".join(lines)


def budget_verdict(r: dict) -> str:
    """The spec's budget for the daemon's work per frame, checked on one run."""
    lat = r["latency_us"]
    parts, ok = [], True
    for q, limit in (("p99", BUDGET_P99_US), ("p99.9", BUDGET_P999_US)):
        met = lat[q] <= limit
        ok &= met
        parts.append(f"{q} {lat[q]:.1f} {'<=' if met else '>'} {limit:g} us")
    ok &= r["frames_without_command"] == 0
    parts.append(f"{r['frames_without_command']} frames without a command")
    return ("MET: " if ok else "MISSED: ") + ", ".join(parts)


def hil_args(scenario: Path, duration_s: float) -> tuple[str, ...]:
    """The daemon's arguments for the `hil` run: the scenario armed at start for the whole
    run (a second longer than the simulator streams, so that it is not played out early)."""
    return ("--hil", str(scenario), "--hil-duration", repr(duration_s + 1.0))


def hil_lines(runs: dict[str, dict]) -> list[str]:
    """The hybrid simulation's work per frame beside the force-tracking loop's (the `off`
    run, the same outputs off) of the same session, against the spec's p99 budget."""
    hil = runs["hil"]["latency_split_us"]["work"]
    lines = [
        f"hybrid simulation: work per frame p50 {hil['p50']:.0f}  p99 {hil['p99']:.0f}  "
        f"p99.9 {hil['p99.9']:.0f} us (p99 {'<=' if hil['p99'] <= BUDGET_P99_US else '>'} "
        f"{BUDGET_P99_US:g} us)"
    ]
    if "off" in runs:
        off = runs["off"]["latency_split_us"]["work"]
        lines.append(
            f"  beside the force-tracking loop (off): p50 {off['p50']:.0f}  p99 "
            f"{off['p99']:.0f}  p99.9 {off['p99.9']:.0f} us; the hybrid simulation adds "
            f"{hil['p50'] - off['p50']:+.0f} us at p50, {hil['p99'] - off['p99']:+.0f} us at p99"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig bench loop", description=__doc__
    )
    ap.add_argument("--config", type=Path, default=Path("configs/rig.toml"))
    ap.add_argument("--sim-config", type=Path, default=Path("configs/sim.toml"))
    ap.add_argument("--duration", type=positive, default=60.0, help="seconds per run (default 60)")
    ap.add_argument("--only", choices=MODES, help="one run instead of all three")
    ap.add_argument(
        "--hil",
        type=Path,
        metavar="SCENARIO",
        help="a last run with the daemon running this hybrid simulation (configs/hil/*.toml)",
    )
    ap.add_argument(
        "--numerics",
        choices=("compiled", "python"),
        default="compiled",
        help="the daemon's frame numerics in the off, on and hil runs (default compiled; the "
        "python run's are python)",
    )
    ap.add_argument("--json", type=output_file, help="also write the numbers here")
    args = ap.parse_args(argv)
    from mrrig.cli.demo import SIM_MODEL, ensure_sim_model

    ensure_sim_model(SIM_MODEL)
    runs = {}
    for mode in [args.only] if args.only else MODES:
        log.info("run %s, %.0f s", mode, args.duration)
        runs[mode] = run_once(
            args.config, args.sim_config, args.duration, mode, numerics=args.numerics
        )
        print(format_run(runs[mode]), flush=True)
    if args.hil is not None:
        log.info("run hil (%s), %.0f s", args.hil, args.duration)
        runs["hil"] = run_once(
            args.config,
            args.sim_config,
            args.duration,
            "hil",
            hil_args(args.hil, args.duration),
            args.numerics,
        )
        print(format_run(runs["hil"]), flush=True)
        print("\n".join(hil_lines(runs)), flush=True)
    result: dict = {"runs": list(runs.values())}
    if "on" in runs and "off" in runs:
        ratio = runs["on"]["latency_us"]["p99"] / runs["off"]["latency_us"]["p99"]
        result["p99_ratio_on_off"] = ratio
        print(f"latency p99 ratio on/off: {ratio:.2f}")
    if "on" in runs and "python" in runs:
        print(compiled_beside_python(runs["on"], runs["python"]))
        work = runs["on"]["latency_split_us"]["work"]
        result["work_python_over_compiled"] = {
            q: runs["python"]["latency_split_us"]["work"][q] / work[q] for q in QUANTILES
        }
    if "echo" in runs:
        floor = runs["echo"]["latency_us"]
        print(
            f"transport floor (echo): p99 {floor['p99']:.0f} us, p99.9 {floor['p99.9']:.0f} us"
            + "".join(
                f"; daemon {m} p99 {runs[m]['latency_us']['p99']:.0f} us"
                f" = floor x {runs[m]['latency_us']['p99'] / floor['p99']:.2f}"
                for m in ("off", "on")
                if m in runs
            )
        )
    print(
        f"budget (spec/system.md): p99 <= {BUDGET_P99_US:g} us, p99.9 <= {BUDGET_P999_US:g} us,"
        " 0 frames without a command"
    )
    if args.json:
        args.json.write_text(json_text.dumps(result, indent=2))
    return 0
