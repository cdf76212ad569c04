"""The daemon's hybrid-simulation mode (spec/hil.md; `[hil]` in the daemon's config): the
numerical substructure in the loop, one step per valid sensor frame while armed.

Per frame the daemon calls `HilLoop.on_frame` before its force reference is read: the
measured force and stroke go into `HybridStep`; the law's desired force becomes the force
reference's value (`HilDemand`, a reference like any other, so it goes through the daemon's
controller, network inversion by default); a law that asks a current (passive-soft/hard,
Dyke's on-off) has it sent as it is (`current`). After the DamperCommand, `after_command`
sends the frame's ActuatorSetpoint, echoing that sensor frame's counter.

Arming starts a run: a fresh substructure and excitation, the actuator in STREAM. Any end of
streaming (a disarm, a fault of any kind, the scenario played out, a safety check of
`mrrig.hil.watch`) stops the setpoints and sends HOLD; `hold_s` later STOP, from which the
firmware ramps the piston to rest. A daemon that dies mid-run leaves the firmware's own
setpoint watchdog to do the same (HOLD after 20 ms, ramp after 500 ms).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mrrig.config import DaemonConfig, HilCompensation, HilLaw, HilSection
from mrrig.hil.laws import Demand
from mrrig.hil.playback import ActuatorLimits, StrokePlayback, infeasibility
from mrrig.hil.scenario import Scenario, load_scenario
from mrrig.hil.stepper import HybridStep
from mrrig.hil.substructure import QuarterCar
from mrrig.hil.watch import HilWatch, WatchLimits
from mrrig.loop import reference as ref
from mrrig.loop.safety import Fault, Supervisor
from mrrig.rigio.canbus.profile import ProfileError, RigProfile
from mrrig.rigio.canbus.setpoint import SetpointError, SetpointStream
from mrrig.rigio.run_identity import file_sha256
from mrrig.typed_config import ConfigError, parse

log = logging.getLogger(__name__)

# the sample fields this mode fills (NaN without it): x_c, the setpoint, the delay estimate,
# the model's frame index, the body's (roof's) absolute acceleration and the tyre load, the
# quarter car's body and wheel displacement and velocity, the building's storey 2-3 drifts
SAMPLE_FIELDS = (
    "hil_k", "hil_x_c", "hil_setpoint", "hil_delay_s", "hil_acc", "hil_load_n",
    "hil_z_body", "hil_v_body", "hil_z_wheel", "hil_v_wheel", "hil_drift_2", "hil_drift_3",
)  # fmt: skip


# a run starts with the piston this close to 0 (the model's equilibrium): else a fault
REST_TOLERANCE_M = 0.002

# the firmware's FaultCodes (RigStatus; contract 1.1) that break a stream while the firmware
# itself runs on (State RUNNING, so the supervisor takes no fault of them): by the DBC's label,
# with what the firmware did
STREAM_FAULTS = {
    "ACTUATOR_SETPOINT_TIMEOUT": (7, "no valid ActuatorSetpoint for 20 ms: it holds the piston"),
    "STROKE_LIMIT": (3, "it clamped a setpoint to its envelope or stroke"),
}


class HilDemand(ref.ForceReference):
    """The law's desired force of the present frame, set by `HilLoop.on_frame` (0 N while no
    run streams); not known ahead: the next one needs the next measured force."""

    kind = "hil"
    known_ahead = False

    def __init__(self) -> None:
        self.force_n = 0.0

    def reset(self, t_s: float, x_m: float) -> None:
        self.force_n = 0.0

    def force(self, t_s: float, x_m: float, xd_m_s: float) -> float:
        return self.force_n


def build_scenario(cfg: DaemonConfig) -> Scenario:
    """The `[hil]` section's scenario with its overrides, checked against the loop."""
    h = cfg.hil
    where = f"{cfg.source}: hil"
    try:
        scenario = load_scenario(h.scenario, law=h.law)
    except OSError as exc:
        raise ConfigError(f"{where}.scenario: {h.scenario}: {exc.strerror or exc}") from None
    if h.compensation is not None:
        c = dataclasses.replace(scenario.compensation, method=h.compensation)
        scenario = dataclasses.replace(scenario, compensation=c)
    if h.duration_s is not None:
        scenario = dataclasses.replace(scenario, duration_s=h.duration_s)
        try:
            scenario.check()  # a playback's record is this long
        except ValueError as exc:
            raise ConfigError(f"{where}.duration_s: {h.scenario}: {exc}") from None
    if not math.isclose(scenario.period_s, cfg.loop.period_s, rel_tol=1e-9):
        raise ConfigError(
            f"{where}.scenario: {h.scenario}: period_s {scenario.period_s:g} s is not the "
            f"loop's {cfg.loop.period_s:g} s (one model step per sensor frame)"
        )
    if scenario.damper.i_max_a > cfg.loop.i_max_a:
        raise ConfigError(
            f"{where}.scenario: {h.scenario}: damper.i_max_a {scenario.damper.i_max_a:g} A "
            f"above loop.i_max_a {cfg.loop.i_max_a:g} A"
        )
    if scenario.kind == "playback":  # the feasibility check before any arming
        played = scenario.played_stroke()
        why = infeasibility(played, playback_limits(h), str(scenario.playback.file))
        if why is not None:
            raise ConfigError(f"{where}.scenario: {why} ([hil] limits)")
    return scenario


