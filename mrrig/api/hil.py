"""A hybrid simulation on a live (or simulated) rig whose daemon runs `[hil]`: arm, let the
scenario play out, disarm, then judge the run from its telemetry (every frame's x_c, x_m and
the model's outputs) against the all-numerical reference (spec/hil.md, Metrics).

`run_on_rig(rig_name, scenario, zenoh_config, progress)` is what `mrrig hil --sim | --rig`
calls; `run_hil(rig, law=...)` the same from Python on a rig's own scenario (`mrrig.api`);
`judge(samples, reference)` and `hil_tracking(samples)` are pure numerics on the samples."""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mrrig.errors import MrrigError
from mrrig.hil.measured_stalls import measured_windows
from mrrig.hil.metrics import (
    ResponseError,
    StallApart,
    Tracking,
    WindowsApart,
    response_error,
    tracking,
    tracking_apart_from_stalls,
    tracking_apart_from_windows,
)
from mrrig.hil.playback import ActuatorLimits, infeasibility
from mrrig.hil.reference import DaemonCommand, ReferenceRun
from mrrig.hil.scenario import Scenario
from mrrig.rigio.run_identity import file_sha256

log = logging.getLogger(__name__)

STATUS_EVERY_S = 1.0
START_S = 5.0
REST_WAIT_S = 1.5  # the run's first streamed frame within this long of the arm


class HilRunError(MrrigError, RuntimeError):
    """The rig runs no hybrid simulation, or the run could not be judged."""


def daemon_command(config: str | Path) -> DaemonCommand:
    """The daemon's controller path of the config at `config` (its controller and model built
    as the daemon builds them: `build_controller`), for the reference; MrrigError (one line)
    where the config or its model does not load."""
    from mrrig.config import load_config
    from mrrig.loop.daemon import build_controller

    cfg = load_config(config)
    return DaemonCommand(
        build_controller(cfg),
        period_s=cfg.loop.period_s,
        i_max_a=cfg.loop.i_max_a,
        max_current_slew_a_per_s=cfg.loop.max_current_slew_a_per_s,
        f_range_n=cfg.loop.f_range_n,
        kalman_q=cfg.estimator.q,
        kalman_r0_m2=cfg.estimator.r0_m2,
    )


def rig_command(hil_status: dict[str, Any]) -> DaemonCommand | None:
    """The controller path of the daemon whose status' `hil` is `hil_status`: its config file,
    where this machine has the same one (sha256, as the simulated rig's); None where not (a
    live rig's config elsewhere: the reference then inverts the simulator's model exactly)."""
    path = hil_status.get("config")
    if not path or file_sha256(path) != hil_status.get("config_sha256"):
        log.warning(
            "the rig's daemon config %s is not on this machine: the reference inverts the "
            "simulator's damper model exactly, not with the daemon's controller",
            path,
        )
        return None
    return daemon_command(path)


def rig_limits(hil_status: dict[str, Any]) -> ActuatorLimits:
    """What the daemon whose status' `hil` is `hil_status` lets its actuator play."""
    return ActuatorLimits(
        hil_status["envelope_m"],
        hil_status["max_setpoint_velocity_m_s"],
        hil_status["max_setpoint_acceleration_m_s2"],
    )


def playback_problem(scenario: Scenario, hil_status: dict[str, Any]) -> str | None:
    """A playback's feasibility check against the rig's limits, before arming: one line
    naming the first frame its actuator cannot play, or None (also for a model's scenario)."""
    if scenario.kind != "playback":
        return None
    return infeasibility(
        scenario.played_stroke(), rig_limits(hil_status), str(scenario.playback.file)
    )


