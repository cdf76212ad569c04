"""The rig daemon: one DamperCommand per valid RigSensors frame.

read -> check -> Kalman -> force reference -> controller -> clamp -> send, paced by the sensor
frames, in one thread that never waits on telemetry: samples, events and status are handed to
the sidecar process (Zenoh + Rerun) through a non-blocking pipe. The loop owns the bus, the
packer, the controller and the safety state; control requests are checked and prepared by
`mrrig.rigio.control.ControlWorker` in its own thread, and the loop swaps in what it prepared
between frames.

`mrrig run --config configs/rig.toml`
"""

from __future__ import annotations

import argparse
import functools
import gc
import logging
import math
import resource
import signal
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from mrrig import json_text
from mrrig.cli_args import HelpFormatter, add_bus_options, output_file, positive
from mrrig.config import DaemonConfig, ReferenceSection, load_config
from mrrig.config_gaps import config_gaps
from mrrig.errors import MrrigError
from mrrig.loop import hil_loop
from mrrig.loop import reference as ref
from mrrig.loop.controllers import (
    CONTROLLERS,
    FORWARD_INPUTS,
    ControlInput,
    Controller,
    ControllerSettings,
    make_controller,
)
from mrrig.loop.coverage import controller_envelope
from mrrig.loop.detectors import Detectors
from mrrig.loop.estimation import RealtimeKalman
from mrrig.loop.inversion import DEFAULT_CONTINUITY
from mrrig.loop.kernel_stalls import KernelStalls, stall_event
from mrrig.loop.lease import PATH_QUIET_S, ArmLease
from mrrig.loop.mlp import MLP, ModelError
from mrrig.loop.model_fit import RigUnits, check_cost, check_period, check_units
from mrrig.loop.model_plausibility import self_check
from mrrig.loop.realtime import keep_off_cpu, leave_realtime, make_realtime
from mrrig.loop.safety import Fault, Limits, Supervisor
from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.loop.slew import SlewLimit, loop_command
from mrrig.loop.summary import (
    LATENCY_BIN_US,
    LATENCY_PARTS,
    LATENCY_TOP_US,
    Histogram,
    SummaryAccumulator,
    format_summary,
)
from mrrig.loop.twin_model import TwinModel, load_forward_model
from mrrig.rigio import sdnotify
from mrrig.rigio.canbus.bus import open_bus
from mrrig.rigio.canbus.codec import Codec
from mrrig.rigio.canbus.profile import ProfileError, load_profile
from mrrig.rigio.canbus.profile_limits import daemon_limits
from mrrig.rigio.control import (
    Change,
    ControlWorker,
    Pending,
    Preparer,
    RequestError,
    check_actuator_step,
    settings_in_force,
)
from mrrig.rigio.ipc import LoopEnd, Msg, ReplyWriter, make_channel
from mrrig.rigio.run_identity import IN_FORCE, STATUS_IDENTITY, run_identity
from mrrig.rigio.zenoh_config import check_secure, load_zenoh_config
from mrrig.typed_config import ConfigError

log = logging.getLogger(__name__)

ACTUATOR_PERIOD_S = 0.1
STATUS_PERIOD_S = 0.1  # to the sidecar, which answers `status` requests and publishes at 1 Hz
# the longest a control-thread computation holds the GIL against the loop (Python's default
# of 5 ms is two and a half sensor periods)
SWITCH_INTERVAL_S = 0.0002
SIDECAR_START_S = 20.0  # a new telemetry process's first heartbeat may take this long
MAX_SIDECAR_RESTARTS = 1
MAX_REPLAYED_EVENTS = 20  # events a restarted telemetry process is told again
CLOCK_SANE_S = 60.0  # a frame timestamp further off than this is not on this machine's clock
WAVEFORMS = {"stop": "STOP", "sine": "SINE", "random": "RANDOM", "hold": "HOLD", "stream": "STREAM"}
# importing rerun and zenoh and opening both, on a loaded 2-core machine; a live_url that
# nothing listens on alone blocks the recorder about 6 s
SIDECAR_START_TIMEOUT_S = 30.0


# each ends a run as SIGTERM does (SAFE, the actuator stopped, the summary, the recording
# closed): SIGHUP is an ssh session that dropped, SIGQUIT a Ctrl-\\, SIGUSR1/2 a stray kill;
# their default actions killed the daemon with its last command ACTIVE. SIGPIPE stays ignored
# (Python's choice): a reader that went away is an error on that write, not a stop
STOP_SIGNALS = (
    signal.SIGINT,
    signal.SIGTERM,
    signal.SIGHUP,
    signal.SIGQUIT,
    signal.SIGUSR1,
    signal.SIGUSR2,
)
# a stop is honoured within the spec's sensor timeout (3 periods) whatever the config's: the
# loop never waits longer than this for a frame
SPEC_TIMEOUT_PERIODS = 3
# the faults of the error detectors' disarm and stop actions
DETECTOR_FAULTS = {
    "tracking_error": Fault.TRACKING_ERROR,
    "velocity": Fault.OVER_VELOCITY,
    "temperature": Fault.OVER_TEMPERATURE,
}
MAX_IDS_NAMED = 8  # CAN IDs a no_sensor_frames fault names (the most frequent)
MAX_IDS_COUNTED = 64  # distinct IDs counted before the first valid sensor frame


class SidecarStartError(MrrigError, OSError):
    """The telemetry process (Zenoh, recording) could not start: the daemon does not run."""


class Exit:
    """`mrrig run`'s exit codes (README: Exit codes)."""

    OK = 0  # stopped by its duration or a signal, not in FAULT
    FAULT = 1  # ended in FAULT (a fault that nobody re-armed)
    USAGE = 2  # a bad config, model or argument (the CLI's one-line error)
    BUS_LOST = 3  # the CAN bus failed or went away (a killed bridge)
    TELEMETRY_LOST = 4  # the telemetry process died again after its one restart


@functools.cache
def rig_units() -> RigUnits:
    """The units a model's signals must have: the DBC's (`model_fit.check_units`), which the
    config's limits share (loop.x_range_m, loop.i_max_a, loop.f_range_n)."""
    codec = Codec()
    dbc = codec.dbc_path.name

    def where(message: str, signal: str, config: str) -> tuple[str, str]:
        return codec.unit(message, signal), f"{message}.{signal} in {dbc}, {config}"

    x, x_where = where("RigSensors", "Displacement", "loop.x_range_m")
    command = where("DamperCommand", "CurrentSetpoint", "loop.i_max_a")
    return {
        "x": (x, x_where),
        "xd": (f"{x}/s", f"the rate of {x_where}"),
        "xdd": (f"{x}/s^2", f"the rate of rate of {x_where}"),
        "current": command,
        "v": command,  # the RNN's previous commands
        "command": command,
        "f_des": where("DamperCommand", "DesiredForce", "loop.f_range_n"),
        "force": where("RigSensors", "Force", "loop.f_range_n"),
    }