def playback_limits(h: HilSection) -> ActuatorLimits:
    """What a daemon's `[hil]` lets an actuator play (a playback's feasibility check)."""
    return ActuatorLimits(
        h.envelope_m, h.max_setpoint_velocity_m_s, h.max_setpoint_acceleration_m_s2
    )


@dataclass(frozen=True)
class HilRunSettings:
    """What a `set_hil` request changes of the daemon's scenario while disarmed (a plan's `hil`
    step: one law after another on the same road); a field left out is as `[hil]` set it at
    start. The scenario file itself is the daemon's, fixed at start."""

    law: HilLaw | None = None
    compensation: HilCompensation | None = None
    duration_s: float | None = None


def scenario_with(base: Scenario, table: dict[str, Any], where: str) -> Scenario:
    """`base` (the daemon's scenario as configured) with a `set_hil` request's fields;
    ConfigError (one line naming the field) for what the scenario cannot take."""
    s = parse(HilRunSettings, table, where)
    new = base
    if s.law is not None:
        new = dataclasses.replace(new, law=s.law)
    if s.compensation is not None:
        c = dataclasses.replace(new.compensation, method=s.compensation)
        new = dataclasses.replace(new, compensation=c)
    if s.duration_s is not None:
        new = dataclasses.replace(new, duration_s=s.duration_s)
    try:
        new.check()
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    return new