@dataclass(frozen=True)
class HilResult:
    frames: int  # streamed frames received
    missing: int  # frames of the run not in the telemetry
    tracking: Tracking | None  # None: a run that faulted too soon to judge
    errors: dict[str, ResponseError]  # per output, against the reference (the same frames)
    figures: dict[str, float]  # RMS of the HIL run's outputs
    delay_s: float  # the last delay estimate
    end: dict[str, Any]  # the rig's status at the end
    retried: tuple[str, ...] = ()  # the transport faults of the runs before this one
    samples: np.ndarray | None = None  # the run's telemetry (every frame)
    apart: StallApart | None = None  # J2, J3 apart from what a measured stall explains


def _streamed(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, model frame index) of a run's streamed frames, each frame once."""
    rows = samples[np.isfinite(samples["hil_k"])]
    if rows.size <= 60:
        raise HilRunError(f"{rows.size} streamed frames: too few to judge")
    k, first = np.unique(rows["hil_k"].astype(int), return_index=True)
    return rows[first], k


def hil_tracking(samples: np.ndarray, period_s: float = 0.002) -> Tracking:
    """J1-J3 (spec/hil.md, Metrics) of a HIL run's samples: a `Telemetry`'s, a `Recording`'s
    (`Recording(path).samples`) or a `HilResult`'s; the streamed frames of the last run in
    them if it holds more than one (the model's frame index starts again at 0). HilRunError
    where they hold too few streamed frames (a daemon without `[hil]`: none)."""
    starts = np.flatnonzero(samples["hil_k"] == 0)
    rows, _ = _streamed(samples[starts[-1] :] if starts.size else samples)
    return tracking(rows["hil_x_c"], rows["x"], period_s)


def judge(samples: np.ndarray, reference: ReferenceRun) -> tuple[int, int, Tracking, dict, dict]:
    """(frames, missing, J1-J3, response errors, RMS figures) of a run's streamed samples."""
    rows, k = _streamed(samples)
    missing = int(k[-1] + 1 - k.size)
    period = reference.scenario.period_s
    t = tracking(rows["hil_x_c"], rows["x"], period)
    # the damper's stroke: the quarter car's suspension travel, the building's first storey's
    # drift (the damper sits between the ground and the first floor)
    stroke = (rows["hil_x_c"], reference.stroke_m[k])
    if "body_acceleration_m_s2" in reference.outputs:
        outputs = {"suspension_travel_m": stroke}
        outputs["body_acceleration_m_s2"] = (
            rows["hil_acc"],
            reference.outputs["body_acceleration_m_s2"][k],
        )
        outputs["tyre_load_n"] = (rows["hil_load_n"], reference.outputs["tyre_load_n"][k])
    elif "force_n" in reference.outputs:  # a playback: the damper's force on the stroke
        # (its stroke is the record: J1-J3 say how the actuator played it)
        outputs = {"force_n": (rows["f_meas"], reference.outputs["force_n"][k])}
    else:
        outputs = {"storey_1_drift_m": stroke}
        outputs["roof_acceleration_m_s2"] = (
            rows["hil_acc"],
            reference.outputs["acceleration_m_s2"][k, -1],
        )
    errors = {name: response_error(y, y_ref) for name, (y, y_ref) in outputs.items()}
    figures = {
        name: (float(np.sqrt(np.mean(y**2))), float(np.sqrt(np.mean(y_ref**2))))
        for name, (y, y_ref) in outputs.items()
    }
    return int(k.size), missing, t, errors, figures


def stall_apart(samples: np.ndarray, period_s: float) -> StallApart:
    """J2 and J3 of a run's streamed samples apart from the frames a measured stall of the
    loop explains (`tracking_apart_from_stalls`); the peak's time from the run's start."""
    rows, _k = _streamed(samples)
    t = rows["t"] - rows["t"][0]
    return tracking_apart_from_stalls(rows["hil_x_c"], rows["x"], t, rows["latency_us"], period_s)


