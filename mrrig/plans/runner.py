"""Run a plan on a live rig through its public interfaces only (control requests, status,
telemetry over Zenoh: `mrrig.api.Rig`), step by step.

Per step: out of FAULT by an explicit `reset` (spec/system.md: a new step needs it), disarm,
the step's actuator, controller and profile, arm, settle, telemetry for the step's duration,
disarm, verdict. A fault aborts the step with the fault's reason (with `faults = "transport"`
a transport fault is reset and re-armed, and counted, at most 3 times in any 10 s: one more is
a faulty bus, and aborts the step; a hil step's run is never re-armed mid-scenario: one a
transport fault ended is run again from its start, `mrrig.plans.hil_step.hil_tries`); Ctrl-C
disarms, marks the step aborted and ends the plan.
The arm's lease is renewed in the background while the step holds the rig (`mrrig.api.Rig`):
a plan killed mid-step leaves the daemon to disarm and stop the actuator once it lapses; the
plan's end (normal or Ctrl-C) stops the actuator.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mrrig.api import Rig, RigError, register_run
from mrrig.api.live import RigUnanswered
from mrrig.errors import MrrigError
from mrrig.interruption import what
from mrrig.loop.safety import TRANSPORT_FAULTS
from mrrig.loop.samples import SAMPLE_DTYPE
from mrrig.plans.criteria import Numbers, failures, measure
from mrrig.plans.feasibility import Prediction, before_arming
from mrrig.plans.hil_step import HilNumbers, hil_failures, hil_numbers, law_tables, run_hil_step
from mrrig.plans.interrupts import interruptible
from mrrig.plans.plan import Plan, Step
from mrrig.rigio.client import ClientError
from mrrig.rigio.control import MAX_MARK_CHARS, MAX_MARK_DATA_CHARS
from mrrig.rigio.rearm import RearmLimit

log = logging.getLogger(__name__)

STATUS_PERIOD_S = 0.25  # how often a running step asks for the status (faults)
# a running step goes on while the rig's control plane or telemetry is silent for up to this
# long (a stall of the machine: the daemon keeps its own safety); longer, it is aborted
CONTROL_PATIENCE_S = 10.0
PROGRESS_PERIOD_S = 1.0


@dataclass
class StepResult:
    step: Step
    verdict: str  # "passed", "failed", "aborted", "skipped"
    reasons: list[str] = field(default_factory=list)
    numbers: Numbers | None = None
    faults: list[str] = field(default_factory=list)
    rearms: int = 0
    wall_s: float = 0.0
    samples: np.ndarray = field(default_factory=lambda: np.empty(0, SAMPLE_DTYPE))
    controller: str | None = None
    recording: str | None = None  # the daemon's recording the step is in
    # the daemon's run identity as in force at the step's start (its status): specimen, the
    # model's path and sha256 as deployed, controller parameters, config and DBC sha256
    identity: dict = field(default_factory=dict)
    # the share of desired forces against the motion, as known before arming
    predicted: Prediction | None = None
    hil: HilNumbers | None = None  # a hil step's run against its reference


# what a step's catalog row takes from the daemon's identity in force (`StepResult.identity`)
STEP_IDENTITY = (
    "specimen",
    "controller_params",
    "model_path",
    "model_sha256",
    "config_sha256",
    "dbc_sha256",
)


class StepAborted(MrrigError):
    """The step cannot go on: a fault (its reason) or a refused request."""


Progress = Callable[[str], None]


def run_plan(
    plan: Plan,
    rig: Rig,
    progress: Progress,
    catalog: str | None = None,
    campaign: str | None = None,
) -> tuple[list[StepResult], bool]:
    """Every step in order, and whether Ctrl-C ended the plan (the step it came in aborted,
    the rig disarmed, the rest `skipped`). With `catalog`, each step run is registered there
    as a run (plan, step, verdict, numbers; `campaign`, which groups them) when it ends."""
    results: list[StepResult] = []
    interrupted = False
    for index, step in enumerate(plan.steps, start=1):
        if interrupted:
            results.append(StepResult(step, "skipped", ["not run: the plan was interrupted"]))
            continue
        result = StepResult(step, "aborted")
        t0, started_utc = time.monotonic(), dt.datetime.now(dt.UTC)
        where = f"plan {plan.name}: step {index}/{len(plan.steps)} {step.name}"
        try:
            _mark(rig, f"{where}: start", _start_data(plan, index, step))
            with interruptible():  # a stop signal interrupts the step, never its ending
                run = _run_step if step.hil is None else _run_hil_step
                run(index, len(plan.steps), step, rig, result, progress)
        except StepAborted as exc:
            result.verdict, result.reasons = "aborted", [str(exc)]
        except KeyboardInterrupt as exc:
            interrupted = True
            reason = f"interrupted ({what(exc)}): the rig disarmed"
            result.verdict, result.reasons = "aborted", [reason]
        finally:
            _disarm(rig)
            result.wall_s = time.monotonic() - t0
            _mark(rig, f"{where}: end, {result.verdict}", _end_data(plan, index, result))
        results.append(result)
        progress(_step_line(index, len(plan.steps), result))
        if catalog is not None:
            _register(catalog, plan, rig, result, started_utc, campaign)
    return results, interrupted


def _register(
    catalog: str,
    plan: Plan,
    rig: Rig,
    r: StepResult,
    started_utc: dt.datetime,
    campaign: str | None,
) -> None:
    """The step's run into the catalog; a catalog that cannot take it does not stop the plan."""
    n = r.numbers
    numbers = {}
    if n is not None:
        numbers = {
            "et": n.et,
            "peak_current_a": n.peak_current_a,
            "latency_p99_us": n.latency_p99_us,
            "temp_max_degc": n.temperature_max_degc,
        }
    traced = {k: r.identity[k] for k in STEP_IDENTITY if r.identity.get(k) is not None}
    if r.step.hil is not None:  # the law the run had (its figures: the plan's table, reports)
        traced["tags"] = [f"hil:{r.step.hil.law}"]
    try:
        register_run(
            rig.name,
            started_utc,
            ended_utc=dt.datetime.now(dt.UTC),
            **traced,
            catalog=catalog,
            plan=plan.name,
            step=r.step.name,
            campaign=campaign,
            verdict=r.verdict,
            controller=r.controller or "",
            faults=[{"fault": f} for f in r.faults],
            faults_count=len(r.faults),
            operator=rig.operator,
            recording_path=r.recording,  # still being written: no sha256 yet
            **numbers,
        )
    except MrrigError as exc:
        log.error("step %s not registered in the catalog: %s", r.step.name, exc)


