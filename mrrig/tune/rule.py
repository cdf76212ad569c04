"""The tuning rule (pure): a grid of the controller's free parameters and the choice among
closed-loop trials by their measured Et (eqs 41-43), the paper's error norm.

A trial runs on a TUNING profile (the training excitation, or on a rig a profile of the same
kind), never on the validation cases: what it chooses is then judged on cases it has not seen.
A trial that faulted, or whose Et could not be measured, is never chosen: its Et says nothing
about the controller (a stall of the machine is not a property of the parameters).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from mrrig.errors import MrrigError

# the exact solve's pull toward the previous command (mrrig train's own candidates)
CONTINUITY_CANDIDATES = (0.0, 0.01, 0.03, 0.1, 0.3, 1.0)
# the load-cell feedback residual's low-pass: none (the last residual as it is) or 2 ms
FEEDBACK_TAU_CANDIDATES_S = (0.0, 0.002)
# the adaptation's forgetting time, where adaptation is on
ADAPTATION_MEMORY_CANDIDATES_S = (0.5, 2.0, 8.0)


class TuneError(MrrigError, ValueError):
    """No trial can be chosen (all faulted or unmeasured), or a grid that cannot be built."""


@dataclass(frozen=True)
class Candidate:
    """One setting of the free parameters. `feedback_tau_s` None: no load-cell feedback;
    `adaptation_memory_s` None: adaptation off (or not tuned)."""

    continuity: float
    feedback_tau_s: float | None = 0.0
    adaptation_memory_s: float | None = None

    def label(self) -> str:
        fb = "off" if self.feedback_tau_s is None else f"{self.feedback_tau_s * 1e3:g} ms"
        out = f"mu {self.continuity:g}, feedback tau {fb}"
        if self.adaptation_memory_s is not None:
            out += f", memory {self.adaptation_memory_s:g} s"
        return out

    def as_dict(self) -> dict[str, float | None]:
        return {
            "continuity": self.continuity,
            "feedback_tau_s": self.feedback_tau_s,
            "adaptation_memory_s": self.adaptation_memory_s,
        }


@dataclass(frozen=True)
class Trial:
    """A candidate's measured closed-loop Et on the tuning profile, and the faults seen."""

    candidate: Candidate
    et: float  # NaN: not measured
    faults: tuple[str, ...] = ()
    attempts: int = 1
    note: str = ""
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def usable(self) -> bool:
        return not self.faults and math.isfinite(self.et)

    def as_dict(self) -> dict:
        return {
            **self.candidate.as_dict(),
            "et": self.et if math.isfinite(self.et) else None,
            "faults": list(self.faults),
            "attempts": self.attempts,
            "usable": self.usable,
            "note": self.note,
            **self.extra,
        }


def grid(
    continuities: Iterable[float] = CONTINUITY_CANDIDATES,
    feedback_taus_s: Iterable[float | None] = FEEDBACK_TAU_CANDIDATES_S,
    adaptation_memories_s: Iterable[float | None] = (None,),
) -> list[Candidate]:
    """Every combination, continuity innermost (so a table reads by feedback, then mu)."""
    mus, taus, mems = list(continuities), list(feedback_taus_s), list(adaptation_memories_s)
    if not (mus and taus and mems):
        raise TuneError("grid: every axis needs at least one value")
    for mu in mus:
        if not (math.isfinite(mu) and mu >= 0):
            raise TuneError(f"continuity: {mu!r} must be a number >= 0")
    for tau in taus:
        if tau is not None and not (math.isfinite(tau) and 0 <= tau <= 10):
            raise TuneError(f"feedback_tau_s: {tau!r} must be in [0, 10] s")
    for mem in mems:
        if mem is not None and not (math.isfinite(mem) and mem > 0):
            raise TuneError(f"adaptation memory_s: {mem!r} must be > 0")
    return [Candidate(mu, tau, mem) for mem, tau, mu in itertools.product(mems, taus, mus)]


def choose(trials: Sequence[Trial]) -> Trial:
    """The usable trial (no fault, Et measured) with the smallest Et; ties go to the earlier
    trial of the grid. TuneError when none is usable."""
    usable = [t for t in trials if t.usable]
    if not usable:
        raise TuneError(
            f"no usable trial among {len(trials)}: every one faulted or had no measured Et"
        )
    return min(usable, key=lambda t: t.et)