def measured_apart(
    samples: np.ndarray,
    sim_stats: dict[str, Any],
    daemon_summary: dict[str, Any],
    period_s: float,
) -> tuple[WindowsApart, list]:
    """J2 and J3 of a simulated run's streamed samples apart from the stalls the actuator,
    the simulator and the kernel measured (`mrrig.hil.measured_stalls`), on the run's clock
    (from its first streamed frame); and those windows, unmerged."""
    rows, _k = _streamed(samples)
    t0 = float(rows["t"][0])
    windows = measured_windows(sim_stats, daemon_summary, t0)
    t = rows["t"] - t0
    return tracking_apart_from_windows(rows["hil_x_c"], rows["x"], t, windows, period_s), windows


def run_hil(
    rig,
    *,
    law: str | None = None,
    compensation: str | None = None,
    duration_s: float | None = None,
    scenario: str | Path | None = None,
    progress: Callable[[str], None] | None = None,
    zenoh_config: str | Path | None = None,
) -> HilResult:
    """One hybrid-simulation run (a model's scenario or a stroke playback) on a rig whose
    daemon runs `[hil]`, from Python: `rig` an open `mrrig.api.Rig` or a rig's name. `law`,
    `compensation`, `duration_s`: the daemon's next runs' (a `set_hil` request, while
    disarmed). The run's scenario is the daemon's (its status' `hil.scenario`) unless
    `scenario` names the file here; either way the file here must be the daemon's (sha256).
    The reference is computed, a playback checked against the rig's limits, then the rig is
    armed, followed to the run's end (`progress` gets a line a second), disarmed, and the run
    judged: the `HilResult`'s `tracking` (J1-J3), `errors` and `figures` against the
    reference, `end` the rig's status. HilRunError (one line) where it cannot run."""
    from mrrig.api.live import Rig
    from mrrig.hil.reference import run_reference
    from mrrig.hil.scenario import load_scenario

    if isinstance(rig, str):
        with Rig(rig, zenoh_config=zenoh_config) as opened:
            return run_hil(
                opened, law=law, compensation=compensation, duration_s=duration_s,
                scenario=scenario, progress=progress,
            )  # fmt: skip
    hil = rig.status().get("hil")
    if not hil:
        raise HilRunError(
            f"rig {rig.name} runs no hybrid simulation (its daemon has no [hil] scenario)"
        )
    change = {"law": law, "compensation": compensation, "duration_s": duration_s}
    change = {k: v for k, v in change.items() if v is not None}
    if change:
        rig.request({"cmd": "set_hil", **change})
        hil = rig.status()["hil"]
    path = Path(scenario if scenario is not None else hil["scenario"])
    if not path.is_file() or file_sha256(path) != hil.get("scenario_sha256"):
        raise HilRunError(
            f"rig {rig.name}'s daemon runs scenario {hil['scenario']} (sha256 "
            f"{str(hil.get('scenario_sha256'))[:12]}), which {path} here is not"
        )
    s = load_scenario(path, law=hil["law"])
    method = dataclasses.replace(s.compensation, method=hil["compensation"])
    s = dataclasses.replace(s, duration_s=hil["duration_s"], compensation=method)
    if (why := playback_problem(s, hil)) is not None:  # before the reference's work
        raise HilRunError(why)
    reference = run_reference(s, command=rig_command(hil))
    return follow(rig, s, reference, progress or log.info)


def run_on_rig(
    rig_name: str,
    scenario: Scenario,
    reference: ReferenceRun,
    zenoh_config: Path,
    progress: Callable[[str], None],
    tries: int = 1,
) -> HilResult:
    """Arm the rig (its daemon runs the scenario), follow it once a second until the run
    ends, disarm, and judge the telemetry; a run ended by a transport fault is run again from
    its start (`follow_tries`)."""
    from mrrig.api import Rig

    with Rig(rig_name, zenoh_config=zenoh_config) as rig:
        return follow_tries(rig, scenario, reference, progress, tries)