def _mark(rig: Rig, text: str, data: dict) -> None:
    """A marker in the rig's recording (`mark`: its telemetry process writes it, and audits
    the request); a rig that takes none (a daemon from before `mark`, or without telemetry)
    does not stop the plan."""
    if len(json.dumps(data)) > MAX_MARK_DATA_CHARS:
        data = {k: v for k, v in data.items() if k in ("plan", "step", "name")}
        data["note"] = "settings too long for a mark: see the plan"
    try:
        rig.request({"cmd": "mark", "text": text[:MAX_MARK_CHARS], "data": data})
    except (RigError, ClientError) as exc:
        log.warning("no marker in the recording (%s): %s", text, exc)


def _start_data(plan: Plan, index: int, step: Step) -> dict:
    """The step's settings, as it sends them."""
    settings = {r["cmd"]: {k: v for k, v in r.items() if k != "cmd"} for r in step.requests()}
    return {
        "plan": plan.name,
        "step": index,
        "name": step.name,
        "duration_s": step.duration_s,
        "settle_s": step.settle_s,
        "settings": settings,
    }


def _end_data(plan: Plan, index: int, r: StepResult) -> dict:
    """The step's verdict and numbers (JSON has no NaN: an undefined number is null)."""
    out = {"plan": plan.name, "step": index, "name": r.step.name, "verdict": r.verdict}
    if r.numbers is not None:
        for key in ("et", "opposed_share", "peak_current_a", "latency_p99_us"):
            value = getattr(r.numbers, key)
            out[key] = None if math.isnan(value) else value
    return out | {"faults": r.faults, "reasons": "; ".join(r.reasons)[:300]}


def _disarm(rig: Rig) -> None:
    """SAFE whatever happened (a second Ctrl-C here is not honoured: the disarm comes first)."""
    try:
        rig.disarm()
    except (RigError, OSError) as exc:
        log.error("disarm after the step: %s", exc)


def _request(rig: Rig, req: dict) -> None:
    """A request the step needs: refused, or not answered (ClientError), the step is aborted
    (and the rig disarmed after it), never the plan."""
    try:
        rig.request(req)
    except (RigError, ClientError) as exc:
        raise StepAborted(str(exc)) from None


def _status(rig: Rig) -> dict:
    try:
        return rig.status()
    except (RigError, ClientError) as exc:
        raise StepAborted(f"no status from the rig: {exc}") from None


