"""A plan's `hil` step (spec/hil.md; the quarter-car plan of issue 41): one hybrid-simulation
run of the `[hil]` daemon's scenario with the step's law (`set_hil`), judged against the same
scenario computed all-numerically (the reference), and the plan's table of the laws.

Per step: the RMS of each output of the run (quarter car: body acceleration, suspension travel,
dynamic tyre load; building: the first storey's drift, the roof's acceleration) beside the
reference's over the same frames, their agreement (% difference), and the RTHS benchmark's J1-J3.
The plan's table sets the laws side by side with each one's % change against the passive-soft
and passive-hard steps of the plan, for the HIL runs and for the reference.

`hil_numbers`, `hil_failures`, `hil_criteria_rows` and `law_tables` are numerics on a run's
result; `run_hil_step` is the step on the rig (through `mrrig.api.hil.follow`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from mrrig.config import ACTUATOR_AMPLITUDE_MAX_M
from mrrig.hil.metrics import StallApart, Tracking
from mrrig.hil.reference import ReferenceRun, envelope_problem, percent_change, run_reference
from mrrig.hil.scenario import Scenario, load_scenario
from mrrig.plans.criteria import Criteria
from mrrig.plans.plan import Step
from mrrig.rigio.run_identity import file_sha256

# each output's label in the table, and its unit's scale
OUTPUTS = {
    "body_acceleration_m_s2": ("body acc", "m/s^2", 1.0),
    "suspension_travel_m": ("travel", "mm", 1e3),
    "tyre_load_n": ("tyre load", "N", 1.0),
    "storey_1_drift_m": ("storey-1 drift", "mm", 1e3),
    "roof_acceleration_m_s2": ("roof acc", "m/s^2", 1.0),
    "force_n": ("damper force", "N", 1.0),  # a playback's
}
# a figure the rig cannot give above this force (the load cell's, as `mrrig hil`)
FORCE_LIMIT_N = 6000.0
# runs in all of a hil step with `faults = "transport"` (`mrrig hil --tries`' default)
HIL_TRIES = 3


@dataclass(frozen=True)
class HilNumbers:
    """A hil step's run: its law, frames, J1-J3, and per output (HIL RMS, reference RMS)."""

    law: str
    frames: int
    missing: int
    tracking: Tracking | None
    rms: dict[str, tuple[float, float]]
    apart: StallApart | None = None  # J2, J3 apart from what a measured stall explains
    # how far the judged run went (the model's frames of the scenario's) and why it ended
    end_k: int = 0
    steps: int = 0
    ended: str = ""

    def unfinished(self) -> str | None:
        """Why the run is not the whole scenario (a fault ended it early), None if it is."""
        if self.end_k >= self.steps:
            return None
        return f"the run ended at frame {self.end_k} of {self.steps}: {self.ended or '-'}"

    def agreement_pct(self) -> dict[str, float]:
        """Each output's RMS against the reference's: 100 (HIL - reference) / reference."""
        return {name: percent_change(hil, ref) for name, (hil, ref) in self.rms.items()}


def hil_numbers(law: str, result) -> HilNumbers:
    """The numbers of a `mrrig.api.hil.HilResult`."""
    h = result.end.get("hil") or {}
    return HilNumbers(
        law, result.frames, result.missing, result.tracking, result.figures, result.apart,
        end_k=int(h.get("k", 0)), steps=int(h.get("steps", 0)), ended=str(h.get("ended", "")),
    )  # fmt: skip


def _label(name: str) -> tuple[str, str, float]:
    return OUTPUTS.get(name, (name, "", 1.0))


def _limits(criteria: Criteria, numbers: HilNumbers) -> list[tuple[str, str, float, float, str]]:
    """(criterion, what, value, limit, unit) of each hil criterion the step sets."""
    out = []
    if criteria.agreement_pct_max is not None:
        for name, pct in numbers.agreement_pct().items():
            what = f"{_label(name)[0]} RMS against the reference"
            out.append(("agreement_pct_max", what, abs(pct), criteria.agreement_pct_max, " %"))
    t = numbers.tracking
    for field, what, value, unit in (
        ("j1_ms_max", "|J1| tracking delay", None if t is None else abs(t.j1_ms), " ms"),
        ("j2_pct_max", "J2 RMS tracking error", None if t is None else t.j2_pct, " %"),
        ("j3_pct_max", "J3 peak tracking error", None if t is None else t.j3_pct, " %"),
    ):
        limit = getattr(criteria, field)
        if limit is not None:
            out.append((field, what, math.nan if value is None else value, limit, unit))
    return out


def hil_failures(criteria: Criteria, numbers: HilNumbers | None) -> list[str]:
    """Why the hil step failed its hil criteria (empty: met them all)."""
    if numbers is None:
        return ["the run was not judged (no HIL numbers)"]
    out = []
    # a part of the scenario is not the scenario: whatever faults the step allows (a run a
    # transport fault ended was run again from its start, `run_hil_step`'s tries)
    if (why := numbers.unfinished()) is not None:
        out.append(why)
    if criteria.agreement_pct_max is not None and not numbers.rms:
        out.append("agreement_pct_max: the run was not judged (too few frames)")
    for field, what, value, limit, unit in _limits(criteria, numbers):
        if math.isnan(value):
            out.append(f"{field}: {what} is undefined (the run was not judged)")
        elif value > limit:
            out.append(f"{field}: {what} {value:.2f}{unit} > {limit:g}{unit}")
    return out


