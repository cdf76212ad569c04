"""The rig daemon: one DamperCommand per valid RigSensors frame.

read -> check -> Kalman -> force reference -> controller -> clamp -> send, paced by the sensor
frames, in one thread that never waits on telemetry: samples, events and status are handed to
the sidecar process (Zenoh + Rerun) through a non-blocking pipe. The loop owns the bus, the
packer, the controller and the safety state; control requests are checked and prepared by
`mrrig.rigio.control.ControlWorker` in its own thread, and the loop swaps in what it prepared
between frames.

Here: the daemon's state, built from its config, and its loop (`run`, one pass per received
frame or timeout). Its parts, each a module of its own:
  - `frame_path`: the frame's path, `on_frame` -> `cycle` -> the command sent;
  - `sensor_watch`: the sensor frames' arrival (the first one due, gaps, counter timing);
  - `control_requests`: control requests applied between frames, the arm's lease, force_ref;
  - `sidecar_watch`: the telemetry process, started, heard and restarted once;
  - `shutdown`: SAFE, the actuator to rest, the summary;
  - `batches`: the sample rows handed on; `frame_age`: a frame's wait at the bus;
  - `build`: the controller and reference a config names; `run_command`: `mrrig run`.
"""

from __future__ import annotations

import functools
import gc
import logging
import math
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from mrrig.config import DaemonConfig
from mrrig.config_gaps import config_gaps
from mrrig.loop import hil_loop
from mrrig.loop import reference as ref
from mrrig.loop.batches import SampleBatches
from mrrig.loop.build import build_controller, build_reference, kalman
from mrrig.loop.collector import CollectorOffWhileArmed
from mrrig.loop.control_requests import ControlRequests
from mrrig.loop.coverage import controller_envelope
from mrrig.loop.detectors import Detectors
from mrrig.loop.exit_codes import Exit
from mrrig.loop.frame_age import FrameAge
from mrrig.loop.frame_path import FramePath
from mrrig.loop.kernel_stalls import KernelStalls, stall_event
from mrrig.loop.realtime import keep_off_cpu, make_realtime
from mrrig.loop.safety import Fault, Limits, Supervisor
from mrrig.loop.sensor_watch import SensorWatch
from mrrig.loop.shutdown import shut_down
from mrrig.loop.sidecar_watch import SidecarWatch
from mrrig.loop.slew import SlewLimit
from mrrig.rigio import sdnotify
from mrrig.rigio.canbus.bus import open_bus
from mrrig.rigio.canbus.profile import ProfileError, load_profile
from mrrig.rigio.canbus.profile_limits import daemon_limits
from mrrig.rigio.control import ControlWorker, Pending, Preparer
from mrrig.rigio.run_identity import IN_FORCE, STATUS_IDENTITY, run_identity

log = logging.getLogger(__name__)

ACTUATOR_PERIOD_S = 0.1
STATUS_PERIOD_S = 0.1  # to the sidecar, which answers `status` requests and publishes at 1 Hz
# the longest a control-thread computation holds the GIL against the loop (Python's default
# of 5 ms is two and a half sensor periods)
SWITCH_INTERVAL_S = 0.0002
WAVEFORMS = {"stop": "STOP", "sine": "SINE", "random": "RANDOM", "hold": "HOLD", "stream": "STREAM"}
# a stop is honoured within the spec's sensor timeout (3 periods) whatever the config's: the
# loop never waits longer than this for a frame
SPEC_TIMEOUT_PERIODS = 3


def loop_realtime(cfg: DaemonConfig) -> None:
    """SCHED_FIFO, CPU affinity, locked memory and idle CPUs that poll, where permitted; a
    warning where not."""
    make_realtime(
        50 if cfg.loop.realtime else 0,
        cpu=cfg.loop.cpu,
        lock_memory=cfg.loop.realtime,
        who="daemon",
        wakeup_latency_us=0 if cfg.loop.realtime and cfg.loop.poll_idle else None,
    )