def _out_of_fault(rig: Rig) -> None:
    status = _status(rig)
    if status["state"] != "FAULT":
        return
    log.info("rig in FAULT (%s): reset before the step", status.get("fault"))
    try:
        rig.reset()
    except (RigError, ClientError) as exc:
        if "unknown command" in str(exc):  # a daemon from before `reset`
            raise StepAborted(
                f"the rig is in FAULT ({status.get('fault')}) and its daemon has no `reset` "
                f"command to leave it ({exc}): restart the daemon"
            ) from None
        raise StepAborted(f"reset of the FAULT ({status.get('fault')}) refused: {exc}") from None
    _wait_state(rig, "IDLE")


def _wait_state(rig: Rig, state: str, timeout_s: float = 3.0) -> dict:
    """The status once in `state`: the sidecar answers with the daemon's last published one,
    which may lag a request by a status period."""
    deadline = time.monotonic() + timeout_s
    while (status := _status(rig))["state"] != state:
        if time.monotonic() > deadline:
            raise StepAborted(f"the rig is {status['state']}, not {state}, after {timeout_s:g} s")
        time.sleep(0.05)
    return status


def _set_up(step: Step, rig: Rig, result: StepResult) -> None:
    """Out of FAULT, disarmed, the step's requests sent; what the rig has in force noted."""
    _out_of_fault(rig)
    try:
        rig.disarm()  # asked again where the daemon did not answer in time
    except (RigError, ClientError) as exc:
        raise StepAborted(str(exc)) from None
    for req in step.requests():
        _request(rig, req)
    status = _status(rig)
    result.controller = status.get("controller")
    result.identity = status.get("identity") or {}  # a daemon from before it carried one: {}
    recording = status.get("recording")  # the sidecar's file, or the loop's "failed: ..."
    result.recording = recording.get("path") if isinstance(recording, dict) else None


def _run_hil_step(
    index: int, count: int, step: Step, rig: Rig, result: StepResult, progress: Progress
) -> None:
    """One hybrid-simulation run of the step's law (`mrrig.plans.hil_step`): the rig's own
    end of the run (the scenario played out, a fault) ends the step; its numbers against the
    reference."""
    from mrrig.api.hil import HilRunError

    _set_up(step, rig, result)
    law = step.hil.law
    progress(f"  step {index}/{count} {step.name}: {law}, the reference computed, then arm")
    try:
        run = run_hil_step(rig, step, lambda line: progress(f"  step {index}/{count} {line}"))
    except (ValueError, HilRunError, RigError, ClientError) as exc:
        raise StepAborted(str(exc)) from None
    result.samples = run.samples
    result.numbers = measure(run.samples, 0.0)
    result.hil = hil_numbers(law, run)
    # the transport faults of the runs before (each run again from the scenario's start)
    result.faults += [why.partition(":")[0] for why in run.retried]
    result.rearms = len(run.retried)
    fault = run.end.get("fault")
    if fault is not None:
        result.faults.append(fault)
    result.reasons = failures(step.criteria, result.numbers, result.faults)
    result.reasons += hil_failures(step.criteria, result.hil)
    result.verdict = "failed" if result.reasons else "passed"


def _run_step(
    index: int, count: int, step: Step, rig: Rig, result: StepResult, progress: Progress
) -> None:
    _set_up(step, rig, result)
    result.predicted = before_arming(step)
    progress(f"  step {index}/{count} {step.name}: {result.predicted.text()}")
    tele = rig.telemetry(duration_s=step.settle_s + step.duration_s, quiet_s=CONTROL_PATIENCE_S)
    try:
        rig.arm()  # an arm left unanswered: disarmed and asked again (mrrig.api.Rig.arm)
    except (RigError, ClientError) as exc:
        raise StepAborted(str(exc)) from None
    rearms = RearmLimit()  # per step: a faulty bus aborts it (mrrig.rigio.rearm)
    t0 = last_status = last_progress = answered = time.monotonic()
    total = step.settle_s + step.duration_s
    for _batch in tele:
        now = time.monotonic()
        if now - last_status >= STATUS_PERIOD_S:
            last_status = now
            try:
                _check_faults(step, rig, result, rearms)
                answered = time.monotonic()
            except (ClientError, RigUnanswered) as exc:  # a loaded rig: asked again
                if time.monotonic() - answered > CONTROL_PATIENCE_S:
                    raise StepAborted(
                        f"the rig's control plane did not answer for {CONTROL_PATIENCE_S:g} s:"
                        f" {exc}"
                    ) from None
                log.warning("no status from the rig (going on): %s", exc)
        if now - last_progress >= PROGRESS_PERIOD_S:
            last_progress = now
            numbers = measure(tele.samples, step.settle_s)
            phase = "settling" if now - t0 < step.settle_s else "running"
            progress(
                f"  step {index}/{count} {step.name}: {now - t0:4.0f}/{total:g} s {phase}, "
                f"Et {numbers.et:.4f}, faults {len(result.faults)}"
            )
    end = time.monotonic() + CONTROL_PATIENCE_S
    while True:  # the step's last status: asked again while a loaded rig does not answer
        try:
            _check_faults(step, rig, result, rearms)
            break
        except (ClientError, RigUnanswered) as exc:
            if time.monotonic() > end:
                raise StepAborted(f"no status from the rig at the step's end: {exc}") from None
            log.warning("no status from the rig at the step's end (asking again): %s", exc)
            time.sleep(STATUS_PERIOD_S)
    result.samples = tele.samples
    if time.monotonic() - t0 < total - 1.0:
        raise StepAborted(f"telemetry stopped after {time.monotonic() - t0:.1f} s")
    result.numbers = measure(result.samples, step.settle_s)
    result.reasons = failures(step.criteria, result.numbers, result.faults)
    result.verdict = "failed" if result.reasons else "passed"