def build_controller(cfg: DaemonConfig, section=None, model: MLP | None = None) -> Controller:
    """The configured controller, from the registry (`controllers.make_controller`); a model
    that does not fit stops here with one line: units other than the rig's, or a controller
    whose work per frame is over the loop's budget (measured here, off the loop:
    `model_fit`). `model`: the section's model, already read (the control plane reads it
    under limits)."""
    c = section or cfg.controller
    i_max, dt = cfg.loop.i_max_a, cfg.loop.period_s
    if c.name == "constant" and not 0 <= c.current_a <= i_max:
        raise ConfigError(f"{cfg.source}: controller.current_a: outside [0, {i_max}] A")
    if model is None and CONTROLLERS[c.name].needs_model:
        model = load_model(c.model, cfg.source)
    if model is not None:
        check_units(model, c.model, rig_units())
        check_period(model, c.model, dt)
    if c.on_current_a is not None and c.on_current_a > i_max:
        raise ConfigError(f"{cfg.source}: controller.on_current_a: above loop.i_max_a {i_max} A")
    settings = ControllerSettings(
        i_max, dt_s=dt, model=model, current_a=c.current_a, gain=c.gain, b=c.b,
        on_current_a=c.on_current_a,
    )  # fmt: skip
    if c.name == "network_inversion":
        continuity = c.continuity
        if continuity is None:
            continuity = model_continuity(model, c.model)
            log.info("%s: continuity %g, the model's own", c.model, continuity)
        ahead = c.ahead
        if ahead and len(model.input_names) > len(FORWARD_INPUTS):
            log.warning(
                "%s: a model with history inputs: network inversion solves for the present "
                "instant (the one-step-ahead solve takes a model of x, xd, xdd, current)",
                c.model,
            )
            ahead = False
        if ahead and model.meta.get("current_input", "commanded") != "lagged":
            log.warning(
                "%s: a model of the commanded current (no current_input = 'lagged', no "
                "lag_tau_s): network inversion solves one step ahead without inverting the "
                "coil's lag; for that, train on the lagged current "
                "(mrrig train --current-input lagged)",
                c.model,
            )
        settings = replace(
            settings,
            method=c.method,
            feedback_tau_s=c.feedback_tau_s if c.feedback else None,
            continuity=continuity,
            ahead=ahead,
            adaptation=cfg.adaptation.settings(),
        )
    try:
        controller, spare = (make_controller(c.name, settings) for _ in range(2))
    except ValueError as exc:
        raise ModelError(f"{c.model}: controller {c.name}: {exc}") from None
    check_cost(spare, c.model if model is not None else f"controller {c.name}", dt)
    if model is not None:  # a short closed loop on the model's own envelope (the spare's)
        x_half = 0.5 * (cfg.loop.x_range_m[1] - cfg.loop.x_range_m[0])
        checked = self_check(spare, model, c.model, dt, i_max, x_half)
        log.info("%s: self-check passed in %.0f ms", c.model, checked.seconds * 1e3)
    return controller


def model_continuity(model: MLP, path: Path | None) -> float:
    """The continuity `mrrig train` chose for the model on its training rows (the on-line
    inversion's smallest current RMSE there: `training.choose_continuity`); for a model
    without one, `DEFAULT_CONTINUITY` (the root)."""
    mu = model.meta.get("online_continuity", DEFAULT_CONTINUITY)
    if isinstance(mu, bool) or not isinstance(mu, int | float) or not 0 <= mu < math.inf:
        raise ModelError(f"{path}: meta.online_continuity: expected a number >= 0, got {mu!r}")
    return float(mu)


def load_model(path: Path | None, source: str) -> MLP | TwinModel:
    if path is None:
        raise ModelError(f"{source}: controller.model: no model file given")
    if not Path(path).is_file():
        raise ModelError(
            f"{source}: controller.model: {path} not found (train one: mrrig train ...)"
        )
    return load_forward_model(path)  # a network, or a twin (a plant file)


def build_reference(r: ReferenceSection, dt_s: float) -> ref.ForceReference:
    if r.kind == "constant":
        return ref.Constant(r.offset_n)
    if r.kind == "sine":
        return ref.Sine(r.offset_n, r.amplitude_n, r.freq_hz)
    if r.kind == "noise":
        return ref.Noise(r.offset_n, r.amplitude_n, r.freq_hz, r.seed, dt_s)
    if r.kind == "csv":
        return ref.CsvSeries(r.path)
    if r.kind == "bouc_wen":
        return ref.BoucWenReference(r.preset, r.current_a, r.current_amp_a, r.current_freq_hz, dt_s)
    if r.kind == "paper_case":
        return ref.PaperCase(r.case, r.current_scale, r.preset, dt_s)
    return ref.External(r.timeout_s)


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


