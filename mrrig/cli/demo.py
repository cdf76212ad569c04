"""`mrrig demo`: the simulated rig end to end, as separate processes.

1. a forward model trained from the simulator (once; reused from models/ afterwards),
2. the python-can-remote bridge on 127.0.0.1 (this machine's kernel has no CAN),
3. `firmware_sim` (the simulated rig firmware) as its own process,
4. the rig daemon as its own process: a 20 s force-tracking run with network inversion,
   telemetry on Zenoh (127.0.0.1) and a Rerun recording,
then the daemon's summary and the simulator's view of the same run, and everything stopped.

The daemon faults on a stall of this VM's processes as it would on a real bus (no sensor
frame within its timeout, lost frames) and stays in FAULT: it never re-arms itself. The demo
does what the rig's operator would: it watches the daemon's status over Zenoh and re-arms it
after such a transport fault, never after another one. Isolated faults are re-armed; a burst
(more than `--max-rearms` in `--rearm-window` seconds) means a faulty bus, not a stall, and
ends the re-arming for the run. Each re-arm is logged and counted.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mrrig.cli.demo_report import DemoProgress, open_hint, verdict
from mrrig.cli_args import HelpFormatter, int_at_least, positive
from mrrig.config import load_config
from mrrig.config_gaps import config_gaps
from mrrig.errors import MrrigError
from mrrig.loop.realtime import keep_off_cpu
from mrrig.loop.safety import TRANSPORT_FAULTS
from mrrig.rigio import client
from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge
from mrrig.rigio.lease import Lease
from mrrig.rigio.rearm import REARM_WINDOW_S, RearmLimit
from mrrig.rigio.rig_topics import keys
from mrrig.rigio.zenoh_config import write_loopback_configs

log = logging.getLogger(__name__)

SIM_MODEL = Path("models/sim-forward.json")
WATCH_PERIOD_S = 0.25


class DemoError(MrrigError, RuntimeError):
    """The demo could not run (a process did not start or stop as it should)."""


def ensure_sim_model(path: Path, seed: int = 0) -> Path:
    """Train the forward network on the simulated characterization matrix if `path` is absent,
    or if it is a model of the commanded current (an older demo's): the daemon's default
    inversion wants a model of the lagged current."""
    from mrrig.loop.twin_model import load_forward_model
    from mrrig.offline.training import simulated_matrix_model

    if path.is_file():  # a network, or a twin (a plant file: eq. 36 is its lag)
        if load_forward_model(path).meta.get("current_input") == "lagged":
            log.info("using the forward model %s", path)
            return path
        log.info("%s is a model of the commanded current: training one of the lagged current", path)
    else:
        log.info("no %s yet: training one on the simulated characterization matrix", path)
    simulated_matrix_model(path, seed=seed)
    return path


def _interrupt(signum: int, frame) -> None:
    from mrrig.interruption import Interrupted

    raise Interrupted(signum)  # a KeyboardInterrupt that names its signal


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


class _LatestStatus:
    """Subscriber callback keeping the newest status the daemon published (on change, 1 Hz):
    `status` until acted on, `last` for the progress line, and the faults counted."""

    def __init__(self) -> None:
        self.status: dict | None = None
        self.last: dict | None = None
        self.faults = 0

    def __call__(self, sample) -> None:
        st = json.loads(sample.payload.to_bytes())
        prev = self.last or {}
        if st["state"] == "FAULT" and (
            prev.get("state") != "FAULT" or prev.get("fault_reason") != st["fault_reason"]
        ):
            self.faults += 1
        self.status = self.last = st


def watch_and_rearm(
    daemon: subprocess.Popen,
    rig: str,
    zenoh_config: Path,
    limit: RearmLimit,
    timeout_s: float,
    progress: DemoProgress | None = None,
) -> tuple[int, list[str]]:
    """Wait for the daemon to exit (at most `timeout_s`), re-arming it over Zenoh after each
    transport fault its published status shows, as long as `limit` allows. Returns its exit
    code and the faults' reasons. A refused arm (the firmware still in FAULT) is tried again
    on a later status: a FAULT's, or IDLE's where another stall faulted the disarmed rig
    between the reset and the arm and the daemon cleared it with the frames' return. `progress`
    prints its line a second from the telemetry."""
    deadline = time.monotonic() + timeout_s
    rearmed: list[str] = []
    refused: str | None = None  # the fault whose re-arm was refused: armed once IDLE again
    latest = _LatestStatus()
    held: list[Lease] = []  # the lease of the last re-arm, renewed while the demo runs
    with contextlib.ExitStack() as stack:
        stack.callback(lambda: held and held[0].release())
        session = None
        while daemon.poll() is None:
            if time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(daemon.args, timeout_s)
            time.sleep(WATCH_PERIOD_S)
            if progress is not None:
                progress.tick(latest.last, latest.faults, len(rearmed))
            elif limit.ended:
                continue
            st = latest.status
            try:
                if session is None:
                    session = stack.enter_context(client.open_session(zenoh_config))
                    sub = session.declare_subscriber(keys(rig)["status"], latest)
                    stack.callback(sub.undeclare)  # before the session closes
                    if progress is not None:
                        tel = session.declare_subscriber(keys(rig)["telemetry"], progress.et)
                        stack.callback(tel.undeclare)
                if limit.ended or st is None:
                    continue
                idle_again = refused is not None and st["state"] == "IDLE"
                transport = st["state"] == "FAULT" and st["fault"] in TRANSPORT_FAULTS
                if not (idle_again or transport):
                    continue
                reason = st["fault_reason"] if transport else refused
                latest.status = None  # act on this fault once; the next status tells the rest
                if not limit.allows(time.monotonic()):
                    log.warning(
                        "demo: not re-arming after the fault %r: %d re-arms in the last %g s;"
                        " the daemon stays in FAULT for the rest of the run",
                        reason,
                        limit.count,
                        limit.window_s,
                    )
                    continue
                # the operator's choice, made explicit: acknowledge the fault, then arm
                reply = client.query(session, rig, {"cmd": "reset"}, 1.0)
                if reply.get("ok"):
                    reply = client.query(session, rig, {"cmd": "arm"}, 1.0)
            except client.ClientError as exc:
                log.debug("demo: the daemon does not answer (yet): %s", exc)
                continue
            if reply.get("ok") and reply.get("message") == "armed":
                if held:
                    held.pop().release()
                lease = Lease.of(functools.partial(client.query, session, rig), reply, rig)
                held.extend([lease] if lease is not None else [])
                limit.rearmed(time.monotonic())
                rearmed.append(reason)
                refused = None
                log.warning(
                    "demo: re-armed the daemon after its fault %r (%d in all; at most %d in"
                    " any %g s)",
                    reason,
                    len(rearmed),
                    limit.count,
                    limit.window_s,
                )
            elif not reply.get("ok"):
                refused = reason
                log.info("demo: re-arming refused: %s", reply.get("error"))
    return daemon.returncode, rearmed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig demo", description=__doc__
    )
    ap.add_argument(
        "--config", type=Path, default=Path("configs/rig.toml"), help="daemon config (TOML)"
    )
    ap.add_argument(
        "--sim-config",
        type=Path,
        default=Path("configs/sim.toml"),
        help="simulator config (TOML)",
    )
    ap.add_argument("--duration", type=positive, default=20.0, help="force-tracking time, s")
    ap.add_argument(
        "--model",
        type=Path,
        default=SIM_MODEL,
        help="forward model (JSON); trained on the simulated matrix when absent",
    )
    ap.add_argument(
        "--record", type=Path, help="recording path (default recordings/<rig>-<UTC>.rrd)"
    )
    ap.add_argument(
        "--zenoh-config",
        type=Path,
        help="Zenoh client config reaching the daemon (its status, re-arming), which then uses"
        " its config's telemetry.zenoh_config (default: both on a free port of 127.0.0.1)",
    )
    ap.add_argument(
        "--max-rearms",
        type=int_at_least(0),
        default=3,
        help="re-arm the daemon after a transport fault at most this many times in any"
        " --rearm-window seconds; one more fault ends the re-arming (0: never re-arm;"
        " default %(default)s)",
    )
    ap.add_argument(
        "--rearm-window",
        type=positive,
        default=REARM_WINDOW_S,
        help="seconds of --max-rearms (default %(default)g)",
    )
    args = ap.parse_args(argv)

    cfg = load_config(args.config)
    work = Path(tempfile.mkdtemp(prefix="mrrig-demo-"))
    zenoh_client, daemon_zenoh = args.zenoh_config or client.DEFAULT_CONFIG, None
    if cfg.telemetry.enabled and args.zenoh_config is None:
        # a port of its own: a second demo, or a rig's daemon, on this machine is not reached
        daemon_zenoh, zenoh_client = write_loopback_configs(work, find_free_port())
    elif cfg.telemetry.enabled:
        _refuse_a_running_daemon(cfg.rig.name, zenoh_client)
    record = args.record
    if record is None and cfg.recording.enabled:
        from mrrig.rigio.recording import recording_path

        record = recording_path(cfg.recording.directory, cfg.rig.name)
    ensure_sim_model(args.model)
    port = find_free_port()
    channel = f"ws://127.0.0.1:{port}/"
    # SIGTERM (a service manager, a test's timeout) stops the demo as Ctrl-C does: through
    # the `finally` below, so that the bridge, the simulator and the daemon stop with it
    signal.signal(signal.SIGTERM, _interrupt)
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
                "--rig-config",  # the daemon's [can]: the simulator speaks its rig profile
                str(args.config),
                "--bus-channel",
                channel,
                "--stats",
                str(sim_stats),
                "--measure-echo",  # its stall windows, and the bridge's, in the stats
            ],
        )
        # the daemon's loop gets its CPU (loop.cpu) to itself
        loop_cpu = cfg.loop.cpu
        keep_off_cpu(bridge.pid, loop_cpu, "CAN bridge")
        keep_off_cpu(sim.pid, loop_cpu, "firmware_sim")
        time.sleep(1.0)  # the simulator connects and starts streaming
        if sim.poll() is not None:
            raise DemoError(f"firmware_sim exited at start (code {sim.returncode})")
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
        if daemon_zenoh is not None:
            cmd += ["--zenoh-config", str(daemon_zenoh)]
        if record is not None:
            cmd += ["--record", str(record)]
        else:
            cmd += ["--no-record"]
        log.info("daemon: %s", " ".join(cmd[2:]))
        daemon = subprocess.Popen(cmd)
        keep_off_cpu(os.getpid(), loop_cpu, "demo")  # and the Zenoh session's threads
        max_rearms = args.max_rearms if cfg.telemetry.enabled else 0
        if args.max_rearms and not cfg.telemetry.enabled:
            log.info("demo: telemetry is off in %s: no Zenoh, no re-arming", args.config)
        limit = RearmLimit(max_rearms, args.rearm_window)
        progress = DemoProgress(args.duration) if cfg.telemetry.enabled else None
        rc, rearmed = watch_and_rearm(
            daemon, cfg.rig.name, zenoh_client, limit, args.duration + 120, progress
        )
        # 1: it ended in FAULT, which the verdict below judges
        if rc not in (0, 1):
            raise DemoError(f"the daemon exited with code {rc} (its error is above)")
        _stop(sim, "firmware_sim")
        stats = json.loads(sim_stats.read_text())
        print(_sim_report(stats))
        print(
            f"demo: re-armed the daemon {len(rearmed)} times after a transport fault"
            + "".join(f"\n  {reason}" for reason in rearmed)
        )
        ok, text = verdict(json.loads(summary_json.read_text()), gaps=config_gaps(cfg))
        print(text)
        if record is not None:
            print(open_hint(record))
        return 0 if ok else 1
    finally:
        for proc, name in ((daemon, "daemon"), (sim, "firmware_sim")):
            if proc is not None:
                _stop(proc, name)
        stop_bridge(bridge)


def _refuse_a_running_daemon(rig: str, zenoh_config: Path) -> None:
    """A daemon of this rig that already answers (another demo, a `mrrig run`) would take the
    demo's Zenoh port, and the demo would re-arm it: stop before starting anything."""
    try:
        # as long as a client waits: a loaded machine's daemon answers late, not never
        client.request(rig, {"cmd": "status"}, zenoh_config, 2.0)
    except client.ClientError:
        return  # nothing answers: the way is clear
    raise DemoError(
        f"a daemon of rig {rig!r} already answers on {zenoh_config}'s Zenoh network (another"
        " demo or mrrig run?): stop it first, or give this demo another rig name and port"
    )


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
