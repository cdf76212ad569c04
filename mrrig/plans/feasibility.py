"""A step's force profile judged before arming: the share of its samples that ask a
semi-active damper for force against the motion (`mrrig.loop.feasibility`), from the step's
reference and the actuator's stroke, where both are known ahead.

Known: a constant, sine, noise, CSV, Bouc-Wen or paper-case reference on a sine stroke (the
range over the phase between the two, which the rig sets when it arms), or on no stroke.
Unknown: an external (Zenoh) reference, a RANDOM stroke (the firmware's own record), a
reference or stroke the step leaves as the daemon has it, a CSV file not readable here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from mrrig.config import LoopSection, ReferenceSection
from mrrig.loop import reference as ref
from mrrig.loop.feasibility import predicted_shares
from mrrig.plans.plan import Step


@dataclass(frozen=True)
class Prediction:
    low: float | None  # None: unknown
    high: float | None
    why: str  # what it rests on, or why it is unknown

    def text(self) -> str:
        if self.low is None or self.high is None:
            return f"force against the motion: unknown ({self.why})"
        span = (
            f"{self.low:.1%}"
            if self.high - self.low < 0.01
            else f"{self.low:.1%} to {self.high:.1%} (with the phase between reference and stroke"
            " the rig sets when it arms)"
        )
        return f"force against the motion: {span} of the samples ({self.why})"


def _maker(section: ReferenceSection, dt_s: float) -> Callable[[], ref.ForceReference]:
    """A new reference per call, as the daemon builds it from the same section."""
    s = section
    if s.kind == "constant":
        return lambda: ref.Constant(s.offset_n)
    if s.kind == "sine":
        return lambda: ref.Sine(s.offset_n, s.amplitude_n, s.freq_hz)
    if s.kind == "noise":
        return lambda: ref.Noise(s.offset_n, s.amplitude_n, s.freq_hz, s.seed, dt_s)
    if s.kind == "csv":
        series = ref.CsvSeries(s.path)  # read once; a ForceReferenceError if not readable
        return lambda: series
    if s.kind == "bouc_wen":
        return lambda: ref.BoucWenReference(
            s.preset, s.current_a, s.current_amp_a, s.current_freq_hz, dt_s
        )
    if s.kind == "paper_case":
        return lambda: ref.PaperCase(s.case, s.current_scale, s.preset, dt_s)
    raise ref.ForceReferenceError(f"a {s.kind} reference is known only as it comes")


def before_arming(step: Step, dt_s: float = LoopSection.period_s) -> Prediction:
    """The share of the step's samples that will ask for force against the motion."""
    if step.reference is None or step.actuator is None:
        which = "reference" if step.reference is None else "actuator"
        return Prediction(None, None, f"the step keeps the daemon's {which}")
    a = step.actuator
    if a.waveform == "random":
        return Prediction(None, None, "a RANDOM stroke: the firmware's own record")
    if a.waveform == "stream":
        return Prediction(None, None, "a STREAM stroke: the setpoints' own, known as they come")
    try:
        make = _maker(step.reference, dt_s)
    except ref.ForceReferenceError as exc:
        return Prediction(None, None, str(exc))
    moving = a.waveform == "sine" and a.amplitude_m > 0 and a.frequency_hz > 0
    amplitude, frequency = (a.amplitude_m, a.frequency_hz) if moving else (0.0, 0.0)
    shares = predicted_shares(make, amplitude, frequency, step.duration_s, dt_s)
    stroke = (
        f"{a.amplitude_m * 1e3:g} mm {a.frequency_hz:g} Hz sine stroke"
        if moving
        else "no stroke (a damper at rest gives no force to follow)"
    )
    return Prediction(
        float(shares.min()), float(shares.max()), f"{step.reference.kind} on {stroke}"
    )