def _check_faults(step: Step, rig: Rig, result: StepResult, limit: RearmLimit) -> None:
    status = rig.status()
    if status["state"] != "FAULT":
        return
    fault = status.get("fault") or "unknown"
    reason = status.get("fault_reason") or fault
    result.faults.append(fault)
    if step.criteria.faults == "transport" and fault in TRANSPORT_FAULTS:
        log.warning("transport fault %s (%s): reset and re-arm", fault, reason)
        try:
            rig.rearm(limit)
        except RigError as exc:
            raise StepAborted(f"{exc}; the last: fault {fault}: {reason}") from None
        result.rearms += 1
        return
    raise StepAborted(f"fault {fault}: {reason}")


def _step_line(index: int, count: int, r: StepResult) -> str:
    why = f": {'; '.join(r.reasons)}" if r.reasons else ""
    return f"step {index}/{count} {r.step.name}: {r.verdict.upper()}{why}"


def table(results: list[StepResult]) -> str:
    """The console table at the end: one row per step; `against`: the share of its desired
    forces that oppose the motion (no current of a semi-active damper gives them); after a
    step that has a floor (a step's `floor_of` names it), the floor's Et and Et/floor."""
    head = (
        f"{'#':>2}  {'step':<24} {'verdict':<8} {'Et':>8} {'I peak A':>8} {'lat p99 us':>10}"
        f" {'T max':>7} {'against':>7} faults"
    )
    rows = [head, "-" * len(head)]
    floors = {r.step.floor_of: (i, r) for i, r in enumerate(results, start=1) if r.step.floor_of}
    for i, r in enumerate(results, start=1):
        n = r.numbers
        nums = (
            f"{n.et:>8.4f} {n.peak_current_a:>8.3f} {n.latency_p99_us:>10.0f}"
            f" {n.temperature_max_degc:>7.1f} {n.opposed_share:>7.1%}"
            if n
            else f"{'-':>8} {'-':>8} {'-':>10} {'-':>7} {'-':>7}"
        )
        beside = ", ".join(f"{k} {v:.4f}" for k, v in r.step.compare_et.items())
        floor = floors.get(r.step.name)
        rows.append(
            f"{i:>2}  {r.step.name[:24]:<24} {r.verdict:<8} {nums} {','.join(r.faults) or '-'}"
            + (f"  (Et {beside})" if beside else "")
            + (_floor_text(r, *floor) if floor else "")
        )
    hil = law_tables([(r.step.name, r.hil) for r in results if r.hil is not None])
    return "\n".join(rows + ([""] if hil else []) + hil)


def floor_ratio(result: StepResult, floor: StepResult) -> float:
    """A step's Et over its floor's (the floor step's Et: e.g. the reference damper's own
    current through the same chain); NaN where either has no Et."""
    if result.numbers is None or floor.numbers is None:
        return math.nan
    et, et_floor = result.numbers.et, floor.numbers.et
    return et / et_floor if et_floor > 0 else math.nan


def _floor_text(r: StepResult, index: int, floor: StepResult) -> str:
    et = floor.numbers.et if floor.numbers is not None else math.nan
    return f"  floor {et:.4f} (step {index}), Et/floor {floor_ratio(r, floor):.2f}"


def overall(results: list[StepResult]) -> str:
    return "passed" if results and all(r.verdict == "passed" for r in results) else "failed"