def follow_tries(
    rig,
    scenario: Scenario,
    reference: ReferenceRun,
    progress: Callable[[str], None],
    tries: int = 1,
) -> HilResult:
    """`follow`; a run ended by a transport fault (a stall of the bus or a process:
    `TRANSPORT_FAULTS`) is run again from its start (the daemon starts a fresh run at each
    arm, never resumes one) after a `reset` and the piston's return to rest, up to `tries`
    runs in all, as `mrrig demo` re-arms after one; each such fault, with its reason, is in
    `HilResult.retried` and said by `progress`. The result is the last run's."""
    from mrrig.loop.safety import TRANSPORT_FAULTS

    retried: list[str] = []
    while True:
        result = follow(rig, scenario, reference, progress)
        fault = result.end.get("fault")
        if fault not in TRANSPORT_FAULTS or len(retried) + 1 >= tries:
            return dataclasses.replace(result, retried=tuple(retried))
        why = f"{fault}: {result.end.get('fault_reason')}"
        retried.append(why)
        progress(f"the run ended by a transport fault ({why}): reset, and run it from its start")
        rig.reset()
        time.sleep(1.0)  # HOLD, then STOP: the piston back at rest


def follow(
    rig, scenario: Scenario, reference: ReferenceRun, progress: Callable[[str], None]
) -> HilResult:
    """One run on an open `mrrig.api.Rig` whose daemon runs `scenario` (disarmed): arm,
    follow it once a second until the run ends, disarm, judge the telemetry. A plan's `hil`
    step calls it after its `set_hil`."""
    status = rig.status()
    hil = status.get("hil")
    if not hil:
        raise HilRunError(
            f"rig {rig.name} runs no hybrid simulation (its daemon has no [hil] scenario)"
        )
    if hil["kind"] != scenario.kind or hil["steps"] != scenario.steps:
        raise HilRunError(
            f"rig {rig.name} runs a {hil['kind']} of {hil['steps']} frames, not this "
            f"{scenario.kind} of {scenario.steps}"
        )
    if (why := playback_problem(scenario, hil)) is not None:
        raise HilRunError(why)
    telemetry = rig.telemetry(quiet_s=scenario.duration_s + 60.0)
    done = threading.Event()

    def collect() -> None:
        for _ in telemetry:
            if done.is_set():
                break

    reader = threading.Thread(target=collect, name="hil-telemetry", daemon=True)
    reader.start()
    # the subscriber declared, and the piston at rest: a daemon just started sent STOP
    # (its config's motion ramps out over the firmware's 0.5 s); a run armed while it still
    # moved gave the delay estimator motion no setpoint made (26 ms at frame 15: a trip)
    time.sleep(REST_WAIT_S)
    runs0 = hil["runs"]
    reply = rig.arm()
    if not reply.get("ok", True) and reply.get("state") != "ARMED":
        raise HilRunError(f"arm refused: {reply.get('error', reply)}")
    t0 = time.monotonic()
    try:
        while True:
            time.sleep(STATUS_EVERY_S)
            status = rig.status()
            h = status["hil"]
            started = h["runs"] > runs0
            delay = h["delay_s"]
            progress(
                f"{time.monotonic() - t0:6.1f} s  frame {h['k']:>6}/{h['steps']}  "
                f"{status['state']:<5}  delay "
                + (f"{delay * 1e3:.2f} ms" if delay is not None else "-")
            )
            if started and not h["streaming"]:
                break
            if status["state"] != "ARMED" and (started or time.monotonic() - t0 > START_S):
                break
    finally:
        if rig.status()["state"] == "ARMED":
            rig.disarm()
        time.sleep(0.5)  # the last batches
        done.set()
        reader.join(timeout=5.0)
    end = rig.status()
    try:
        frames, missing, t, errors, figures = judge(telemetry.samples, reference)
        apart = stall_apart(telemetry.samples, scenario.period_s)
    except HilRunError as exc:
        if end.get("fault") is None:
            raise
        frames, missing, t, errors, figures, apart = 0, 0, None, {}, {}, None
        progress(f"not judged: {exc}")
    delay_s = end["hil"]["delay_s"] or 0.0
    return HilResult(
        frames, missing, t, errors, figures, delay_s, end, samples=telemetry.samples, apart=apart
    )