class Daemon(FramePath):
    """The loop and its state; `run()` until stopped, then a SAFE command and a summary."""

    def __init__(
        self, cfg: DaemonConfig, record_path: Path | None = None, keep_batches: bool = False
    ) -> None:
        """`keep_batches`: keep every sample batch for `batches.handed_over` (an in-process
        consumer such as characterize); otherwise the loop keeps none and its memory stays
        fixed."""
        self.cfg = cfg
        self.period_s = cfg.loop.period_s
        # the rig profile: the DBC and its roles ([can]); the start-up line names what is off
        self.profile = load_profile(
            cfg.can.dbc, cfg.can.signals, cfg.loop.period_s, cfg.source, daemon_limits(cfg)
        )
        if self.profile.protections_off:
            log.warning("%s", self.profile.startup_line())
        if cfg.actuator.waveform == "stream" and (why := self.profile.stream_refusal()):
            raise ProfileError(why)
        self.codec = self.profile.codec
        # who runs what, where and when: into the recording and the run catalog (the sidecar)
        self.identity = run_identity(cfg, self.codec.dbc_path)
        self.in_force = {k: self.identity[k] for k in IN_FORCE}  # set_model / set_controller
        self.packer = self.profile.packer()
        self._own_messages = frozenset(self.packer.messages)
        self._sensor_msg = self.profile.sensor_message
        self._status_msg = self.profile.status_message
        self._status_in_sensors = self._status_msg == self._sensor_msg
        self.parser = self.codec.parser()
        self.controller = build_controller(cfg)
        # the model's training envelope: each frame is marked against it (`coverage`)
        self.envelope = controller_envelope(self.controller)
        build_ref = functools.partial(build_reference, numerics=cfg.loop.numerics)
        self.reference = build_ref(cfg.reference, self.period_s)
        try:
            ref.check_in_range(self.reference, cfg.loop.f_range_n)
        except ref.ForceReferenceError as exc:
            raise ref.ForceReferenceError(f"{cfg.source}: {exc}") from None
        # a hybrid simulation ([hil]): its law's desired force is the force reference
        self.hil = None
        if cfg.hil.scenario is not None:
            self.hil = hil_loop.HilLoop(cfg, self.profile, self.packer, self._set_waveform)
            self.reference = self.hil.reference
        self.kf = kalman(self.period_s, cfg.estimator.q, cfg.estimator.r0_m2, cfg.loop.numerics)
        self.supervisor = Supervisor(
            Limits(
                cfg.loop.x_range_m,
                cfg.loop.f_range_n,
                cfg.loop.bad_frame_budget,
                cfg.loop.lost_frame_budget,
                cfg.loop.budget_window_s,
            )
        )
        self.detectors = Detectors(cfg.detectors)
        self.actuator = cfg.actuator
        # the motion the rig was armed with: armed changes are bounded from it, not per request
        self.actuator_at_arm = cfg.actuator
        self.exit_code = Exit.OK
        # why the daemon raised, where it did: the summary says so (the catalog: `crashed`)
        self.crashed = ""
        self.frame_age = FrameAge()  # of each frame at the bus
        self.control = ControlWorker(Preparer(self, build_controller, build_ref))
        self.control.on_start = self._control_thread_started
        self.stop_reason = ""
        self._stop = False
        self.started = threading.Event()  # set when the loop listens for frames
        self._safe_sent_at_stop = False  # the stop's SAFE command answered a sensor frame
        self.bus = None
        self.tap = None  # canlog.FrameTap: every frame for the bus log, when one is asked for
        if cfg.recording.can_log is not None:
            from mrrig.rigio.canlog import FrameTap

            self.tap = FrameTap()
        self.sidecar = SidecarWatch(self, record_path)  # the telemetry process
        self.requests = ControlRequests(self)  # applied between frames; the arm's lease
        self.t0 = time.perf_counter()
        self._cpu0 = time.process_time()
        self.counters = {
            "frames_received": 0,
            "sensor_frames_valid": 0,
            "sensor_frames_invalid": 0,
            "status_frames": 0,
            "commands_sent": 0,
            "commands_active": 0,
            "safe_commands_unprompted": 0,
            "send_failures": 0,
            "foreign_commands": 0,
            "lost_frames": 0,
            "estimate_restarts": 0,  # after a gap longer than the sensor timeout
            "frames_ignored": 0,  # 29-bit, remote, error and unknown-id frames
            "stale_frames": 0,  # answered SAFE: older than loop.max_frame_age_s
            "sensor_frames_early": 0,  # counter ahead of the time since the last frame
            "telemetry_dropped": 0,
            "force_refs_received": 0,  # on force_ref, with the zenoh reference
            "force_refs_clamped": 0,  # of those, outside loop.f_range_n (clamped into it)
            "can_log_dropped": 0,  # frames the pipe to the bus log's writer could not take
            "leases_lapsed": 0,  # armed by a client that stopped renewing its lease
            "commands_slew_limited": 0,  # moved by loop.max_current_slew_a_per_s
        }
        self.slew = SlewLimit(cfg.loop.max_current_slew_a_per_s, cfg.loop.period_s)
        self.events: list[dict] = []
        self.batches = SampleBatches(cfg.loop.telemetry_batch, keep_batches)
        # the loop thread's run-queue delay and the VM's steal, pass by pass
        self.kernel_stalls = KernelStalls(self.period_s)
        self._send_call_s = math.nan  # the frame's send() call, a part of its latency_us
        self._last_sensor_t = None
        self._restart_next, self._gap_s = False, 0.0  # the estimate, after a gap
        self._frame_age_limit_s = cfg.loop.frame_age_limit_s
        self._first_sensor_t = 0.0
        self.sensors = SensorWatch(
            self.profile, self.supervisor, self.counters, self.period_s, cfg.loop.budget_window_s
        )
        self._arm_pending = False
        self._last_counter = 0
        self._i_meas = 0.0
        self._temp_degc = math.nan  # the damper's, from RigStatus
        self.last_x = 0.0  # the latest displacement estimate, m
        self._last_status_sent = -math.inf
        self._last_actuator_sent = -math.inf
        self._status_key = None
        self.notifier = sdnotify.Notifier.from_env()  # systemd's READY=1 and watchdog
        self._targets: list[float] = []  # desired forces of the coming frames (`_targets_now`)
        self._collector = CollectorOffWhileArmed()  # no automatic collection while armed

    # ---- time, events and status --------------------------------------------------------
    def now(self) -> float:
        return time.perf_counter() - self.t0

    def _emit(self, events: list[dict]) -> None:
        for e in events:
            self.events.append(e)
            level = logging.INFO if e["level"] == "info" else logging.WARNING
            log.log(level, "%s: %s", e["kind"], e["reason"])
            if self.sidecar.link is not None:
                self.sidecar.link.send_event(e)
        if events:
            self._send_status(force=True)

    def status(self) -> dict[str, Any]:
        s, failed = self.supervisor, self.sidecar.recording_failed
        return {
            "rig": self.cfg.rig.name,
            "state": s.state.name,
            "armed": s.active,
            "controller": self.controller.name,
            "adaptation": self.controller.adaptation_state(),
            "reference": self.reference.kind,
            "hil": self.hil.status() if self.hil is not None else None,
            "fault": s.fault.value if s.fault else None,
            "fault_reason": s.reason,
            "firmware_blocking": s.firmware_blocking,
            "recording": "failed: " + failed if failed else None,
            "telemetry_restarts": self.sidecar.restarts,
            "identity": {k: self.identity[k] for k in STATUS_IDENTITY} | self.in_force,
            "t": self.now(),
            **self.counters,
        }

    def _send_status(self, force: bool = False) -> None:
        t = self.now()
        key = (self.supervisor.state, self.supervisor.reason, self.controller.name)
        if force or key != self._status_key or t - self._last_status_sent >= STATUS_PERIOD_S:
            self._status_key = key
            self._last_status_sent = t
            if self.sidecar.link is not None:
                self.sidecar.link.send_status(self.status())

    def _set_waveform(self, waveform: str, amplitude_m: float) -> None:
        """The HIL's actuator changes (STREAM, HOLD, STOP): sent after this pass's frame."""
        self.actuator = replace(
            self.actuator, waveform=waveform, amplitude_m=amplitude_m, frequency_hz=0.0
        )
        self._last_actuator_sent = -math.inf

    def _send_actuator(self) -> None:
        a = self.actuator
        if self.profile.actuator_message is None:  # the lab's firmware drives its actuator
            self._last_actuator_sent = self.now()
            return
        self._send(
            self.profile.actuator_message,
            {
                "Waveform": WAVEFORMS[a.waveform],
                "Amplitude": a.amplitude_m,
                "Frequency": a.frequency_hz,
            },
        )
        self._last_actuator_sent = self.now()

    # ---- hand-off ----------------------------------------------------------------------
    def _flush_samples(self) -> None:
        batch = self.batches.take()
        link = self.sidecar.link
        if link is not None and not link.send_samples(batch):
            self.counters["telemetry_dropped"] += len(batch)
        self._flush_frames()

    def _flush_frames(self, force: bool = False) -> None:
        frames = self.tap.take(force) if self.tap is not None else None
        if frames is not None and self.sidecar.link is not None:
            self.counters["can_log_dropped"] += self.sidecar.link.send_frames(frames)

    # ---- control requests (from Zenoh through the sidecar, or in process) ----------------
    def submit(self, req: dict[str, Any] | bytes, reply) -> None:
        """Queue a control request (any thread, never blocks); `reply(dict)` is called from
        the control thread with the answer once the loop has applied it, or refused it."""
        self.control.submit(req, reply)

    def request(self, req: dict[str, Any], timeout_s: float = 5.0) -> dict[str, Any]:
        """A control request from another thread of this process (characterize, tests):
        blocks that thread until the loop has answered. Never call it from the loop."""
        pending = Pending()
        self.control.submit(req, pending)
        return pending.wait(timeout_s)

    def _control_thread_started(self) -> None:
        keep_off_cpu(threading.get_native_id(), self.cfg.loop.cpu, "control thread")

    # ---- run ---------------------------------------------------------------------------
    def request_stop(self, reason: str) -> None:
        self.stop_reason = reason
        self._stop = True

    def run(self) -> dict[str, Any]:
        cfg = self.cfg
        # the sidecar first: a start-up that fails (its Zenoh port taken, a second daemon of
        # this rig's name alive) must not have touched the bus, where another daemon may own
        # the rig (its ActuatorCommand STOP on the way out faulted the running daemon)
        if self.sidecar.wanted():
            self.sidecar.start()
        try:
            self.bus = open_bus(cfg.bus.interface, cfg.bus.channel, **cfg.bus.options)
        except BaseException as exc:
            self.crashed = f"{type(exc).__name__}: {exc}"
            shut_down(self)
            raise
        try:
            # started before the loop takes real-time priority: it runs at normal priority
            sys.setswitchinterval(SWITCH_INTERVAL_S)
            self.control.start()
            self.controller.reset(1)
            # collect and freeze before raising the priority: a full collection at
            # SCHED_FIFO would starve the simulator and the bridge on a 2-core machine
            gc.collect()
            gc.freeze()
            loop_realtime(cfg)
            self.frame_age.discard_backlog(self.bus, cfg.loop.frame_age_limit_s)
            # the loop's time zero (and its duration) from its first live frame on
            self.t0 = time.perf_counter()
            self._cpu0 = time.process_time()
            self._arm_pending = cfg.loop.arm_on_start
            self._loop()
        except BaseException as exc:
            self.crashed = f"{type(exc).__name__}: {exc}"
            raise
        finally:
            self._collector.close()
            shut_down(self)
        return self.summary

    def _loop(self) -> None:
        cfg = self.cfg
        recv = self.bus.recv
        # the wait for a frame, and for one to answer SAFE after a stop: the spec's sensor
        # timeout at most, so that a long configured timeout cannot make the loop deaf to a
        # stop or to control requests (check_timeout still uses the configured one)
        timeout_s = min(cfg.loop.timeout_periods, SPEC_TIMEOUT_PERIODS) * self.period_s
        end = None if cfg.loop.duration_s is None else self.t0 + cfg.loop.duration_s
        self._send_actuator()
        self.started.set()
        self.notifier.ready(f"rig {cfg.rig.name}: listening on {cfg.bus.channel}")
        log.info("loop running: one command per sensor frame")
        for line in config_gaps(cfg):  # a constant reference, an actuator that does not move
            log.warning("%s", line)
        stop_deadline = None
        self.kernel_stalls.start(self.now())  # this thread's: the loop's
        while not self._safe_sent_at_stop:
            if self._stop and stop_deadline is None:
                stop_deadline = time.perf_counter() + timeout_s
            if stop_deadline is not None and time.perf_counter() > stop_deadline:
                break  # no sensor frame to answer: shut_down sends SAFE on its own
            try:
                msg = recv(timeout=timeout_s)
            except Exception as exc:  # noqa: BLE001 - a dead bus stops the loop safely
                self._emit(self.supervisor.trip(self.now(), Fault.BUS_ERROR, f"receive: {exc}"))
                self.exit_code = Exit.BUS_LOST
                self.request_stop(f"bus error: {exc}")
                break
            t_rx = time.perf_counter()
            self.notifier.pet(t_rx)
            # a change prepared before this frame came applies to it
            self.requests.apply_next()
            if t_rx > self.requests.lease.deadline:
                self.requests.lease_lapsed(t_rx)
            if msg is not None:
                self.on_frame(msg, t_rx, self.frame_age.queued_s(msg))
            self.check_timeout(t_rx)
            t = t_rx - self.t0
            if self.sidecar.link is not None:
                self.sidecar.poll(t_rx)
                self.sidecar.watch(t_rx)
            if t - self._last_actuator_sent >= ACTUATOR_PERIOD_S:
                self._send_actuator()
            self._send_status()
            self._read_kernel_stalls()
            self._collector.after_pass(self.supervisor.active)
            if end is not None and t_rx >= end:
                self.request_stop(f"duration {cfg.loop.duration_s:g} s reached")

    def _read_kernel_stalls(self) -> None:
        """Once a pass, after the frame's command: the run-queue delay and steal since the
        previous pass; a pass that lost a window's worth is an event of the recording."""
        window = self.kernel_stalls.read(self.now())
        if window is not None and self.sidecar.link is not None:
            self.sidecar.link.send_event(stall_event(window))