class Daemon:
    """The loop and its state; `run()` until stopped, then a SAFE command and a summary."""

    def __init__(
        self, cfg: DaemonConfig, record_path: Path | None = None, keep_batches: bool = False
    ) -> None:
        """`keep_batches`: keep every sample batch for `handed_over` (an in-process consumer
        such as characterize); otherwise the loop keeps none and its memory stays fixed."""
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
        self.reference = build_reference(cfg.reference, self.period_s)
        try:
            ref.check_in_range(self.reference, cfg.loop.f_range_n)
        except ref.ForceReferenceError as exc:
            raise ref.ForceReferenceError(f"{cfg.source}: {exc}") from None
        # a hybrid simulation ([hil]): its law's desired force is the force reference
        self.hil = None
        if cfg.hil.scenario is not None:
            self.hil = hil_loop.HilLoop(cfg, self.profile, self.packer, self._set_waveform)
            self.reference = self.hil.reference
        self.kf = RealtimeKalman(self.period_s, q=cfg.estimator.q, r0=cfg.estimator.r0_m2)
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
        self.lease = ArmLease(cfg.control.lease_timeout_s)  # a remote arm's, while held
        self.record_path = record_path
        self.exit_code = Exit.OK
        # why the daemon raised, where it did: the summary says so (the catalog: `crashed`)
        self.crashed = ""
        self.record_paths = [record_path] if record_path is not None else []
        self._clock_warned = False
        self._sidecar_deadline = math.inf
        self.control = ControlWorker(Preparer(self, build_controller, build_reference))
        self.control.on_start = self._control_thread_started
        self.stop_reason = ""
        self._stop = False
        self.started = threading.Event()  # set when the loop listens for frames
        self._safe_sent_at_stop = False  # the stop's SAFE command answered a sensor frame
        self.bus = None
        self.link: LoopEnd | None = None  # to the sidecar, when telemetry or recording is on
        self._replies: ReplyWriter | None = None  # the control thread's end of the same pipe
        self.tap = None  # canlog.FrameTap: every frame for the bus log, when one is asked for
        if cfg.recording.can_log is not None:
            from mrrig.rigio.canlog import FrameTap

            self.tap = FrameTap()
        self.sidecar = None
        self._sidecar_restarts = 0
        self._sidecar_restarting = False
        self.recording_failed = ""  # why the recording stopped, if it did
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
        self._keep_batches = keep_batches
        self._chunks: list[np.ndarray] = []  # only with keep_batches
        self._summary = SummaryAccumulator()  # the exit summary, built batch by batch
        # the loop thread's run-queue delay and the VM's steal, pass by pass
        self.kernel_stalls = KernelStalls(self.period_s)
        # per answered frame, the parts of latency_us: the wait between the bus's receive
        # timestamp and the loop's read, the loop's work from its read to the end of send()
        # (the spec's budget), and the send() call within that work
        self._send_call_s = math.nan
        self._split = np.full((cfg.loop.telemetry_batch, 3), np.nan)
        self._split_us = {k: Histogram(LATENCY_BIN_US, LATENCY_TOP_US) for k in LATENCY_PARTS}
        self._buf = np.zeros(cfg.loop.telemetry_batch, dtype=SAMPLE_DTYPE)
        self._n = 0
        self._last_sensor_t = None
        self._last_sensor_bus_ts = None  # the bus's receive timestamp of that frame
        self._restart_next, self._gap_s = False, 0.0  # the estimate, after a gap
        self._early_event_t = -math.inf
        self._frame_age_limit_s = cfg.loop.frame_age_limit_s
        self._first_sensor_t = 0.0
        # until the first valid sensor frame: since when one is due (the first frame of any
        # kind, an arm), and the frames the bus carried instead, per CAN ID
        self._listen_since: float | None = None
        self._bus_heard = False
        self._ids_seen: dict[str, int] = {}
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

    # ---- time and hand-off -------------------------------------------------------------
    def now(self) -> float:
        return time.perf_counter() - self.t0

    def _emit(self, events: list[dict]) -> None:
        for e in events:
            self.events.append(e)
            level = logging.INFO if e["level"] == "info" else logging.WARNING
            log.log(level, "%s: %s", e["kind"], e["reason"])
            if self.link is not None:
                self.link.send_event(e)
        if events:
            self._send_status(force=True)

    def status(self) -> dict[str, Any]:
        s = self.supervisor
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
            "recording": "failed: " + self.recording_failed if self.recording_failed else None,
            "telemetry_restarts": self._sidecar_restarts,
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
            if self.link is not None:
                self.link.send_status(self.status())

    # ---- CAN ---------------------------------------------------------------------------
    def _send(self, name: str, values: dict[str, Any]) -> bool:
        """Encode and send; a failure of either (a value the profile cannot carry, the bus) is
        a BUS_ERROR fault, never the end of the loop."""
        try:
            msg = self.packer.message(name, values)
            t = time.perf_counter()
            self.bus.send(msg, timeout=self.cfg.bus.send_timeout_s)
            self._send_call_s = time.perf_counter() - t
            if self.tap is not None:
                self.tap.tx(msg)
            return True
        except Exception as exc:  # noqa: BLE001 - any bus failure is a BUS_ERROR fault
            self.counters["send_failures"] += 1
            self._emit(self.supervisor.trip(self.now(), Fault.BUS_ERROR, f"send {name}: {exc}"))
            return False

    def _send_command(self, active: bool, current_a: float, f_des: float, echo: int) -> None:
        self.slew.sent(current_a if active else None)
        ok = self._send(
            self.profile.command_message,
            {
                "Mode": 1 if active else 0,
                "CurrentSetpoint": current_a if active else 0.0,
                "SensorCounterEcho": echo,
                "ControllerId": self.controller.controller_id if active else 0,
                "DesiredForce": f_des if active else 0.0,
            },
        )
        if ok:
            self.counters["commands_sent"] += 1
            self.counters["commands_active"] += active
        elif active:  # in FAULT now: the frame is answered SAFE, if that can be sent
            self._send_command(False, 0.0, 0.0, echo)

    def _send_frame(self, msg) -> bool:
        """Send a frame already encoded (the HIL's ActuatorSetpoint); a failure is a
        BUS_ERROR fault, as in `_send`."""
        try:
            self.bus.send(msg, timeout=self.cfg.bus.send_timeout_s)
            if self.tap is not None:
                self.tap.tx(msg)
            return True
        except Exception as exc:  # noqa: BLE001 - any bus failure is a BUS_ERROR fault
            self.counters["send_failures"] += 1
            self._emit(self.supervisor.trip(self.now(), Fault.BUS_ERROR, f"send setpoint: {exc}"))
            return False

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

    # ---- the cycle ---------------------------------------------------------------------
    def cycle(
        self, values: dict[str, float], counter: int, t_rx: float, queued_s: float = 0.0
    ) -> None:
        """One valid RigSensors frame -> exactly one DamperCommand.

        `queued_s`: how long the frame waited between its receive timestamp at the bus and
        `t_rx` (the loop reading it); its age when answered is that plus the cycle's time.
        A frame older than `loop.max_frame_age_s` is answered SAFE, and while armed the stall
        is a fault. An unexpected error in the computation does not unwind the loop: it is a
        fault, and the frame is still answered, SAFE.
        """
        sup = self.supervisor
        t = t_rx - self.t0
        x_meas, f_meas = values["Displacement"], values["Force"]
        events = sup.sensors(t, values)
        x = xd = xdd = f_des = math.nan
        i_cmd = 0.0
        try:
            x, xd, xdd = self.kf.update(x_meas)
            if self._last_sensor_t is None:
                self.reset_reference(t, x)
            events += sup.finite(t, "the Kalman estimate", x, xd, xdd)
            if self.hil is not None:  # the model steps on the measured force and stroke
                events += self.hil.on_frame(t, f_meas, x_meas, sup)
            f_next = None
            try:
                if self._pipelined():
                    f_des, f_next = self._targets_now(t, x, xd, xdd)
                else:
                    f_des = float(self.reference.forecast(t, x, xd))
            except ref.StaleReference as exc:
                f_des = 0.0
                if sup.active:
                    events += sup.trip(t, Fault.STALE_REFERENCE, f"stale force reference: {exc}")
            if f_next is None and self.controller.wants_next_target:
                f_next = f_des  # a reference not known ahead holds its present value
            # the clamp below passes NaN, and a controller may map it to a finite current
            what = f"the {self.reference.kind} force reference"
            targets = (f_des, f_des if f_next is None else f_next)
            events += sup.finite(t, what, *targets)
            if not all(math.isfinite(f) for f in targets):
                # a reference damper driven off its range keeps a NaN state: it starts again
                # here, or it would fault the rig again as soon as it left FAULT
                self.reset_reference(t, x_meas)
            f_des = self._clamp_force(f_des)
            if f_next is not None:
                f_next = self._clamp_force(f_next)
            if sup.active:
                events += self._detect(t, f_meas, f_des, xd)
            if sup.active:
                i = self.controller.command_one(x, xd, xdd, f_meas, f_des, f_next)
                events += sup.finite(t, f"the {self.controller.name} controller's command", i)
                if sup.active:
                    i_cmd = self._slew_limit(i)
                if self.hil is not None:  # a law's current; the scenario's current range
                    i_cmd = self.hil.command(i_cmd, self.cfg.loop.i_max_a)
        except Exception as exc:  # noqa: BLE001 - a bug must not leave a frame unanswered
            log.exception("cycle failed")
            events += sup.trip(t, Fault.INTERNAL_ERROR, f"{type(exc).__name__}: {exc}")
            i_cmd = 0.0
        if self._stop and sup.active:
            # the stop answers this frame SAFE: the rig is disarmed from this frame on, and the
            # frame is recorded so (not as an armed frame whose command fell to 0 A)
            events += sup.disarm(t, f"stopping: {self.stop_reason}")
        age_s = queued_s + (time.perf_counter() - t_rx)
        if age_s > self._frame_age_limit_s:
            self.counters["stale_frames"] += 1
            if sup.active:
                events += sup.trip(
                    t,
                    Fault.STALE_FRAME,
                    f"sensor frame {age_s * 1e3:.1f} ms old when answered (limit "
                    f"{self._frame_age_limit_s * 1e3:g} ms): the daemon or the bus stalled",
                )
        active = sup.active
        safe_f = f_des if math.isfinite(f_des) else 0.0
        self._send_command(active, i_cmd if active else 0.0, safe_f, counter)
        active = active and sup.active  # a send that failed faulted it: answered SAFE
        if self.hil is not None:  # the frame's ActuatorSetpoint, after its command
            events += self.hil.after_command(self._send_frame, counter, t, sup)
        f_record = f_des
        if self._stop:
            self._safe_sent_at_stop = True
        work_us = (time.perf_counter() - t_rx) * 1e6
        latency_us = work_us + queued_s * 1e6
        self._split[self._n] = (queued_s * 1e6, work_us, self._send_call_s * 1e6)
        self._send_call_s = math.nan
        self.last_x = x
        f_model = math.nan
        try:
            if active:
                self.controller.after_send()  # on-line adaptation: armed, no fault this frame
            if self.reference.follows_motion:
                # this instant's desired force: the reference moved on along the motion as
                # estimated now that the frame has come (the targets were its forecasts)
                f_record = self._clamp_force(float(self.reference.force(t, x, xd)))
            # off the latency path: the next frame's Kalman step, reference and controller
            # work, from the predicted state
            self._prepare_next(t + self.period_s, active)
            if active:
                s = ControlInput(
                    np.array([x]),
                    np.array([xd]),
                    np.array([xdd]),
                    np.array([f_meas]),
                    np.array([f_des]),
                )
                f_model = float(self.controller.model_force(s, np.array([i_cmd]))[0])
        except Exception as exc:  # noqa: BLE001
            log.exception("after-send work failed")
            events += sup.trip(t, Fault.INTERNAL_ERROR, f"{type(exc).__name__}: {exc}")
        row = self._buf[self._n]
        row["t"], row["counter"], row["x"], row["x_est"] = t, counter, x_meas, x
        row["xd"], row["xdd"], row["f_meas"], row["f_des"] = xd, xdd, f_meas, f_record
        row["f_model"], row["i_cmd"] = f_model, i_cmd if active else 0.0
        row["i_meas"], row["latency_us"], row["state"] = self._i_meas, latency_us, sup.state
        row["temp_degc"] = self._temp_degc
        env = self.envelope  # off the latency path: the command is sent
        row["outside"] = math.nan if env is None else env.outside(x, xd, xdd, i_cmd)
        (hil_loop.record_nan if self.hil is None else self.hil.record)(row)
        adapt = getattr(self.controller, "adapt", None)
        if adapt is None:
            row["adapt_gain"] = row["adapt_offset_n"] = math.nan
        else:
            row["adapt_gain"], row["adapt_offset_n"] = adapt.theta[0, 0], adapt.offset_n[0]
        self._n += 1
        if self._n == len(self._buf):
            self._flush_samples()
        if events:
            self._emit(events)

    def _detect(self, t: float, f_meas: float, f_des: float, xd: float) -> list[dict]:
        """The error detectors on an armed frame, and their actions: `warn` an event,
        `disarm` a fault (this frame is answered SAFE), `stop` that and the actuator stopped
        (its command sent at the end of this pass of the loop, off the latency path)."""
        events: list[dict] = []
        for d in self.detectors.check(t, f_meas, f_des, xd, self._temp_degc):
            if d.action == "warn":
                events += self.supervisor.notice(t, "detector", d.text)
                continue
            if self.supervisor.active:
                events += self.supervisor.trip(t, DETECTOR_FAULTS[d.name], d.text)
            if d.action == "stop":
                self.actuator = replace(self.actuator, waveform="stop")
                self._last_actuator_sent = -math.inf
        return events

    def _pipelined(self) -> bool:
        """Whether the desired forces are computed a frame ahead (`_targets`): for a controller
        that solves for the instant its command acts on, with a reference known ahead."""
        return self.controller.wants_next_target and self.reference.known_ahead

    def reset_reference(self, t: float, x: float, reference: ref.ForceReference | None = None):
        """(Re)start the force reference (a new one if given) at time t; forget its forces
        computed ahead."""
        if reference is not None:
            self.reference = reference
        self.reference.reset(t, x)
        self._targets = []

    def _targets_now(self, t: float, x: float, xd: float, xdd: float) -> tuple[float, float]:
        """This frame's desired force and the next frame's: computed after the previous
        frames' commands (`_prepare_next`) where they were, else now, the next one at the
        state one period on (eq. 21): the reference's forecasts, each instant's once, on
        the frame sequence rather than on receive times, which jitter. A reference damper
        moves on after the command, on the estimate of the instant (`cycle`)."""
        T = self.period_s
        q = self._targets
        f_des = q[0] if q else float(self.reference.forecast(t, x, xd))
        if len(q) > 1:
            f_next = q[1]
        else:
            xn, xdn = x + xd * T + 0.5 * xdd * T * T, xd + xdd * T
            f_next = float(self.reference.forecast(t + T, xn, xdn))
        self._targets = [f_next]
        return f_des, f_next

    def _slew_limit(self, i_a: float) -> float:
        """The controller's command within [0, loop.i_max_a] and (a model's) within
        loop.max_current_slew_a_per_s of the last one sent (`slew.loop_command`, the HIL
        reference's too); a command the slew limit moved is counted."""
        sent, moved = loop_command(self.slew, self.controller, i_a, self.cfg.loop.i_max_a)
        self.counters["commands_slew_limited"] += moved
        return sent

    def _clamp_force(self, f_n: float) -> float:
        """A desired force inside `loop.f_range_n`, whatever its source (NaN passes, for the
        finiteness check to name)."""
        lo, hi = self.cfg.loop.f_range_n
        return min(max(f_n, lo), hi)

    def _prepare_next(self, t_next: float, active: bool) -> None:
        """What the next frame's cycle can know before the frame: the Kalman filter's
        prediction, gain and covariance, the reference for the predicted state (one instant
        further for a controller that solves one step ahead: `_targets_now`), and the
        controller's solve on it (`Controller.prepare_one`)."""
        kf = self.kf
        kf.prepare()
        xp, xdp, xddp = kf.prior
        if self._pipelined():
            if len(self._targets) != 1:
                return  # not after a frame's targets: the next frame computes its own
            T = self.period_s
            xn, xdn = xp + xdp * T + 0.5 * xddp * T * T, xdp + xddp * T
            self._targets.append(float(self.reference.forecast(t_next + T, xn, xdn)))
            if active:
                f_now, f_after = (self._clamp_force(f) for f in self._targets)
                self.controller.prepare_one(xp, xdp, xddp, f_now, f_after)
            return
        try:  # the frame's own desired force, forecast off its latency path
            f_next = float(self.reference.forecast(t_next, xp, xdp))
        except ref.StaleReference:
            return  # the frame itself will say so
        if not active:
            return
        f_next = self._clamp_force(f_next)
        wants = self.controller.wants_next_target
        self.controller.prepare_one(xp, xdp, xddp, f_next, f_next if wants else None)

    def _flush_samples(self) -> None:
        batch = self._buf[: self._n].copy()
        if self._keep_batches:
            self._chunks.append(batch)
        self._summary.add(batch)
        for k, part in enumerate(LATENCY_PARTS):
            self._split_us[part].add(self._split[: self._n, k])
        self._split[:] = np.nan
        self._n = 0
        if self.link is not None and not self.link.send_samples(batch):
            self.counters["telemetry_dropped"] += len(batch)
        self._flush_frames()

    def _flush_frames(self, force: bool = False) -> None:
        frames = self.tap.take(force) if self.tap is not None else None
        if frames is not None and self.link is not None:
            self.counters["can_log_dropped"] += self.link.send_frames(frames)

    def handed_over(self, start: int = 0) -> list[np.ndarray]:
        """The sample batches completed so far, from batch `start` on (needs keep_batches).

        Safe from another thread while the loop runs: the loop only appends whole batches,
        and a list slice is atomic.
        """
        if not self._keep_batches:
            raise RuntimeError("the daemon keeps no batches: construct it with keep_batches=True")
        return self._chunks[start:]

    # ---- frames ------------------------------------------------------------------------
    def on_frame(self, msg, t_rx: float, queued_s: float = 0.0) -> None:
        """One received frame; `queued_s` as in `cycle`."""
        self.counters["frames_received"] += 1
        if self.tap is not None:
            self.tap.rx(msg)
        if self._last_sensor_t is None:
            self._note_id(msg, t_rx)
        # 29-bit, remote and error frames are none of the DBC's 11-bit messages
        p = self.parser.parse_message(msg, t_rx)
        if p.name == self._sensor_msg:
            if not p.ok:
                self.counters["sensor_frames_invalid"] += 1
                self._emit(self.supervisor.bad_frame(t_rx - self.t0, p.reason))
                return
            self.counters["sensor_frames_valid"] += 1
            gap_s = self._sensor_gap_s(msg.timestamp)
            self._check_counter_timing(msg.timestamp, p.lost_frames, t_rx)
            if p.lost_frames:
                self.counters["lost_frames"] += p.lost_frames
                self._emit(self.supervisor.lost_frames(t_rx - self.t0, p.lost_frames))
            restart, self._restart_next = self._restart_next, False
            if gap_s > self.cfg.loop.timeout_periods * self.period_s:
                self._restart_next = True  # this frame may hold a sample from before the gap
                self._gap_s = gap_s
            if restart:
                self._restart_estimate(t_rx, p.values["Displacement"], self._gap_s)
            elif p.lost_frames:
                del self._targets[: p.lost_frames]  # those computed for the missing frames
                for _ in range(p.lost_frames):  # the estimate goes on through the missing periods
                    self.kf.predict_only()
            if self._last_sensor_t is None:
                self._first_sensor_t = t_rx
            if self._arm_pending and t_rx - self._first_sensor_t >= self.cfg.loop.arm_settle_s:
                self._arm_at_start(t_rx)
            counter = p.counter or 0  # None: a layout without E2E has no counter to echo
            self.cycle(p.values, counter, t_rx, queued_s)
            self._last_sensor_t = t_rx
            self._last_counter = counter
            if self._status_in_sensors:
                self._on_status(p.values, t_rx)
        elif p.name == self._status_msg and p.ok:
            self._on_status(p.values, t_rx)
        elif p.name in self._own_messages:
            self.counters["foreign_commands"] += 1
            self._emit(self.supervisor.foreign_command(t_rx - self.t0, p.name))
        elif not p.ok and p.name is None:
            self.counters["frames_ignored"] += 1
            log.debug("ignored frame: %s", p.reason)

    def _on_status(self, v: dict[str, float], t_rx: float) -> None:
        """The firmware's status (RigStatus, or the roles a profile has in another frame)."""
        self.counters["status_frames"] += 1
        self._i_meas = v["CoilCurrent"]
        self._temp_degc = v["DamperTemperature"]
        status = self.profile.firmware_status(v)
        if status is not None:
            self._emit(self.supervisor.firmware_status(t_rx - self.t0, *status))

    def _note_id(self, msg, t_rx: float) -> None:
        """Count a frame by its CAN ID until the first valid sensor frame: a no_sensor_frames
        fault names what the bus carried (a rig on another DBC, a wrong channel). The first
        frame of the run opens the window a sensor frame is due in: a silent bus is a rig not
        yet streaming (a daemon started first), a bus of other frames one that is not ours."""
        if not self._bus_heard:
            self._bus_heard = True
            self._listen_since = t_rx
        if msg.is_error_frame:
            key = "error frames"
        else:
            key = (
                f"0x{msg.arbitration_id:08X}"
                if msg.is_extended_id
                else f"0x{msg.arbitration_id:03X}"
            )
            key += " (remote)" if msg.is_remote_frame else ""
        if key in self._ids_seen or len(self._ids_seen) < MAX_IDS_COUNTED:
            self._ids_seen[key] = self._ids_seen.get(key, 0) + 1
        else:
            self._ids_seen["other"] = self._ids_seen.get("other", 0) + 1

    def _check_first_frame(self, now_abs: float, limit_s: float) -> None:
        """No valid sensor frame yet: one within the sensor timeout of the bus's first frame
        or of an arm, or fault no_sensor_frames (once for each), naming the IDs seen."""
        if self._listen_since is None or now_abs - self._listen_since <= limit_s:
            return
        self._listen_since = None
        since = "arming" if self.supervisor.active else "the bus's first frame"
        self._no_sensor_frames(now_abs, f"within {limit_s * 1e3:g} ms of {since}")

    def _no_sensor_frames(self, now_abs: float, when: str) -> None:
        seen = sorted(self._ids_seen.items(), key=lambda kv: -kv[1])
        n = sum(self._ids_seen.values())
        if n:
            ids = ", ".join(f"{k} x{c}" for k, c in seen[:MAX_IDS_NAMED])
            more = f" and {len(seen) - MAX_IDS_NAMED} more" if len(seen) > MAX_IDS_NAMED else ""
            heard = f"the bus carried {n} other frames: {ids}{more}"
        else:
            heard = "the bus carried no frames at all"
        sensors = self.profile.sensor_layout
        self._emit(
            self.supervisor.trip(
                now_abs - self.t0,
                Fault.NO_SENSOR_FRAMES,
                f"no valid {sensors.name} frame (0x{sensors.frame_id:03X}) {when}; {heard} "
                "(another DBC, channel or rig?)",
            )
        )

    def _sensor_gap_s(self, bus_ts: float) -> float:
        """Time since the previous sensor frame by the bus's receive timestamps (0 for the
        first one)."""
        last = self._last_sensor_bus_ts
        return 0.0 if last is None else bus_ts - last

    def _restart_estimate(self, t_rx: float, x_meas: float, gap_s: float) -> None:
        """After a gap longer than the sensor timeout the 4-bit counter no longer tells how
        many periods passed (a 100 ms stall moved it on 2, not 50): predicting through the
        counter's periods would read the travel of the whole gap as a few periods' and the
        velocity would spike. The estimate and the force reference start again, as at the
        first frame, from the second frame after the gap: the first may carry a sample taken
        before it (the firmware sampled, then stalled before sending), and a filter started
        on it read the next frame's jump as a velocity of 1.8 m/s."""
        self.kf.reset(x_meas)
        self.reset_reference(t_rx - self.t0, x_meas)
        self.controller.reset(1)
        self.counters["estimate_restarts"] += 1
        log.info("estimate restarted after %.1f ms without sensor frames", gap_s * 1e3)

    def _check_counter_timing(self, bus_ts: float, lost: int, t_rx: float) -> None:
        """A sensor frame whose counter moved on more periods than time has passed since the
        last one (a counter jump inside one period): a replayed or forged frame with a valid
        CRC, or a second sender. E2E profile 2's 4-bit counter cannot stop such frames (README,
        security); this only makes them seen: counted, and an event per budget window."""
        last, self._last_sensor_bus_ts = self._last_sensor_bus_ts, bus_ts
        if last is None or lost == 0 or bus_ts - last >= lost * self.period_s:
            return
        self.counters["sensor_frames_early"] += 1
        t = t_rx - self.t0
        if t - self._early_event_t >= self.cfg.loop.budget_window_s:
            self._early_event_t = t
            self._emit(
                self.supervisor.notice(
                    t,
                    "suspect_frame",
                    f"sensor counter advanced {lost + 1} in {(bus_ts - last) * 1e3:.2f} ms: "
                    "a replayed or forged frame, or a second sender?",
                )
            )

    def _arm_at_start(self, t_rx: float) -> None:
        """arm_on_start: once the sensor frames have streamed for arm_settle_s."""
        self._arm_pending = False
        if self.supervisor.state is not RigState.IDLE:
            log.warning("not armed at start: the daemon is in %s", self.supervisor.state.name)
            return
        ok, msg, events = self.supervisor.arm(t_rx - self.t0)
        if not ok:
            log.warning("arm at start refused: %s", msg)
        self.actuator_at_arm = self.actuator
        self.controller.reset(1)
        self.detectors.reset()
        self._emit(events)

    def check_timeout(self, now_abs: float) -> None:
        """No sensor frame for timeout_periods: FAULT, and a SAFE command on its own."""
        limit = self.cfg.loop.timeout_periods * self.period_s
        if self._last_sensor_t is None:
            self._check_first_frame(now_abs, limit)
            return
        if now_abs - self._last_sensor_t <= limit:
            return
        if self.supervisor.state is not RigState.FAULT:
            self._emit(
                self.supervisor.trip(
                    now_abs - self.t0,
                    Fault.SENSOR_TIMEOUT,
                    f"no sensor frame for {(now_abs - self._last_sensor_t) * 1e3:.1f} ms",
                )
            )
        self._send_command(False, 0.0, 0.0, self._last_counter)
        self.counters["safe_commands_unprompted"] += 1
        self._last_sensor_t = now_abs  # again after another timeout period

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

    def _apply_change(self) -> None:
        """At most one prepared change per pass of the loop, between frames."""
        taken = self.control.take()
        if taken is None:
            return
        change, item = taken
        try:
            reply = {"ok": True, **self.apply(change)}
        except RequestError as exc:
            reply = {"ok": False, "error": str(exc)}
        except Exception as exc:  # noqa: BLE001 - a failed change must not stop the loop
            log.exception("applying %s failed", change.cmd)
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        self.control.done(item, reply)

    def apply(self, c: Change) -> dict[str, Any]:
        """Swap in a prepared change (loop thread). The state is checked again here: an arm
        that came after the change was prepared wins."""
        sup = self.supervisor
        if c.cmd == "arm":
            ok, msg, events = sup.arm(self.now())
            if not ok:
                raise RequestError(msg)
            if events:
                self.lease.end()  # armed anew: a lease of its own
                self.actuator_at_arm = self.actuator
                self.controller.reset(1)
                self.detectors.reset()
                self.reset_reference(self.now(), self.last_x)
                self._listen_since = time.perf_counter()  # frames must come while armed
            self._emit(events)
            if not c.remote:  # in process: the daemon ends with its client
                return {"state": sup.state.name, "message": msg}
            self.lease.grant(time.perf_counter())
            return {"state": sup.state.name, "message": msg, **self.lease.reply()}
        if c.cmd == "renew":
            return self._renew(c.lease)
        if c.cmd == "reset":
            msg, events = sup.reset(self.now())
            self._emit(events)
            return {"state": sup.state.name, "message": msg}
        if c.cmd == "disarm":
            self._emit(sup.disarm(self.now(), "disarmed by request"))
            self.lease.end()
            return {"state": sup.state.name}
        if c.cmd == "status":
            return {"status": self.status()}
        if c.cmd in ("reset_adaptation", "freeze_adaptation"):  # allowed while armed
            return self._adaptation_change(c)
        if c.cmd == "sidecar":
            if c.sidecar is None:
                self.exit_code = Exit.TELEMETRY_LOST
                self.request_stop("telemetry lost: its restart failed")
            else:
                self._sidecar_back(*c.sidecar)
            return {}
        if c.cmd in ("set_controller", "set_profile", "set_hil") and sup.state is RigState.ARMED:
            raise RequestError(f"{c.cmd} only when not armed (disarm first)")
        if c.cmd == "set_controller":
            self.envelope = controller_envelope(c.controller)
            self.controller = c.controller
            self.controller.reset(1)
            self.reset_reference(self.now(), self.last_x)  # its desired forces ahead, if any
            self.cfg = replace(self.cfg, controller=c.controller_section)
            self.in_force = c.in_force or self.in_force
            self._send_status(force=True)
            settings = settings_in_force(c.controller_section, c.controller)
            return {"controller": self.controller.name, "settings": settings}
        if c.cmd == "set_hil":
            if self.hil.streaming:  # a disarm ends the run at the next frame
                raise RequestError("set_hil: the last run is still ending (ask again)")
            self.hil.set_scenario(c.hil_scenario)
            self._send_status(force=True)
            return {"hil": self.hil.status()}
        if c.cmd == "set_profile":
            self.reset_reference(self.now(), self.last_x, c.reference)
            self.cfg = replace(self.cfg, reference=c.reference_section)
            self._send_status(force=True)
            return {"reference": self.reference.kind}
        a = c.actuator
        check_actuator_step(sup.state, self.actuator, a, self.cfg, self.actuator_at_arm)
        self.actuator = a
        self._send_actuator()
        return {
            "waveform": a.waveform,
            "amplitude_m": a.amplitude_m,
            "frequency_hz": a.frequency_hz,
        }

    def _renew(self, lease_id: str) -> dict[str, Any]:
        """Keep an arm's lease; refused when it is not the one held or the rig left ARMED."""
        if self.supervisor.state is not RigState.ARMED:
            self.lease.end()
            raise RequestError(f"lease {lease_id}: ended, the rig is {self.supervisor.state.name}")
        if not self.lease.renew(lease_id, time.perf_counter()):
            raise RequestError(f"lease {lease_id}: not held (lapsed, or another arm's)")
        return self.lease.reply()

    def _lease_lapsed(self, t_rx: float) -> None:
        """No renewal of the arm's lease within its timeout (its client killed or cut off):
        FAULT (this frame on answered SAFE) and the actuator stopped, as a detector's stop. The
        lease's clock stops while the telemetry process, which carries the renewals, is
        silent (a stall of it is no client's end; `telemetry_lost` guards that)."""
        heard = self._sidecar_deadline - self.cfg.telemetry.heartbeat_timeout_s
        if self.link is not None and t_rx - heard > PATH_QUIET_S:
            self.lease.deadline = t_rx + self.lease.timeout_s
            return
        timeout_s, unrenewed_s = self.lease.timeout_s, t_rx - self.lease.deadline
        self.lease.end()
        if not self.supervisor.active:
            return
        self.counters["leases_lapsed"] += 1
        reason = (
            f"lease lapsed: no renewal for {unrenewed_s + timeout_s:.2f} s"
            f" (limit control.lease_timeout_s = {timeout_s:g} s): the client that armed is gone"
        )
        self.actuator = replace(self.actuator, waveform="stop")
        self._last_actuator_sent = -math.inf
        self._emit(self.supervisor.trip(t_rx - self.t0, Fault.LEASE_LAPSED, reason))

    def _adaptation_change(self, c: Change) -> dict[str, Any]:
        adapt = getattr(self.controller, "adapt", None)
        if adapt is None:
            raise RequestError(
                f"controller {self.controller.name} has no on-line adaptation "
                "([adaptation] enabled)"
            )
        if c.cmd == "reset_adaptation":  # back to the model as trained (gain 1, offset 0)
            adapt.reset(adapt.theta.shape[0])
            what = "reset"
        else:  # frozen: the adapted state stays in use, without updates
            adapt.frozen = c.frozen
            what = "frozen" if c.frozen else "resumed"
        self._emit(
            [self.supervisor.event(self.now(), "adaptation", f"adaptation {what} by request")]
        )
        return {"adaptation": adapt.state()}

    def on_force_ref(self, force_n: float, t_rx_mono: float) -> None:
        if isinstance(self.reference, ref.External):
            self.counters["force_refs_received"] += 1
            lo, hi = self.cfg.loop.f_range_n
            if not lo <= force_n <= hi:
                self.counters["force_refs_clamped"] += 1
                if self.counters["force_refs_clamped"] == 1:
                    self._emit(
                        [
                            self.supervisor.event(
                                self.now(),
                                "force_ref_clamped",
                                f"force_ref {force_n:g} N outside loop.f_range_n [{lo:g}, "
                                f"{hi:g}] N: clamped (counted in force_refs_clamped)",
                            )
                        ]
                    )
                force_n = min(max(force_n, lo), hi)
            # the sidecar stamps with time.monotonic(); both clocks tick at the same rate
            delay = time.monotonic() - t_rx_mono
            self.reference.receive(force_n, self.now() - delay)

    def _poll_link(self, now: float) -> None:
        for mtype, payload in self.link.poll():
            if mtype == Msg.REQUEST:
                request_id, raw = payload
                self.control.submit(raw, self._replies.reply_to(request_id))
            elif mtype == Msg.FORCE_REF:
                self.on_force_ref(*payload)
            elif mtype == Msg.HEARTBEAT:
                self._sidecar_deadline = now + self.cfg.telemetry.heartbeat_timeout_s
            elif mtype == Msg.NOTICE and payload.get("kind") == "recording_failed":
                self._recording_failed(str(payload.get("reason", "")))
            elif mtype == Msg.NOTICE and payload.get("kind") == "duplicate_rig":
                reason = str(payload.get("reason", ""))
                self._emit(self.supervisor.trip(self.now(), Fault.DUPLICATE_RIG, reason))

    def _recording_failed(self, reason: str) -> None:
        self.recording_failed = reason or "unknown"
        self._emit(
            self.supervisor.trip(self.now(), Fault.RECORDING_FAILED, f"recording failed: {reason}")
        )

    # ---- supervision of the telemetry process ------------------------------------------
    def _watch_sidecar(self, now: float) -> None:
        """A dead sidecar (its pipe closed) or one without a heartbeat for
        `telemetry.heartbeat_timeout_s`: fault `telemetry_lost`, then one restart."""
        if self._sidecar_restarting:
            return
        if self.link.closed:
            code = self.sidecar.poll() if self.sidecar is not None else None
            why = f"the telemetry process exited (code {code})"
        elif now > self._sidecar_deadline:
            why = (
                "no heartbeat from the telemetry process for "
                f"{self.cfg.telemetry.heartbeat_timeout_s:g} s (stopped or stuck)"
            )
        else:
            return
        self._emit(self.supervisor.trip(self.now(), Fault.TELEMETRY_LOST, why))
        old = (self.sidecar, self.link, self._replies)
        self.link = None
        if self._sidecar_restarts >= MAX_SIDECAR_RESTARTS:
            log.error("telemetry lost again after its restart: stopping the daemon")
            self.exit_code = Exit.TELEMETRY_LOST
            self.request_stop(f"telemetry lost: {why}")
            self.control.submit_job(lambda: self._end_sidecar(*old))
            return
        self._sidecar_restarts += 1
        self._sidecar_restarting = True
        log.warning("%s: restarting it", why)
        self.control.submit_job(lambda: self._restart_sidecar(*old))

    def _end_sidecar(self, proc, link, replies) -> None:
        """Kill and reap a lost sidecar and close its pipes (control thread)."""
        if proc is not None and proc.poll() is None:
            proc.kill()
        if proc is not None:
            try:
                proc.wait(timeout=5)
            except Exception:  # noqa: BLE001
                log.warning("telemetry process %d not reaped", proc.pid)
        replies.close()
        link.close()

    def _restart_sidecar(self, proc, link, replies) -> Change:
        """Control thread: the lost process ended, a new one started (its own recording);
        a Change for the loop either way (`sidecar` None: it could not start)."""
        self._end_sidecar(proc, link, replies)
        if self.record_path is not None:
            n = self._sidecar_restarts
            self.record_path = self.record_path.with_name(
                f"{self.record_path.stem.split('.restart')[0]}.restart{n}.rrd"
            )
            self.record_paths.append(self.record_path)
        if self.tap is not None:
            log.warning("the bus log ends here: a restarted telemetry process does not continue it")
        try:
            return Change("sidecar", sidecar=self._spawn_sidecar(can_log=False))
        except Exception as exc:  # noqa: BLE001 - the loop is told and stops
            log.error("restarting the telemetry process failed: %s", exc)
            return Change("sidecar")

    def _sidecar_back(self, proc, link, replies) -> None:
        self.sidecar, self.link, self._replies = proc, link, replies
        self._sidecar_deadline = time.perf_counter() + SIDECAR_START_S
        self._sidecar_restarting = False
        log.info("telemetry process restarted (pid %d)", proc.pid)
        for e in self.events[-MAX_REPLAYED_EVENTS:]:
            link.send_event(e)
        self._send_status(force=True)

    # ---- run ---------------------------------------------------------------------------
    def request_stop(self, reason: str) -> None:
        self.stop_reason = reason
        self._stop = True

    def run(self) -> dict[str, Any]:
        cfg = self.cfg
        # the sidecar first: a start-up that fails (its Zenoh port taken, a second daemon of
        # this rig's name alive) must not have touched the bus, where another daemon may own
        # the rig (its ActuatorCommand STOP on the way out faulted the running daemon)
        if cfg.telemetry.enabled or self.record_path is not None or self.tap is not None:
            self.sidecar, self.link, self._replies = self._spawn_sidecar()
            self._sidecar_deadline = time.perf_counter() + SIDECAR_START_S
        try:
            self.bus = open_bus(cfg.bus.interface, cfg.bus.channel, **cfg.bus.options)
        except BaseException as exc:
            self.crashed = f"{type(exc).__name__}: {exc}"
            self._shutdown()
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
            self._discard_backlog()
            # the loop's time zero (and its duration) from its first live frame on
            self.t0 = time.perf_counter()
            self._cpu0 = time.process_time()
            self._arm_pending = cfg.loop.arm_on_start
            self._loop()
        except BaseException as exc:
            self.crashed = f"{type(exc).__name__}: {exc}"
            raise
        finally:
            self._shutdown()
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
                break  # no sensor frame to answer: _shutdown sends SAFE on its own
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
            self._apply_change()
            if t_rx > self.lease.deadline:
                self._lease_lapsed(t_rx)
            if msg is not None:
                self.on_frame(msg, t_rx, self._queued_s(msg))
            self.check_timeout(t_rx)
            t = t_rx - self.t0
            if self.link is not None:
                self._poll_link(t_rx)
                self._watch_sidecar(t_rx)
            if t - self._last_actuator_sent >= ACTUATOR_PERIOD_S:
                self._send_actuator()
            self._send_status()
            self._read_kernel_stalls()
            if end is not None and t_rx >= end:
                self.request_stop(f"duration {cfg.loop.duration_s:g} s reached")

    def _read_kernel_stalls(self) -> None:
        """Once a pass, after the frame's command: the run-queue delay and steal since the
        previous pass; a pass that lost a window's worth is an event of the recording."""
        window = self.kernel_stalls.read(self.now())
        if window is not None and self.link is not None:
            self.link.send_event(stall_event(window))

    def _discard_backlog(self) -> None:
        """Drop the frames queued while the daemon started: the rig has moved on. Up to the
        first one that is no older than `max_frame_age_s`: a bridge that delivers a long
        backlog barely faster than the rig sends would otherwise keep this going for as long
        again."""
        stale = 0
        while (msg := self.bus.recv(timeout=0)) is not None:
            stale += 1
            if self._queued_s(msg) <= self.cfg.loop.frame_age_limit_s:
                break
        if stale:
            log.info("discarded %d frames queued before the loop started", stale)

    def _queued_s(self, msg) -> float:
        """How long ago the bus received `msg` (its timestamp: the kernel's on SocketCAN, the
        bridge's on the Python bridge; both time.time())."""
        q = time.time() - msg.timestamp
        if 0.0 <= q < CLOCK_SANE_S:
            return q
        if -CLOCK_SANE_S < q < 0.0:
            return 0.0  # stamped a hair in our future: the two clocks' reads, not an age
        if not self._clock_warned:
            self._clock_warned = True
            log.warning(
                "frame timestamps are not on this machine's clock (%.0f s off): frame age "
                "is measured from the loop's read only",
                q,
            )
        return 0.0

    def _spawn_sidecar(self, can_log: bool = True) -> tuple[Any, LoopEnd, ReplyWriter]:
        """Start the telemetry process and wait for it to be ready; `can_log` False: without
        the bus log (a restarted process would start the run's bus log over)."""
        from mrrig.rigio.sidecar import is_duplicate_text, start_sidecar

        fds = make_channel()
        proc = start_sidecar(
            rig=self.cfg.rig.name,
            zenoh_config=self.cfg.telemetry.zenoh_config if self.cfg.telemetry.enabled else None,
            record=self.record_path,
            fds=fds,
            telemetry_hz=self.cfg.telemetry.rate_hz,
            live_url=self.cfg.recording.live_url,
            insecure=self.cfg.telemetry.insecure,
            can_log=self._can_log() if can_log else None,
            identity=self.identity,
        )
        keep_off_cpu(proc.pid, self.cfg.loop.cpu, "telemetry process")
        link = LoopEnd(*fds.loop_fds())
        # a rig must not run unobserved: no telemetry or recording, no loop
        error = link.wait_ready(SIDECAR_START_TIMEOUT_S)
        if error is not None:
            link.close()
            off = ""
            # not for a name already served: without Zenoh it would open that rig's bus
            if self.cfg.telemetry.enabled and not is_duplicate_text(error):
                off = " (to run without Zenoh: telemetry.enabled = false, or --no-telemetry)"
            raise SidecarStartError(f"the telemetry process could not start: {error}{off}")
        return proc, link, link.reply_writer()

    def _can_log(self) -> tuple[Path, str] | None:
        """The bus log and the channel name it shows (the interface's, a rig name otherwise)."""
        path = self.cfg.recording.can_log
        if path is None:
            return None
        bus = self.cfg.bus
        return path, bus.channel if bus.interface == "socketcan" else self.cfg.rig.name

    def _shutdown(self) -> None:
        """SAFE first, then the actuator to rest, the summary, the sidecar, the bus."""
        self.kernel_stalls.stop(self.now())  # the loop's last pass
        self.control.stop()
        while (taken := self.control.take()) is not None:
            if taken[0].cmd == "sidecar" and taken[0].sidecar is not None:
                self._sidecar_back(*taken[0].sidecar)  # a restart that finished as it ended
        if self.bus is not None and self.started.is_set():
            if self._last_sensor_t is not None and not self._safe_sent_at_stop:
                self._send_command(False, 0.0, 0.0, self._last_counter)
            self.actuator = replace(self.actuator, waveform="stop")
            try:
                self._send_actuator()
            finally:
                self.bus.shutdown()
        elif self.bus is not None:  # never listened: this daemon did not own the rig
            self.bus.shutdown()
        # the loop is over: what follows (and the exit) must not starve another rig's loop;
        # a full collection of the unfrozen heap is one such thing
        leave_realtime("daemon")
        gc.unfreeze()
        self.notifier.stopping()  # after the SAFE command
        self.counters["cpu_loop_s"] = time.process_time() - self._cpu0
        adaptation = self.controller.adaptation_state()
        ahead, missed = self.controller.solved_ahead()
        self.counters["commands_solved_ahead"] = ahead
        self.counters["commands_ahead_missed"] = missed
        self.counters["loop_wall_s"] = self.now()
        never = self.started.is_set() and self.counters["sensor_frames_valid"] == 0
        if never and self.cfg.loop.arm_on_start and self.supervisor.state is not RigState.FAULT:
            # asked to run armed (--arm) on a bus that never carried a frame of any kind
            self._no_sensor_frames(time.perf_counter(), f"in the whole run ({self.now():.1f} s)")
        if self._n:
            self._flush_samples()
        self._flush_frames(force=True)
        self.counters["telemetry_dropped"] += self.link.dropped if self.link else 0
        self.summary = self._summary.result(self.events, dict(self.counters))
        self.summary["stop_reason"] = self.stop_reason
        # the loop's time zero on CLOCK_MONOTONIC: its times set beside another process's
        self.summary["clock_t0_s"] = self.t0
        self.summary["run_id"] = self.identity["run_id"]
        self.summary["controller"] = self.controller.name
        self.summary["reference"] = self.reference.kind
        if adaptation is not None:
            self.summary["adaptation"] = adaptation
        if self.exit_code == Exit.OK and self.supervisor.state is RigState.FAULT:
            self.exit_code = Exit.FAULT
        self.summary["exit_code"] = self.exit_code
        if self.crashed:
            self.summary["crashed"] = self.crashed
        qs = (50, 99, 99.9)
        self.summary["latency_split_us"] = {k: h.percentiles(qs) for k, h in self._split_us.items()}
        self.summary["kernel_stalls"] = self.kernel_stalls.result()
        if self.link is not None:
            self.link.send_summary(self.summary)
            self.link.send_stop()
            self.link.close()
            self._replies.close()
        if self.sidecar is not None:
            try:
                self.sidecar.wait(timeout=15)
            except Exception:  # noqa: BLE001
                log.warning("telemetry process did not stop in 15 s; terminating it")
                self.sidecar.terminate()
            self.summary["cpu_sidecar_s"] = (
                resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime
                + resource.getrusage(resource.RUSAGE_CHILDREN).ru_stime
            )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="mrrig run", description="Run the rig daemon.", formatter_class=HelpFormatter
    )
    ap.add_argument("--config", required=True, type=Path, help="daemon config (TOML)")
    ap.add_argument("--duration", type=positive, help="stop after this many seconds (s)")
    ap.add_argument("--arm", action="store_true", help="arm at start (commands ACTIVE)")
    ap.add_argument(
        "--record", type=Path, help="recording file (default: recordings/<rig>-<UTC>.rrd)"
    )
    ap.add_argument("--no-record", action="store_true", help="no Rerun recording")
    ap.add_argument(
        "--can-log",
        type=Path,
        help="also write every frame to this bus log (.blf, .asc, .log candump, .trc, .csv,"
        " .mf4 with asammdf; overrides recording.can_log)",
    )
    ap.add_argument("--summary-json", type=output_file, help="also write the summary to this file")
    add_bus_options(ap)
    ap.add_argument("--no-telemetry", action="store_true", help="no Zenoh telemetry")
    ap.add_argument(
        "--zenoh-config", type=Path, help="the sidecar's Zenoh config (overrides the config's)"
    )
    ap.add_argument(
        "--adaptation",
        choices=("on", "off"),
        help="override adaptation.enabled: on-line gain and offset of the model's force",
    )
    ap.add_argument(
        "--insecure",
        action="store_true",
        help="allow a Zenoh config off loopback without authentication and access control "
        "(a closed lab network only); warned in every status and recording",
    )
    ap.add_argument("--hil", help="a hybrid simulation: this scenario (configs/hil/*.toml)")
    ap.add_argument("--hil-law", help="--hil: this law in place of the scenario's")
    ap.add_argument(
        "--hil-compensation",
        choices=("none", "polynomial", "adaptive", "model"),
        help="--hil: this delay compensation in place of the scenario's",
    )
    ap.add_argument("--hil-duration", type=positive, help="--hil: seconds, for the scenario's")
    ap.add_argument("--specimen", help="the damper under test (its serial number), for the catalog")
    ap.add_argument("--operator", help="who runs the test (default: the local user)")
    ap.add_argument("--tag", action="append", default=[], help="a free-text tag (repeatable)")
    ap.add_argument("--catalog", help="register the run in this catalog (file or database URL)")
    args = ap.parse_args(argv)
    overrides: dict[str, dict] = {}
    rig = {k: v for k, v in (("specimen", args.specimen), ("operator", args.operator)) if v}
    if args.tag:
        rig["tags"] = args.tag
    if rig:
        overrides["rig"] = rig
    if args.catalog:
        overrides["catalog"] = {"url": args.catalog}
    bus = {k: v for k, v in (("interface", args.bus_interface), ("channel", args.bus_channel)) if v}
    if bus:
        overrides["bus"] = bus
    if args.no_telemetry:
        overrides["telemetry"] = {"enabled": False}
    if args.can_log is not None:
        overrides["recording"] = {"can_log": str(args.can_log)}
    if args.adaptation:
        overrides["adaptation"] = {"enabled": args.adaptation == "on"}
    if args.insecure:
        overrides.setdefault("telemetry", {})["insecure"] = True
    if args.zenoh_config is not None:
        overrides.setdefault("telemetry", {})["zenoh_config"] = str(args.zenoh_config)
    hil = {k: v for k, v in (("scenario", args.hil), ("law", args.hil_law),
                             ("compensation", args.hil_compensation),
                             ("duration_s", args.hil_duration)) if v is not None}  # fmt: skip
    if hil:
        overrides["hil"] = hil
    loop = {}
    if args.duration is not None:
        loop["duration_s"] = args.duration
    if args.arm:
        loop["arm_on_start"] = True
    if loop:
        overrides["loop"] = loop
    cfg = load_config(args.config, overrides)
    if cfg.telemetry.enabled:  # the sidecar checks it too; refused here before the bus opens
        check_secure(
            load_zenoh_config(cfg.telemetry.zenoh_config),
            str(cfg.telemetry.zenoh_config),
            cfg.telemetry.insecure,
        )
    record = args.record
    if args.no_record:
        record = None
    elif record is None and cfg.recording.enabled:
        # imports rerun (its threads, its libraries locked with the loop's memory): only when
        # this run records
        from mrrig.rigio.recording import recording_path

        record = recording_path(cfg.recording.directory, cfg.rig.name)
    daemon = Daemon(cfg, record_path=record)
    for sig in STOP_SIGNALS:
        signal.signal(sig, lambda s, _f: daemon.request_stop(signal.Signals(s).name))
    log.info(
        "rig %s: %s on %s/%s",
        cfg.rig.name,
        daemon.controller.name,
        cfg.bus.interface,
        cfg.bus.channel,
    )
    summary = daemon.run()
    print(format_summary(summary))
    for path in daemon.record_paths:
        print(f"recording: {path}")
    if cfg.recording.can_log is not None:
        print(f"bus log: {cfg.recording.can_log}")
    if args.summary_json:
        args.summary_json.write_text(json_text.dumps(summary, indent=2))
    if daemon.exit_code != Exit.OK:
        log.warning("exit code %d: %s", daemon.exit_code, summary["stop_reason"] or "a fault")
    return daemon.exit_code