def hil_criteria_rows(
    criteria: Criteria, numbers: HilNumbers | None
) -> list[tuple[str, str, str, str]]:
    """The test record's rows of the hil criteria: (criterion, limit, measured, met)."""
    if numbers is None:
        return []
    rows = []
    for _field, what, value, limit, unit in _limits(criteria, numbers):
        if math.isnan(value):
            rows.append((what, f"<= {limit:g}{unit}", "n/a", "not measured"))
        else:
            met = "met" if value <= limit else "not met"
            rows.append((what, f"<= {limit:g}{unit}", f"{value:.2f}{unit}", met))
    return rows


def _change(value: float, against: float | None) -> str:
    return "-" if against is None else f"{percent_change(value, against):+.1f}"


def law_tables(rows: Sequence[tuple[str, HilNumbers]]) -> list[str]:
    """The plan's tables of its hil steps ((step name, numbers), in plan order): the RMS
    figures of the HIL run and the reference side by side with their agreement, then each
    law's % change against the plan's passive-soft and passive-hard steps, HIL / reference."""
    rows = [(name, n) for name, n in rows if n.rms]
    if not rows:
        return []
    first = rows[0][1]
    outputs = sorted(first.rms, key=lambda name: list(OUTPUTS).index(name))
    head = f"{'step':<18} {'law':<16}"
    for name in outputs:
        label, unit, _ = _label(name)
        head += f" | {label + ' ' + unit:>19} {'agree':>7}"
    head += f" | {'J1 ms':>6} {'J2 %':>6} {'J3 %':>6} {'apart':>6}"
    lines = ["HIL run beside the reference (RMS: HIL / reference; agree: % difference)", head]
    lines.append("-" * len(head))
    for step, n in rows:
        line = f"{step[:18]:<18} {n.law:<16}"
        agree = n.agreement_pct()
        for name in outputs:
            _, _, scale = _label(name)
            hil, ref = n.rms[name]
            line += f" | {hil * scale:>9.4g}/{ref * scale:<9.4g} {agree[name]:>+6.2f}%"
        t = n.tracking
        line += (
            f" | {t.j1_ms:>6.2f} {t.j2_pct:>6.2f} {t.j3_pct:>6.2f}"
            if t is not None
            else f" | {'-':>6} {'-':>6} {'-':>6}"
        )
        line += f" {n.apart.j3_pct:>6.2f}" if n.apart is not None else f" {'-':>6}"
        lines.append(line)
    lines.append("apart: J3 apart from the frames a measured stall of the loop explains")
    passive = {n.law: n for _, n in rows if n.law in ("passive-soft", "passive-hard")}
    lines += ["", "% change against passive-soft and passive-hard (HIL / reference)"]
    head = f"{'step':<18} {'law':<16}"
    for against in ("passive-soft", "passive-hard"):
        for name in outputs:
            head += f" | {against[8:] + ' ' + _label(name)[0]:>13}"
    lines += [head, "-" * len(head)]
    for step, n in rows:
        line = f"{step[:18]:<18} {n.law:<16}"
        for against in ("passive-soft", "passive-hard"):
            p = passive.get(against)
            for name in outputs:
                hil, ref = n.rms[name]
                p_hil, p_ref = p.rms[name] if p is not None else (None, None)
                line += f" | {_change(hil, p_hil):>6}/{_change(ref, p_ref):<6}"
        lines.append(line)
    return lines


def step_scenario(step: Step) -> Scenario:
    """The scenario the step runs: the file's, with the step's law, compensation, duration."""
    h = step.hil
    scenario = load_scenario(h.scenario, law=h.law)
    scenario = dataclasses.replace(scenario, duration_s=step.duration_s)
    if h.compensation is not None:
        c = dataclasses.replace(scenario.compensation, method=h.compensation)
        scenario = dataclasses.replace(scenario, compensation=c)
    return scenario


def before_arming(step: Step, hil_status: dict | None) -> tuple[Scenario, ReferenceRun]:
    """The step's scenario and reference, once the daemon (its status' `hil`) is known to run
    that scenario file; ValueError (one line) where it runs another, or none, or the
    reference's stroke or force does not fit the rig."""
    path = step.hil.scenario
    if not hil_status:
        raise ValueError("the rig runs no hybrid simulation (its daemon has no [hil] scenario)")
    sha = file_sha256(path)
    if hil_status.get("scenario_sha256") != sha:
        raise ValueError(
            f"the rig's daemon runs scenario {hil_status.get('scenario')} (sha256 "
            f"{str(hil_status.get('scenario_sha256'))[:12]}), not this step's {path} (sha256 "
            f"{str(sha)[:12]}): start it with --hil {path}"
        )
    from mrrig.api.hil import rig_command

    scenario = step_scenario(step)
    reference = run_reference(scenario, command=rig_command(hil_status))
    stroke_m = hil_status.get("envelope_m", ACTUATOR_AMPLITUDE_MAX_M)
    problem = envelope_problem(reference.figures(), stroke_m, FORCE_LIMIT_N)
    if problem is not None:
        raise ValueError(f"{path} with {step.hil.law}: {problem}: it does not fit the rig")
    return scenario, reference


def hil_tries(step: Step) -> int:
    """Runs in all a hil step may take: with `faults = "transport"` a run that a transport
    fault ended is run again from the scenario's start (never resumed, never judged in part),
    up to HIL_TRIES; otherwise one (a fault fails the step)."""
    return HIL_TRIES if step.criteria.faults == "transport" else 1


def run_hil_step(rig, step: Step, progress: Callable[[str], None]):
    """The step's run on the rig (disarmed, `set_hil` sent): its `HilResult` (the last run's,
    `retried` the transport faults of the runs before it), with the reference beside it.
    ValueError or `mrrig.api.hil.HilRunError` where it cannot run."""
    from mrrig.api.hil import follow_tries

    scenario, reference = before_arming(step, rig.status().get("hil"))
    return follow_tries(rig, scenario, reference, progress, hil_tries(step))
