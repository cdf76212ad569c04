"""`mrrig bench fuzz --minutes N`: hostile frames, requests and signals against a live rig.

The bridge, firmware_sim and the daemon (telemetry and recording on, armed) run as processes.
A quiet phase and a request burst (1000 status requests, 50 malformed ones and one of 1 MB a
second, as in issue 23) come first, each min(20 s, a third of the run), and compare the
answer latency as the firmware sees it; then, for the rest of the run, the fuzzer sends random
and mutated CAN frames (29-bit, remote, unknown IDs, wrong lengths, broken CRCs, frames that
waited; its invalid RigSensors frames stay inside the bad-frame budget so that the rig stays
armed), random JSON requests (any depth, size, type, unicode, NaN) and, while armed, request
sequences: chains of individually valid changes 5 ms apart (six actuator amplitude steps of
4 mm, six frequency steps, set_profile forces rising past `loop.f_range_n` then arming,
force_ref values rising to 1e300), and re-arms the daemon after every fault (renewing the
lease of its arms). Every 15 s a client that holds the rig armed (`mrrig arm --hold`) is
SIGKILLed at a random moment: the rig must leave ARMED within the lease's timeout
(`armed_without_lease`, mrrig.offline.bench.fuzz_lease). Every minute (the first at half the
fuzz phase, or half a minute) a client's step (`mrrig test`) holds the rig while the simulator
is held up 0.1 s every 0.6 s: a faulty bus, on which the step must be aborted `faulty bus` at
the re-arm cap (`faulty_bus_not_aborted`, mrrig.offline.bench.fuzz_faulty_bus). It sends the
daemon SIGHUP, SIGUSR1, SIGUSR2, SIGQUIT and SIGPIPE in turn: each must end the run SAFE (the
last DamperCommand SAFE, the actuator stopped, a summary written, exit code 0 or 1) or be
ignored (the daemon answers on); a daemon that ended is started again. A listener on the bus
checks every command against the genuine sensor frames.

Printed counts, and the exit code 1 when one is not 0: crashes (a process that died, a signal
that killed the daemon or ended it any other way than SAFE, the daemon's exit code not 0 or 1,
a telemetry restart), commands above the current limit or with a desired force outside
`loop.f_range_n`, motion beyond the limits in force at arming (the simulator's armed_motion:
per stretch of ACTIVE commands, the actuator's amplitude beyond the one in force at arming
plus `control.armed_amplitude_step_m`, or its frequency above the one in force at arming),
ACTIVE commands the firmware applied to a stale frame (older than its stale_answer_age_s on
its own clock) or to no valid frame, ACTIVE answers to no genuine frame (the listener's),
control requests without an answer (but those sent while a signal ended the daemon). The
late commands the firmware dropped (spec/can-protocol.md) and the ACTIVE answers that
reached the bus over the age limit are reported. Then, the rig stopped, every daemon start's
recording must have its run in the bench's catalog once the journals beside them are replayed
(`runs_missing_from_catalog`), and an observer's misuse of a sidecar on the shipped access
control (`mrrig.offline.bench.fuzz_observer`).

Answer latency "as the firmware sees it": from the bridge's receive timestamp of a sensor
frame to the bridge's receive timestamp of its command (both carried in the frames a bus
client receives), so the listener's own scheduling does not enter it.
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import logging
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from mrrig import json_text
from mrrig.cli_args import HelpFormatter, output_file, positive
from mrrig.config import load_config
from mrrig.offline.bench import fuzz_faulty_bus, fuzz_lease, fuzz_observer
from mrrig.offline.bench.fuzz_inputs import BASE_MOTION, CHAINS, chain, junk_frame, random_request
from mrrig.offline.bench.fuzz_verdict import failures, motion_beyond_limits, report
from mrrig.pycan import can
from mrrig.rigio.canbus.bus import find_free_port, open_bus, start_bridge, stop_bridge
from mrrig.rigio.canbus.codec import Codec
from mrrig.rigio.lease import Lease
from mrrig.rigio.rig_topics import JSON, keys
from mrrig.rigio.run_identity import CATALOG_ENV
from mrrig.rigio.zenoh_config import local_config

log = logging.getLogger(__name__)

JUNK_HZ = 200.0  # random frames the daemon must ignore
# broken RigSensors frames, evenly spaced: at most 2 in any second, inside the bad-frame
# budget (3 a second) so that the rig stays armed
BAD_SENSORS_PERIOD_S = 0.6
REQUESTS_HZ = 20.0
BURST_STATUS_HZ = 1000
BURST_BAD_HZ = 50
PHASE_S = 20.0
ANSWER_WINDOW = 16  # genuine frames an ACTIVE command may answer (32 ms)
REQUEST_TIMEOUT_S = 3.0
# request sequences: a chain (fuzz_inputs.chain) every SEQUENCE_EVERY_S while armed, its requests
# CHAIN_GAP_S apart (issue 32: six 4 mm steps took an armed rig from 15 mm to 39 mm)
SEQUENCE_EVERY_S = 1.5
CHAIN_GAP_S = 0.005
# signals: each ends the run SAFE or is ignored; a daemon still running this long after one
# ignored it. One every SIGNAL_EVERY_MAX_S at most, each at least once in any run.
SIGNALS = (signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2, signal.SIGQUIT, signal.SIGPIPE)
SIGNAL_EXIT_S = 8.0
SIGNAL_EVERY_MAX_S = 20.0
DESIRED_FORCE_TOL_N = 0.01  # the DBC's resolution


class Listener:
    """A bus client that sees every other client's frames: the simulator's sensor frames,
    the daemon's commands and the fuzzer's frames, which it tells apart from the genuine
    ones as the daemon must (flags, DBC, CRC, counter)."""

    def __init__(self, channel: str, i_max_a: float, f_range_n: tuple[float, float]) -> None:
        self.bus = open_bus("remote", channel)
        codec = Codec()
        self.parser = codec.parser()
        self.sensor_id = codec.layout("RigSensors").frame_id
        self.command_id = codec.layout("DamperCommand").frame_id
        self.actuator_id = codec.layout("ActuatorCommand").frame_id
        self.waveforms = codec.choices("ActuatorCommand", "Waveform")
        self.i_max_a = i_max_a
        self.f_range_n = f_range_n
        self.recent: collections.deque[list] = collections.deque(maxlen=ANSWER_WINDOW)
        self.commands = 0
        self.above_limit = 0
        self.force_out_of_range = 0
        self.active_unmatched = 0
        self.last_mode = 0  # of the latest DamperCommand: 1 ACTIVE
        # the latest ActuatorCommand: (waveform label, amplitude m, frequency Hz)
        self.actuator: tuple[str, float, float] | None = None
        self.latency_s: list[tuple[float, float]] = []  # (bridge time of the frame, latency)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.bus.shutdown()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.1)
            except can.CanError:
                return
            if msg is None or msg.is_extended_id or msg.is_remote_frame:
                continue
            if msg.arbitration_id == self.sensor_id:
                p = self.parser.parse_message(msg)
                if p.ok:
                    self.recent.append([p.counter, msg.timestamp, False])
            elif msg.arbitration_id == self.actuator_id:
                p = self.parser.parse_message(msg)
                if p.ok:
                    v = p.values
                    wave = self.waveforms[int(v["Waveform"])]
                    self.actuator = (wave, v["Amplitude"], v["Frequency"])
            elif msg.arbitration_id == self.command_id:
                p = self.parser.parse_message(msg)
                if not p.ok:
                    continue
                self.commands += 1
                v = p.values
                self.last_mode = int(v["Mode"])
                if v["CurrentSetpoint"] > self.i_max_a + 1e-4:
                    self.above_limit += 1
                lo, hi = self.f_range_n
                if not lo - DESIRED_FORCE_TOL_N <= v["DesiredForce"] <= hi + DESIRED_FORCE_TOL_N:
                    self.force_out_of_range += 1
                echo = int(v["SensorCounterEcho"])
                frame = next((f for f in self.recent if f[0] == echo and not f[2]), None)
                if frame is not None:
                    frame[2] = True
                    self.latency_s.append((frame[1], msg.timestamp - frame[1]))
                elif int(v["Mode"]) == 1:
                    self.active_unmatched += 1

    def latency_p99_us(self, t0: float, t1: float) -> tuple[float, int]:
        lat = np.array([d for t, d in self.latency_s if t0 <= t < t1])
        if not lat.size:
            return float("nan"), 0
        return float(np.percentile(lat, 99) * 1e6), int(lat.size)


class Requests:
    """Control requests over Zenoh; their replies counted as they come (Zenoh's thread).
    `session` is swapped for a new daemon's."""

    def __init__(self, session: zenoh.Session, rig: str) -> None:
        self.session = session
        self.key = keys(rig)["control"]
        self.sent_s: list[float] = []  # when each request left (time.monotonic())
        self.answered: list[bool] = []

    @property
    def sent(self) -> int:
        return len(self.sent_s)

    def _on_reply(self, i: int, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self.answered[i] = True

    def send(self, payload: str | bytes) -> None:
        self.answered.append(False)
        self.sent_s.append(time.monotonic())
        try:
            self.session.get(
                self.key,
                functools.partial(self._on_reply, len(self.sent_s) - 1),
                payload=payload,
                encoding=JSON,
                timeout=REQUEST_TIMEOUT_S,
            )
        except zenoh.ZError:  # the session closed: a daemon that did not come back
            return

    def unanswered(
        self, excused: list[tuple[float, float]], wait_s: float = REQUEST_TIMEOUT_S + 1.0
    ) -> int:
        """Requests without a reply, once the last could still have got one, but those sent
        in an `excused` window (a daemon ending on a signal, or starting again)."""
        time.sleep(wait_s)
        return sum(
            not ok and not any(a <= t <= b for a, b in excused)
            for t, ok in zip(self.sent_s, self.answered, strict=True)
        )

    def ask(self, request: dict) -> dict | None:
        try:
            replies = self.session.get(
                self.key, payload=json.dumps(request), encoding=JSON, timeout=REQUEST_TIMEOUT_S
            )
        except zenoh.ZError:  # the session closed: a daemon that did not come back
            return None
        for reply in replies:
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
        return None


class Holder:
    """The lease of the bench's last arm, renewed as a client that holds the rig renews it
    (`mrrig.rigio.lease`): the campaign's armed stretches last as long as it wants them."""

    def __init__(self, requests: Requests) -> None:
        self.requests = requests
        self.lease: Lease | None = None

    def _ask(self, payload: dict, _timeout_s: float) -> dict:
        reply = self.requests.ask(payload)
        if reply is None:
            raise ConnectionError("no answer")
        return reply

    def arm(self) -> dict | None:
        reply = self.requests.ask({"cmd": "arm"})
        if reply is not None and reply.get("lease"):
            self.release()
            self.lease = Lease(self._ask, reply, "fuzz")
        return reply

    def release(self) -> None:
        if self.lease is not None:
            self.lease.release()
            self.lease = None


SHOW_S = 0.6  # a chain's end held armed: the firmware's ramp (0.5 s) shows the motion


class Daemon:
    """The daemon's process, started again after a signal ended it, and a Zenoh session to
    its telemetry process; each start has its own recording and summary."""

    def __init__(self, config: Path, channel: str, endpoints: list[str], work: Path) -> None:
        self.config, self.channel, self.endpoints, self.work = config, channel, endpoints, work
        self.summaries: list[Path] = []
        self.proc: subprocess.Popen | None = None
        self.session: zenoh.Session | None = None

    def start(self, timeout_s: float = 60.0) -> zenoh.Session:
        n = len(self.summaries)
        self.summaries.append(self.work / f"daemon-{n}.json")
        cmd = [sys.executable, "-m", "mrrig", "-q", "run", "--config", str(self.config)]
        cmd += [
            "--bus-channel",
            self.channel,
            "--arm",
            "--record",
            str(self.work / f"fuzz-{n}.rrd"),
        ]
        cmd += ["--summary-json", str(self.summaries[-1])]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
        end = time.monotonic() + timeout_s
        while self.session is None:  # the daemon's telemetry process listens once it is ready
            try:
                self.session = zenoh.open(local_config("client", connect=self.endpoints))
            except zenoh.ZError:
                if self.proc.poll() is not None or time.monotonic() > end:
                    raise RuntimeError("the daemon did not come up") from None
                time.sleep(0.5)
        return self.session

    def wait_ready(self, requests: Requests, timeout_s: float = 60.0) -> None:
        end = time.monotonic() + timeout_s
        while requests.ask({"cmd": "status"}) is None:
            if self.proc is None or self.proc.poll() is not None or time.monotonic() > end:
                raise RuntimeError("the daemon did not answer")

    def close_session(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None


def signal_outcome(
    rc: int | None, last_active: bool, actuator_stopped: bool, summary: Path
) -> tuple[str, bool]:
    """What a signal did to the daemon (rc None: still running, it ignored it) and whether
    that is allowed: ended SAFE (exit code 0 or 1, its last DamperCommand SAFE, its last
    ActuatorCommand STOP, a summary written) or ignored."""
    if rc is None:
        return "ignored", True
    problems = []
    if rc not in (0, 1):
        problems.append(f"exit code {rc}")
    if last_active:
        problems.append("last command ACTIVE")
    if not actuator_stopped:
        problems.append("actuator not stopped")
    if not summary.exists():
        problems.append("no summary")
    if problems:
        return "ended, " + ", ".join(problems), False
    return f"ended SAFE (exit code {rc}, summary written)", True


def run(minutes: float, config: Path, sim_config: Path, seed: int, out: Path | None) -> int:
    rng = random.Random(seed)
    cfg = load_config(config)
    total_s = minutes * 60.0
    phase_s = min(PHASE_S, total_s / 4)
    fuzz_s = total_s - 2 * phase_s
    work = Path(tempfile.mkdtemp(prefix="mrrig-bench-fuzz-"))
    # the benchmark's daemon runs go into a catalog of their own, not the lab's
    os.environ[CATALOG_ENV] = str(work / "catalog.sqlite")
    daemon_config, endpoints = _daemon_config(config, cfg, work)
    port = find_free_port()
    channel = f"ws://127.0.0.1:{port}/"
    bridge = start_bridge(port)
    daemon = Daemon(daemon_config, channel, endpoints, work)
    sim: subprocess.Popen | None = None
    crashes: list[str] = []
    signals: list[dict[str, str]] = []
    excused: list[tuple[float, float]] = []  # requests sent here may go unanswered
    listener = fuzz_bus = holder = None
    try:
        requests = Requests(daemon.start(), cfg.rig.name)
        holder = Holder(requests)
        daemon.wait_ready(requests)
        sim_stats = work / "sim.json"
        sim = subprocess.Popen(
            [sys.executable, "-m", "firmware_sim", "--config", str(sim_config),
             "--bus-channel", channel, "--stats", str(sim_stats),
             # its own frames' bus timestamps: a frame's age counts from there (spec/system.md)
             "--measure-echo",
             # a net for an orphan, not an end: a loaded machine stretches the phases
             "--duration", str(3 * total_s + 120)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        listener = Listener(channel, cfg.loop.i_max_a, cfg.loop.f_range_n)
        listener.start()
        fuzz_bus = open_bus("remote", channel)
        packer = Codec().packer("RIG")
        sensors = packer.encode(
            "RigSensors",
            {"ActuatorEnabled": 1, "LimitTripped": 0, "EStop": 0, "SensorFault": 0,
             "Displacement": 0.001, "Force": 10.0},
        )  # fmt: skip
        time.sleep(3.0)  # the simulator streams, the daemon arms
        frames = 0
        rearms = 0
        sequences: collections.Counter[str] = collections.Counter()
        force_ref_key = keys(cfg.rig.name)["force_ref"]

        def alive() -> None:
            if sim.poll() is not None and not any("firmware_sim" in c for c in crashes):
                crashes.append(f"firmware_sim exited with code {sim.returncode}")

        def restart() -> bool:
            daemon.close_session()
            try:
                requests.session = daemon.start()
                daemon.wait_ready(requests)
            except RuntimeError as exc:
                crashes.append(f"daemon: {exc} after a restart")
                return False
            return True

        def judge(sig: signal.Signals, rc: int | None) -> None:
            if rc is not None:
                time.sleep(0.5)  # its last frames through the bridge to the listener
            outcome, ok = signal_outcome(
                rc,
                listener.last_mode != 0,
                listener.actuator is not None and listener.actuator[0] == "STOP",
                daemon.summaries[-1],
            )
            signals.append({"signal": sig.name, "outcome": outcome})
            if not ok:
                crashes.append(f"daemon on {sig.name}: {outcome}")

        def rearm() -> bool:
            requests.ask({"cmd": "set_controller", "name": "network_inversion"})
            requests.ask({"cmd": "set_profile", "kind": "bouc_wen", "current_a": 0.8,
                          "current_amp_a": 0.5})  # fmt: skip
            requests.ask({"cmd": "reset"})  # re-arming after a fault: acknowledged
            return bool((holder.arm() or {}).get("ok"))

        def sequence(kind: str) -> None:
            """One chain of small changes 5 ms apart: disarmed, the motion or the reference
            it starts from; armed (set_profile's: after the chain, with what it left); the
            chain; held armed for SHOW_S."""
            sequences[kind] += 1
            requests.ask({"cmd": "disarm"})
            if kind in ("amplitude", "frequency"):
                requests.ask(BASE_MOTION)
            elif kind == "force_ref":
                requests.ask({"cmd": "set_profile", "kind": "zenoh", "timeout_s": 1.0})
                daemon.session.put(force_ref_key, "0")  # not stale when armed
            steps = chain(kind, rng)
            if kind != "set_profile":
                requests.ask({"cmd": "reset"})
                holder.arm()
            for step in steps:
                if kind == "force_ref":
                    daemon.session.put(force_ref_key, json.dumps(step))
                else:
                    requests.send(json.dumps(step))
                time.sleep(CHAIN_GAP_S)
            if kind == "set_profile":
                requests.ask({"cmd": "reset"})
                holder.arm()
            time.sleep(SHOW_S)
            if kind == "force_ref":  # back to the reference the campaign runs on
                requests.ask({"cmd": "disarm"})
                rearm()

        # ---- quiet, then the burst: the answer latency as the firmware sees it
        t_quiet = time.time()
        time.sleep(phase_s)
        t_burst = time.time()
        big = json.dumps({"cmd": "status", "pad": "x" * 1_000_000})
        deep = '{"cmd": "status", "x": ' + "[" * 1000 + "]" * 1000 + "}"
        every_bad = BURST_STATUS_HZ // BURST_BAD_HZ
        for _ in range(round(phase_s)):
            second = time.monotonic()
            requests.send(big)
            for k in range(BURST_STATUS_HZ):
                requests.send(deep if k % every_bad == 0 else '{"cmd": "status"}')
                if k % 50 == 0:  # evenly over the second
                    time.sleep(max(0.0, second + k / BURST_STATUS_HZ - time.monotonic()))
            alive()
            time.sleep(max(0.0, second + 1.0 - time.monotonic()))
        t_fuzz = time.time()
        burst_sent = requests.sent
        # ---- fuzz: frames, requests, sequences and signals, until every signal had its turn
        end = time.monotonic() + fuzz_s
        signal_every_s = min(SIGNAL_EVERY_MAX_S, fuzz_s / len(SIGNALS))
        to_send: list[signal.Signals] = []
        unsent = set(SIGNALS)  # the last of them ends the campaign, in the daemon's stead
        to_chain: list[str] = []
        pending: tuple[signal.Signals, float] | None = None  # (signal, sent at)
        next_req = next_arm = next_bad = next_seq = time.monotonic()
        next_signal = time.monotonic() + signal_every_s / 2
        # clients that hold the rig, killed at random (issue 40): their lease must lapse
        killed = fuzz_lease.KilledClients()
        client_z = fuzz_lease.client_config(endpoints, work)
        next_kill = time.monotonic() + fuzz_lease.KILL_EVERY_S / 2
        # a client's step on a faulty bus (issue 40): aborted at the re-arm cap
        faulty = fuzz_faulty_bus.FaultyBus()
        next_faulty = time.monotonic() + min(fuzz_faulty_bus.FAULTY_EVERY_S, fuzz_s) / 2
        t_next = time.monotonic()
        armed = False
        while (now := time.monotonic()) < end or len(unsent) > 1 or pending is not None:
            # after a step that blocked (a restart, a sequence): on at the rates, no catch-up
            t_next, next_req = max(t_next, now - 0.1), max(next_req, now - 0.1)
            if now >= t_next:
                bad = now >= next_bad
                if bad:
                    next_bad = now + BAD_SENSORS_PERIOD_S
                fuzz_bus.send(junk_frame(rng, sensors, bad))
                frames += 1
                t_next += 1.0 / JUNK_HZ
            if now >= next_req:
                requests.send(random_request(rng))
                next_req += 1.0 / REQUESTS_HZ
            if pending is not None:
                sig, sent_s = pending
                rc = daemon.proc.poll()
                if rc is not None or now - sent_s > SIGNAL_EXIT_S:
                    judge(sig, rc)
                    pending = None
                    if rc is not None and not restart():
                        break
                    excused[-1] = (excused[-1][0], time.monotonic())
                    next_signal = time.monotonic() + signal_every_s
                    next_arm = next_seq = time.monotonic()
            elif daemon.proc.poll() is not None:  # no signal: a crash
                crashes.append(f"daemon exited with code {daemon.proc.returncode}")
                excused.append((now - REQUEST_TIMEOUT_S, now))
                if not restart():
                    break
                excused[-1] = (excused[-1][0], time.monotonic())
            elif now >= next_signal and (now < end or len(unsent) > 1):
                if not to_send:
                    to_send = rng.sample(SIGNALS, len(SIGNALS))
                if now >= end:  # one that had no turn yet
                    to_send.sort(key=lambda s: s in unsent)
                sig = to_send.pop()
                unsent.discard(sig)
                excused.append((now - REQUEST_TIMEOUT_S, float("inf")))
                daemon.proc.send_signal(sig)
                pending = (sig, now)
            elif now >= next_kill and now < end:
                holder.release()  # the killed client's lease is the only one
                lease_s = cfg.control.lease_timeout_s
                fuzz_lease.kill_a_client(requests.ask, cfg.rig.name, client_z, lease_s, rng, killed)
                next_kill = time.monotonic() + fuzz_lease.KILL_EVERY_S
                next_arm = time.monotonic()
            elif now >= next_faulty and now < end:
                holder.release()  # the client's step holds the rig
                fuzz_faulty_bus.faulty_bus_step(
                    requests.ask, cfg.rig.name, client_z, sim.pid, work, faulty
                )
                next_faulty = time.monotonic() + fuzz_faulty_bus.FAULTY_EVERY_S
                next_arm = time.monotonic()
            elif now >= next_arm:
                next_arm += 1.0
                alive()
                st = requests.ask({"cmd": "status"})
                armed = st is not None and st.get("status", {}).get("state") == "ARMED"
                if st is not None and not armed and rearm():
                    rearms += 1
            elif armed and now >= next_seq:
                next_seq = now + SEQUENCE_EVERY_S
                if not to_chain:
                    to_chain = rng.sample(CHAINS, len(CHAINS))
                sequence(to_chain.pop())
            time.sleep(max(0.0, min(t_next, next_req) - time.monotonic()))
        unanswered = requests.unanswered(excused)
        alive()
        status = (requests.ask({"cmd": "status"}) or {}).get("status", {})
        if status.get("telemetry_restarts"):
            crashes.append(f"telemetry restarted {status['telemetry_restarts']} times")
        for sig in (*unsent, signal.SIGTERM):  # the last signal, then SIGTERM if ignored
            if daemon.proc.poll() is not None:
                break
            daemon.proc.send_signal(sig)
            try:
                rc = daemon.proc.wait(timeout=SIGNAL_EXIT_S if sig in unsent else 60)
            except subprocess.TimeoutExpired:
                rc = None
            if sig in unsent:
                judge(sig, rc)
            elif rc not in (0, 1):
                crashes.append(f"daemon exited with code {rc}")
        sim.send_signal(signal.SIGTERM)  # it was to stream on
        if sim.wait(timeout=60) != 0 and not any("firmware_sim" in c for c in crashes):
            crashes.append(f"firmware_sim exited with code {sim.returncode}")
        listener.stop()
        st = json.loads(sim_stats.read_text())
        runs = [json.loads(p.read_text()) for p in daemon.summaries if p.exists()]
        beyond = motion_beyond_limits(st["armed_motion"], cfg.control.armed_amplitude_step_m)
        q99, nq = listener.latency_p99_us(t_quiet, t_burst)
        b99, nb = listener.latency_p99_us(t_burst, t_fuzz)
        result = {
            "minutes": minutes,
            "frames_fuzzed": frames,
            "requests": requests.sent,
            "requests_unanswered": unanswered,
            "burst": {"requests": burst_sent},
            "sequences": dict(sequences),
            "signals": signals,
            "daemon_starts": len(daemon.summaries),
            "crashes": crashes,
            "commands": listener.commands,
            "commands_above_limit": listener.above_limit,
            "max_commanded_current_a": st["max_commanded_current_a"],
            "desired_force_out_of_range": listener.force_out_of_range,
            "armed_stretches": len(st["armed_motion"]),
            "motion_beyond_limits": len(beyond),
            "motion_beyond": beyond[:10],
            "active_applied_to_stale": st["answers"]["active_applied_to_stale"],
            "active_applied_to_invalid": st["answers"]["active_applied_to_invalid"],
            "applied_active_age_us_max": st["applied_active_age_us"]["max"],
            "late_commands_dropped": st["late_commands"],
            "active_answers_stale_at_bus": st["answers"]["active_to_stale"],
            "active_answers_invalid": listener.active_unmatched,
            "rearms": rearms,
            **killed.counts(),
            **faulty.counts(),
            "answer_latency_p99_us": {"quiet": q99, "burst": b99, "ratio": b99 / q99},
            "answer_latency_frames": {"quiet": nq, "burst": nb},
            "daemon": {
                k: sum(d.get(k) or 0 for d in runs)
                for k in ("frames_ignored", "sensor_frames_invalid", "stale_frames")
            },
            "faults": collections.Counter(
                f["reason"].split(":")[0][:40] for d in runs for f in d["faults"]
            ),
        }
    finally:
        if holder is not None:
            holder.release()
        if fuzz_bus is not None:
            fuzz_bus.shutdown()
        daemon.close_session()
        for p in (daemon.proc, sim):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
        stop_bridge(bridge)
    # every daemon start's run in the catalog, or journalled and replayed into it now
    recordings = [work / f"fuzz-{n}.rrd" for n in range(result["daemon_starts"])]
    missing = fuzz_faulty_bus.runs_missing(recordings, Path(os.environ[CATALOG_ENV]))
    result["recordings"], result["runs_missing_from_catalog"] = len(recordings), missing
    result["observer_misuse"] = fuzz_observer.run(work, rng, minutes)
    print(report(result))
    print(fuzz_observer.report(result["observer_misuse"]))
    if out is not None:
        out.write_text(json_text.dumps(result, indent=2))
    return 1 if failures(result, cfg.loop.i_max_a) else 0


def _daemon_config(config: Path, cfg: Any, work: Path) -> tuple[Path, list[str]]:
    """The daemon's config with a Zenoh config of its own on a free port of 127.0.0.1, and
    the endpoints a client connects to."""
    endpoints = [f"tcp/127.0.0.1:{find_free_port()}"]
    zenoh_file = work / "zenoh-daemon.json5"
    zenoh_file.write_text(
        json.dumps(
            {
                "mode": "peer",
                "listen": {"endpoints": endpoints},
                "scouting": {"multicast": {"enabled": False}},
            }
        )
    )
    text = config.read_text()
    old = f'"{cfg.telemetry.zenoh_config}"'
    if old not in text or not cfg.telemetry.enabled:
        raise ValueError(f"{config}: telemetry.zenoh_config: set and enabled, for the fuzzer")
    path = work / "daemon.toml"
    path.write_text(text.replace(old, f'"{zenoh_file}"'))
    return path, endpoints


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig bench fuzz", description=__doc__
    )
    ap.add_argument("--minutes", type=positive, default=10.0, help="length of the campaign")
    ap.add_argument("--config", type=Path, default=Path("configs/rig.toml"))
    ap.add_argument("--sim-config", type=Path, default=Path("configs/sim.toml"))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", type=output_file, help="also write the counts as JSON")
    args = ap.parse_args(argv)
    from mrrig.cli.demo import SIM_MODEL, ensure_sim_model

    ensure_sim_model(SIM_MODEL)  # the configs' model: trained on first use, as the demo does
    try:
        return run(args.minutes, args.config, args.sim_config, args.seed, args.json)
    except RuntimeError as exc:  # the daemon did not come up at the start
        log.error("error: %s", exc)
        return 1
