"""The tuning trials on a live rig, through its control plane only (`mrrig.api.Rig`): each
candidate of the grid is one short closed-loop step of a test plan (`mrrig.plans.runner`:
reset out of a FAULT, disarm, actuator, `set_controller`, `set_profile`, arm, telemetry,
disarm) on the tuning profile, its Et measured over the armed samples after settling.

A trial aborted by a transport fault (a stall of the machine or the bus, not the controller)
runs once more after a reset; faulted again, or by any other fault, it is kept in the table,
marked, and never chosen. The choice writes the continuity where the daemon reads it (the
model file's `meta.online_continuity`) and the feedback time constant as a config snippet.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import logging
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from mrrig import json_text
from mrrig.api import Rig, RigError
from mrrig.config import ActuatorSection, ControllerSection, ReferenceSection
from mrrig.loop.mlp import MLP
from mrrig.loop.safety import TRANSPORT_FAULTS
from mrrig.plans.criteria import Criteria
from mrrig.plans.plan import Plan, Step
from mrrig.plans.runner import StepResult, run_plan
from mrrig.tune.rule import Candidate, Trial, TuneError, choose

log = logging.getLogger(__name__)

Progress = Callable[[str], None]

# the controller whose free parameters are tuned (the daemon's default)
CONTROLLER = "network_inversion"


@dataclass(frozen=True)
class TuningProfile:
    """What every trial runs: the actuator's motion and the force reference. Of the kind of
    the training excitation (random motion, a reference damper's force with a moving current),
    never a validation case."""

    actuator: ActuatorSection
    reference: ReferenceSection
    duration_s: float = 8.0
    settle_s: float = 2.0

    def describe(self) -> str:
        a, r = self.actuator, self.reference
        return (
            f"actuator {a.waveform} {a.amplitude_m * 1e3:g} mm {a.frequency_hz:g} Hz;"
            f" reference {r.kind} ({r.preset}, {r.current_a:g} A + {r.current_amp_a:g} A at"
            f" {r.current_freq_hz:g} Hz); {self.settle_s:g} s settling + {self.duration_s:g} s"
        )


# Data set A's training displacement is noise 0-3 Hz (spec/modeling.md section 4 A): here 2 cm
# peak within the simulated 4 cm stroke; the reference damper's current sweeps 0.2-1.6 A, the
# range of the characterization matrix the rig's model is trained on. The validation cases
# use other bands, amplitudes and currents (configs/plans/paper-validation.toml).
DEFAULT_PROFILE = TuningProfile(
    actuator=ActuatorSection(waveform="random", amplitude_m=0.02, frequency_hz=3.0),
    reference=ReferenceSection(
        kind="bouc_wen", preset="rig-current", current_a=0.9, current_amp_a=0.7, current_freq_hz=0.7
    ),
)
_ACTUATOR_FIELDS = ("waveform", "amplitude_m", "frequency_hz")
_REFERENCE_FIELDS = ("kind", "preset", "current_a", "current_amp_a", "current_freq_hz")


@dataclass
class TuneResult:
    trials: list[Trial]
    chosen: Trial | None  # None: interrupted, or no usable trial (`why`)
    model: str  # the daemon's model file (its path as the daemon names it)
    interrupted: bool = False
    why: str = ""  # why nothing was chosen
    files: dict[str, str] = field(default_factory=dict)  # what was written, by role


def _step(c: Candidate, profile: TuningProfile, model: str | None) -> Step:
    if c.adaptation_memory_s is not None:
        raise TuneError(
            "adaptation memory: not settable through the control plane (the daemon's"
            " [adaptation] memory_s); tune it offline (mrrig bench paper) or per daemon start"
        )
    controller = ControllerSection(
        name=CONTROLLER,
        model=Path(model) if model else None,
        feedback=c.feedback_tau_s is not None,
        feedback_tau_s=c.feedback_tau_s or 0.0,
        continuity=c.continuity,
    )
    fields = ("name", "feedback", "feedback_tau_s", "continuity") + (("model",) if model else ())
    return Step(
        name=c.label(),
        duration_s=profile.duration_s,
        settle_s=profile.settle_s,
        actuator=profile.actuator,
        controller=controller,
        reference=profile.reference,
        criteria=Criteria(),
        given={
            "actuator": _ACTUATOR_FIELDS,
            "set_controller": fields,
            "set_profile": _REFERENCE_FIELDS,
        },
    )


def _trial(c: Candidate, r: StepResult, attempts: int, before: str = "") -> Trial:
    """The trial from its (last) step; `before`: why the attempt before it was run again."""
    et = r.numbers.et if r.numbers is not None else math.nan
    reasons = [before] if before else []
    reasons += r.reasons if r.verdict != "passed" else []
    note = "; ".join(reasons)
    extra = {}
    if r.numbers is not None:
        extra = {
            "peak_current_a": r.numbers.peak_current_a,
            "latency_p99_us": r.numbers.latency_p99_us,
            "samples": r.numbers.samples,
        }
    return Trial(c, et, tuple(r.faults), attempts, note, extra)


def daemons_model(rig: Rig, model: str | None) -> str:
    """The model file the trials use: `model`, else the daemon's own, as its reply to a
    `set_controller` of the tuned controller names it (while disarmed)."""
    rig.disarm()
    req = {"cmd": "set_controller", "name": CONTROLLER} | ({"model": model} if model else {})
    try:
        reply = rig.request(req)
    except RigError as exc:
        raise TuneError(f"set_controller {CONTROLLER}: {exc}") from None
    return str(reply.get("settings", {}).get("model", model))


def run_trials(
    rig: Rig,
    candidates: Sequence[Candidate],
    profile: TuningProfile,
    progress: Progress,
    model: str | None = None,
    catalog: str | None = None,
) -> TuneResult:
    """Every candidate as one closed-loop trial; a trial aborted by a transport fault once
    more. Ctrl-C ends the trials (the rig disarmed by the runner) without a choice, and so
    does a grid whose every trial faulted."""
    model = daemons_model(rig, model)
    progress(f"tuning {CONTROLLER} with {model}: {len(candidates)} trials; {profile.describe()}")
    trials: list[Trial] = []
    for k, c in enumerate(candidates, start=1):
        trial, interrupted = _run_one(rig, k, len(candidates), c, profile, model, progress, catalog)
        trials.append(trial)
        if interrupted:  # the trial's last reason names the signal
            why = trial.note.split("; ")[-1] or "interrupted"
            return TuneResult(trials, None, model, interrupted=True, why=why)
    try:
        return TuneResult(trials, choose(trials), model)
    except TuneError as exc:
        return TuneResult(trials, None, model, why=str(exc))


def _run_one(
    rig: Rig,
    k: int,
    n: int,
    c: Candidate,
    profile: TuningProfile,
    model: str,
    progress: Progress,
    catalog: str | None = None,
) -> tuple[Trial, bool]:
    plan = Plan(
        name=f"tune trial {k}/{n}", path=Path("<mrrig tune>"), steps=(_step(c, profile, model),)
    )
    progress(f"trial {k}/{n}: {c.label()}")
    before = ""
    for attempt in (1, 2):
        # each attempt a run in the catalog (plan "tune trial k/n", step the candidate)
        (result,), interrupted = run_plan(plan, rig, progress, catalog)
        trial = _trial(c, result, attempt, before)
        transport = result.faults and all(f in TRANSPORT_FAULTS for f in result.faults)
        if interrupted or not transport or attempt == 2:
            break
        before = f"attempt 1: transport fault {', '.join(result.faults)}, run again"
        progress(f"trial {k}/{n}: {before} after a reset")
    progress(f"trial {k}/{n}: " + trial_line(trial))
    return trial, interrupted


def trial_line(t: Trial) -> str:
    et = f"Et {t.et:.4f}" if math.isfinite(t.et) else "Et -"
    faults = f", faults {','.join(t.faults)}" if t.faults else ""
    return f"{t.candidate.label()}: {et}{faults}" + ("" if t.usable else " (not usable)")


def table(trials: Sequence[Trial], chosen: Trial | None) -> str:
    head = (
        f"{'#':>2}  {'continuity':>10} {'fb tau ms':>9} {'Et':>8} {'I peak A':>8}"
        f" {'tries':>5}  faults"
    )
    rows = [head, "-" * len(head)]
    for k, t in enumerate(trials, start=1):
        c = t.candidate
        tau = "off" if c.feedback_tau_s is None else f"{c.feedback_tau_s * 1e3:g}"
        et = f"{t.et:.4f}" if math.isfinite(t.et) else "-"
        peak = t.extra.get("peak_current_a")
        peak_text = f"{peak:.3f}" if peak is not None else "-"
        mark = "  <- chosen" if t is chosen else ""
        rows.append(
            f"{k:>2}  {c.continuity:>10g} {tau:>9} {et:>8} {peak_text:>8} {t.attempts:>5}"
            f"  {','.join(t.faults) or '-'}{mark}" + (f"  ({t.note})" if t.note else "")
        )
    return "\n".join(rows)


def write_trials(result: TuneResult, json_path: Path, profile: TuningProfile, rig: str) -> None:
    """The trial table as JSON (with the profile, the rig and the choice) and as CSV beside,
    each written to a temporary file and renamed into place: a table is whole or not there.
    An interrupted tune's table goes to `<name>.interrupted.json` (and .csv): the last
    complete tune's table stays (an interrupted tune overwrote it)."""
    if result.interrupted:
        json_path = json_path.with_name(f"{json_path.stem}.interrupted{json_path.suffix}")
    record = {
        "rig": rig,
        "model": result.model,
        "when_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "profile": profile.describe(),
        "chosen": result.chosen.as_dict() if result.chosen else None,
        "interrupted": result.interrupted,
        "trials": [t.as_dict() for t in result.trials],
    }
    json_path.parent.mkdir(parents=True, exist_ok=True)
    csv_path = json_path.with_suffix(".csv")
    rows = [t.as_dict() for t in result.trials]
    text = io.StringIO()
    if rows:  # interrupted before its first trial: an empty table
        writer = csv.DictWriter(text, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    _write_whole(csv_path, text.getvalue())
    _write_whole(json_path, json_text.dumps(record, indent=2))
    result.files |= {"trials": str(json_path), "trials_csv": str(csv_path)}


def _write_whole(path: Path, text: str) -> None:
    """`text` into `path` through a temporary file beside it, renamed into place."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with tmp.open("w", newline="") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_choice(result: TuneResult, model_path: Path, rig: str) -> None:
    """The chosen continuity into the model file's meta (`online_continuity`: the daemon takes
    it where its [controller] gives none) and the feedback time constant as a config snippet
    beside it (`<model>.tune.toml`: [controller] feedback_tau_s, to merge into the daemon's
    config; the control plane's `set_controller` does not outlive the daemon)."""
    chosen = result.chosen
    if chosen is None:
        raise TuneError("no choice to write")
    model = MLP.load(model_path)
    c = chosen.candidate
    model.meta["online_continuity"] = c.continuity
    model.meta["online_continuity_rule"] = (
        f"mrrig tune on rig {rig}: closed-loop Et {chosen.et:.4f} on the tuning profile,"
        f" the smallest of {len(result.trials)} trials ({result.files.get('trials', '-')})"
    )
    model.save(model_path)
    snippet = model_path.with_suffix(".tune.toml")
    feedback = c.feedback_tau_s is not None
    when = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    trials = result.files.get("trials", "-")
    snippet.write_text(
        f"# mrrig tune on rig {rig}, {when}:\n"
        f"# closed-loop Et {chosen.et:.4f} on the tuning profile ({trials}).\n"
        f"# The continuity ({c.continuity:g}) is in {model_path}'s meta.online_continuity, which\n"
        "# the daemon takes while [controller] sets no continuity. Merge this into its config:\n"
        "[controller]\n"
        f"feedback = {'true' if feedback else 'false'}\n"
        f"feedback_tau_s = {c.feedback_tau_s or 0.0!r}\n"
    )
    result.files |= {"model": str(model_path), "config_snippet": str(snippet)}


def apply_choice(rig: Rig, result: TuneResult) -> dict:
    """Put the written choice in force on the rig now (while disarmed): `set_controller` with
    the chosen feedback and no continuity, so that the daemon reads the one written into the
    model file; returns the settings it reports in force."""
    if result.chosen is None:
        raise TuneError("no choice to apply")
    c = result.chosen.candidate
    rig.disarm()
    try:
        reply = rig.request(
            {
                "cmd": "set_controller",
                "name": CONTROLLER,
                "model": result.model,
                "feedback": c.feedback_tau_s is not None,
                "feedback_tau_s": c.feedback_tau_s or 0.0,
            }
        )
    except RigError as exc:
        raise TuneError(f"set_controller with the chosen values: {exc}") from None
    return reply.get("settings", {})