class HilLoop:
    """One scenario, run each time the rig is armed."""

    def __init__(
        self,
        cfg: DaemonConfig,
        profile: RigProfile,
        packer,
        set_waveform: Callable[[str, float], None],
    ) -> None:
        """`set_waveform(waveform, amplitude_m)`: the daemon's ActuatorCommand, sent at once."""
        if (why := profile.stream_refusal()) is not None:
            raise ProfileError(f"hil: {why}")
        h = cfg.hil
        self.scenario = build_scenario(cfg)
        # the model's exact steps computed now, at start, not at a run's first frame (cached
        # per model: mrrig.hil.substructure._fraction_table)
        HybridStep(self.scenario)
        self.configured = self.scenario  # what `set_hil` starts from
        self.scenario_path = str(h.scenario)
        self.scenario_sha256 = file_sha256(h.scenario)  # the plan's `hil` step checks it
        # the daemon's config: its controller path is the reference's (`daemon_command`)
        self.config_path = str(cfg.source)
        self.config_sha256 = file_sha256(cfg.source)
        self.envelope_m = h.envelope_m
        self.playback_limits = playback_limits(h)
        self.hold_s = h.hold_s
        self.reference = HilDemand()
        self._stream = SetpointStream(profile, packer, h.envelope_m)
        self._set_waveform = set_waveform
        self._watch = HilWatch(
            WatchLimits(
                h.envelope_m,
                h.tracking_limit_m,
                h.max_setpoint_velocity_m_s,
                # a playback has no model for the damper to put energy into (the measured force
                # goes nowhere): no energy check; its hysteresis near a reversal gives -F s' > 0
                # for a moment, which on a 2 Hz, 10 mm stroke at 1 A passed 0.1 J in 0.25 s
                math.inf if self.scenario.kind == "playback" else h.energy_limit_j,
                h.energy_window_s,
            ),
            self.scenario.period_s,
        )
        self.step: HybridStep | None = None
        # a run's frame compiled (`mrrig.loop.compiled_hil`) with `loop.numerics = "compiled"`
        self._run_type = HybridStep
        if cfg.loop.numerics == "compiled":
            from mrrig.loop import compiled_hil  # numba imported only for the compiled path

            compiled_hil.warm()
            self._run_type = compiled_hil.hybrid_step
        # the next run, built off the loop (here, and by an arm's or set_hil's preparation):
        # its excitation record takes 10 ms to seconds, the first one half a second more
        self._next_run: HybridStep | None = self.build_run()
        self.streaming = False
        self.current: float | None = None  # a law's current for this frame (sent as it is)
        self._setpoint: tuple[float, float] | None = None  # this frame's, to send
        self._stop_at: float | None = None  # HOLD sent: STOP (ramp to rest) at this time
        self._row: dict[str, float] = dict.fromkeys(SAMPLE_FIELDS, math.nan)
        self.runs = 0
        self.setpoints_sent = 0  # of the present (last) run
        self.rest_tolerance_m = REST_TOLERANCE_M
        self._at_rest_sent = False
        self.last_end = ""

    # ---- the frame ---------------------------------------------------------------------
    def on_frame(self, t: float, f_meas: float, x_meas: float, sup: Supervisor) -> list[dict]:
        """Before the force reference is read: start, step or end the run."""
        events: list[dict] = []
        self._setpoint, self.current = None, None
        self._row = dict.fromkeys(SAMPLE_FIELDS, math.nan)
        if not self._at_rest_sent:  # the first frame: the piston to rest (the model's zero)
            self._at_rest_sent = True
            self._set_waveform("stop", 0.0)
        if sup.active and not self.streaming:
            if abs(x_meas) > self.rest_tolerance_m:
                why = (
                    f"the piston is at {x_meas * 1e3:.2f} mm, not at rest (within "
                    f"+-{self.rest_tolerance_m * 1e3:g} mm): the model starts at its equilibrium"
                )
                return sup.trip(t, Fault.HIL_SAFETY, f"hil: {why}")
            self._start(t)
        else:
            self.tick(t, sup)
        if not self.streaming:
            self.reference.force_n = 0.0
            return events
        step = self.step
        sub = step.substructure
        x_c, v_c, k = sub.stroke_m, sub.stroke_velocity_m_s, sub.k
        state = sub.x.tolist()
        frame = step.step(f_meas, x_meas)
        why = self._watch.check(
            x_c, x_meas, f_meas, v_c, frame.target_m, frame.setpoint_m,
            frame.setpoint_velocity_m_s, sub.x,
        )  # fmt: skip
        row = self._row
        row["hil_k"], row["hil_x_c"], row["hil_delay_s"] = k, x_c, frame.delay_s
        if isinstance(sub, QuarterCar):
            row["hil_acc"], row["hil_load_n"] = sub.body_acceleration_m_s2, sub.tyre_load_n
            # frame k's states (x_c's): the step has advanced the model to k + 1
            row["hil_z_body"], row["hil_v_body"], row["hil_z_wheel"], row["hil_v_wheel"] = state
        elif isinstance(sub, StrokePlayback):
            row["hil_acc"] = sub.acceleration_m_s2  # the record's stroke acceleration
        else:
            row["hil_acc"] = float(sub.accelerations_m_s2[-1])
            drifts = sub.drifts_m
            if drifts.size > 1:
                row["hil_drift_2"] = float(drifts[1])
            if drifts.size > 2:
                row["hil_drift_3"] = float(drifts[2])
        if why is not None:
            events += sup.trip(t, Fault.HIL_SAFETY, f"hil: {why}")
            self._end(t, why)
            return events
        demand = frame.demand
        self.reference.force_n = demand.force_n if demand.force_n is not None else 0.0
        self.current = demand.current_a
        self._setpoint = (frame.setpoint_m, frame.setpoint_velocity_m_s)
        row["hil_setpoint"] = frame.setpoint_m
        if step.done:
            events += sup.disarm(t, "hil: the scenario is played out")
            self._end(t, "the scenario is played out")
        return events

    def tick(self, t: float, sup: Supervisor) -> None:
        """Each frame, and each pass of the loop without one (`check_timeout`): a run the
        supervisor left ARMED ends now (HOLD), and STOP follows `hold_s` later, whether the
        sensor frames come or not (a fault that stopped them must not leave the piston held,
        nor the daemon repeating STREAM)."""
        if self.streaming and not sup.active:
            self._end(t, sup.reason or "disarmed")
        if self._stop_at is not None and t >= self._stop_at:
            self._stop_at = None
            self._set_waveform("stop", 0.0)  # the firmware ramps the piston to rest

    def command(self, i_a: float, i_max_a: float) -> float:
        """The frame's current: the law's own where it asks one (passive-soft/hard), else the
        controller's `i_a`; while a run streams, within the scenario's damper range (0 to
        `damper.i_max_a`, as in the reference), and always within `i_max_a` (the loop's)."""
        range_a = self.scenario.damper.i_max_a if self.streaming else None
        return Demand(current_a=self.current).current(i_a, range_a, i_max_a)

    def after_command(
        self, send: Callable[[Any], bool], counter: int, t: float, sup: Supervisor
    ) -> list[dict]:
        """After the DamperCommand: this frame's ActuatorSetpoint, if the run streams and the
        command went out ACTIVE (`send`: the daemon's, False when the bus refused it)."""
        if self.streaming and not sup.active:  # faulted or stopped after `on_frame`
            self._end(t, sup.reason or "disarmed")
            return []
        if self._setpoint is None:
            return []
        try:
            msg = self._stream.message(counter, *self._setpoint)
        except SetpointError as exc:
            self._end(t, str(exc))
            return sup.trip(t, Fault.HIL_SAFETY, f"hil: {exc}") if sup.active else []
        if send(msg):
            self.setpoints_sent += 1
        return []

    def firmware_status(self, t: float, code: int, label: str, sup: Supervisor) -> list[dict]:
        """A RigStatus while a run streams: a stream fault of the firmware (FaultCode 7, the
        setpoint watchdog; 3, a setpoint clamped) ends the run as the loop's own checks do
        (fault, SAFE, HOLD then STOP): the piston no longer follows the model's stroke."""
        known = STREAM_FAULTS.get(label)
        if known is None and label == str(code):  # a layout without the contract's labels
            known = next((v for v in STREAM_FAULTS.values() if v[0] == code), None)
        if not self.streaming or known is None:
            return []
        if not sup.active:  # faulted already (the firmware's FAULT state, ...)
            self._end(t, sup.reason or "disarmed")
            return []
        why = f"the firmware reports FaultCode {known[0]} ({label}) while streaming: {known[1]}"
        events = sup.trip(t, Fault.HIL_SAFETY, f"hil: {why}")
        self._end(t, why)
        return events

    def record(self, row) -> None:
        for name, value in self._row.items():
            row[name] = value

    # ---- start and end -----------------------------------------------------------------
    def build_run(self, scenario: Scenario | None = None) -> HybridStep:
        """A fresh run of `scenario` (default the one in force): any thread but the loop."""
        return self._run_type(self.scenario if scenario is None else scenario)

    def run_ready(self) -> bool:
        """Whether the next run of the scenario in force is built (any thread: a snapshot)."""
        run = self._next_run
        return run is not None and run.scenario is self.scenario

    def ready(self, run: HybridStep | None) -> None:
        """The next run, built off the loop (loop thread, while disarmed); one of a scenario no
        longer in force (a `set_hil` applied after it was built) is not taken."""
        if run is not None and run.scenario is self.scenario:
            self._next_run = run

    def _start(self, t: float) -> None:
        ready, run, self._next_run = self.run_ready(), self._next_run, None
        if not ready:
            log.warning("hil: run %d built in the loop (no run was ready)", self.runs + 1)
            run = self.build_run()
        self.step = run
        self._watch.reset()
        self._stream.restart()
        self.streaming = True
        self._stop_at = None
        self.runs += 1
        self.setpoints_sent = 0
        self.last_end = ""
        self._set_waveform("stream", self.envelope_m)
        log.info("hil: run %d of %s started (%d frames)", self.runs, self.scenario.kind,
                 self.step.substructure.steps)  # fmt: skip

    def _end(self, t: float, why: str) -> None:
        """No setpoint from this frame on; HOLD now, STOP (ramp to rest) `hold_s` later."""
        if not self.streaming:
            return
        self.streaming = False
        self._setpoint = None
        self.current = None
        self.reference.force_n = 0.0
        self.last_end = why
        self._set_waveform("hold", 0.0)
        self._stop_at = t + self.hold_s
        k = self.step.substructure.k if self.step is not None else 0
        log.info("hil: run %d ended at frame %d: %s", self.runs, k, why)

    def set_scenario(self, scenario: Scenario) -> None:
        """`set_hil`'s scenario for the next run (the loop thread, while disarmed)."""
        self.scenario = scenario
        self.step = None
        log.info("hil: next runs %s, %s compensation, %g s", scenario.law,
                 scenario.compensation.method, scenario.duration_s)  # fmt: skip

    def status(self) -> dict[str, Any]:
        sub = self.step.substructure if self.step is not None else None
        return {
            "kind": self.scenario.kind,
            "scenario": self.scenario_path,
            "scenario_sha256": self.scenario_sha256,
            "config": self.config_path,
            "config_sha256": self.config_sha256,
            "duration_s": self.scenario.duration_s,
            "envelope_m": self.envelope_m,
            "max_setpoint_velocity_m_s": self.playback_limits.velocity_m_s,
            "max_setpoint_acceleration_m_s2": self.playback_limits.acceleration_m_s2,
            "law": self.scenario.law if self.step is None else self.step.law.name,
            "compensation": self.scenario.compensation.method,
            "streaming": self.streaming,
            "runs": self.runs,
            "k": sub.k if sub is not None else 0,
            "setpoints_sent": self.setpoints_sent,
            "steps": self.scenario.steps,
            "delay_s": self.step.compensator.delay_s if self.step is not None else None,
            "ended": self.last_end,
        }


def hil_row_values(samples: np.ndarray) -> np.ndarray:
    """The streamed frames of a recording or telemetry (those with a model frame index)."""
    return samples[np.isfinite(samples["hil_k"])]
