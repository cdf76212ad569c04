"""A step's numbers from its telemetry and its verdict against the plan's criteria (numerics:
no I/O).

Et is the paper's error norm (`mrrig.offline.metrics.error_norm`) over the samples whose force
answers an armed command, after the step's settling time; peak current, latency p99, the
highest temperature and the share of desired forces against the motion (which a semi-active
damper cannot give: `mrrig.loop.feasibility`) over the same samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from mrrig.loop.coverage import outside_shares
from mrrig.loop.feasibility import opposed_share
from mrrig.loop.safety import TRANSPORT_FAULTS
from mrrig.loop.samples import RigState
from mrrig.offline.metrics import error_norm

# each limit's physical range (low, high, unit): a damper's coil takes at most 5 A (the
# daemon's i_max_a bound), its fluid works between about -40 and 150 degC; -1e300 degC was
# accepted and failed every step
_RANGES = {
    "et_max": (0.0, 100.0, ""),  # Et: 0 perfect, 1 no better than zero force
    "peak_current_a_max": (0.0, 5.0, " A"),
    "latency_p99_us_max": (0.0, 1e6, " us"),
    "temperature_max_degc": (-40.0, 250.0, " degC"),
}


# the criteria only a hil step has
HIL_CRITERIA = ("agreement_pct_max", "j1_ms_max", "j2_pct_max", "j3_pct_max")


@dataclass(frozen=True)
class Criteria:
    et_max: float | None = None  # the paper's error norm over the armed samples after settling
    faults: Literal["none", "transport"] = "none"  # transport: stalls are re-armed, counted
    peak_current_a_max: float | None = None
    latency_p99_us_max: float | None = None
    temperature_max_degc: float | None = None
    # the share of samples outside the model's training envelope (mrrig/loop/coverage.py)
    coverage_outside_max: float | None = None
    # a hil step's (mrrig/plans/hil_step.py): each RMS figure of the run within this % of the
    # reference's; the RTHS benchmark's tracking delay J1 (|ms|), J2 and J3 (%)
    agreement_pct_max: float | None = None
    j1_ms_max: float | None = None
    j2_pct_max: float | None = None
    j3_pct_max: float | None = None

    def check(self) -> None:
        for name in ("et_max", "peak_current_a_max", "latency_p99_us_max", *HIL_CRITERIA):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name}: must be > 0")
        for name, (low, high, unit) in _RANGES.items():
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and low <= value <= high):
                raise ValueError(f"{name}: {value!r} is outside [{low:g}, {high:g}]{unit}")
        for name in HIL_CRITERIA:
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value <= 1000):
                raise ValueError(f"{name}: {value!r} is outside (0, 1000]")
        share = self.coverage_outside_max
        if share is not None and not 0 <= share <= 1:
            raise ValueError("coverage_outside_max: must be in [0, 1] (a share of the samples)")


@dataclass(frozen=True)
class Numbers:
    samples: int  # armed samples after settling
    et: float  # NaN: no armed sample, or a desired force without spread (a constant)
    peak_current_a: float
    latency_p99_us: float
    temperature_max_degc: float
    # of the samples, those whose desired force opposes the estimated velocity: Et near 1
    # with a large share is the profile, not the controller
    opposed_share: float = math.nan
    # of the samples, those outside the model's training envelope (NaN: it keeps none)
    outside_share: float = math.nan


def judged_samples(samples: np.ndarray, settle_s: float) -> np.ndarray:
    """The armed samples from `settle_s` after the first armed one on."""
    armed = samples[samples["state"] == RigState.ARMED]
    if armed.size == 0:
        return armed
    return armed[armed["t"] >= armed["t"][0] + settle_s]


def measure(samples: np.ndarray, settle_s: float) -> Numbers:
    s = judged_samples(samples, settle_s)
    if s.size == 0:
        nan = math.nan
        return Numbers(0, nan, nan, nan, nan)
    ok = np.isfinite(s["f_des"]) & np.isfinite(s["f_meas"])
    f_des, f_meas = s["f_des"][ok], s["f_meas"][ok]
    spread = f_des.size > 1 and float(np.ptp(f_des)) > 0
    et = error_norm(f_des, f_meas) if spread else math.nan
    return Numbers(
        samples=int(s.size),
        et=et,
        peak_current_a=float(np.nanmax(np.abs(s["i_cmd"]))),
        latency_p99_us=float(np.nanpercentile(s["latency_us"], 99)),
        temperature_max_degc=_nanmax(s["temp_degc"]),
        opposed_share=opposed_share(s["f_des"], s["xd"]),
        outside_share=outside_shares(s["outside"])["outside_share"],
    )


def _nanmax(values: np.ndarray) -> float:
    """The largest finite value; NaN where there is none (a channel the rig does not have)."""
    finite = values[np.isfinite(values)]
    return float(finite.max()) if finite.size else math.nan


# why a criterion's number is NaN, by its field (the samples are there: `failures` checks it)
_UNDEFINED = {
    "et_max": "a desired force without spread?",
    "peak_current_a_max": "no commanded current in the samples",
    "latency_p99_us_max": "no latency in the samples",
    "temperature_max_degc": "the rig reports no damper temperature: its profile maps no"
    " damper_temperature; leave this criterion out",
}


def failures(criteria: Criteria, numbers: Numbers, faults: list[str]) -> list[str]:
    """Why the step failed (empty: passed): each criterion not met, with the number."""
    out = []
    if numbers.samples == 0:
        return ["no armed sample after settling (the rig never ran armed)"]
    allowed = TRANSPORT_FAULTS if criteria.faults == "transport" else frozenset()
    bad = [f for f in faults if f not in allowed]
    if bad:
        out.append(f"faults: {', '.join(bad)} (allowed: {criteria.faults})")
    limits = (
        ("et_max", "Et", numbers.et, ""),
        ("peak_current_a_max", "peak current", numbers.peak_current_a, " A"),
        ("latency_p99_us_max", "latency p99", numbers.latency_p99_us, " us"),
        ("temperature_max_degc", "temperature max", numbers.temperature_max_degc, " degC"),
    )
    for field, what, value, unit in limits:
        limit = getattr(criteria, field)
        if limit is None:
            continue
        if math.isnan(value):
            out.append(f"{field}: {what} is undefined ({_UNDEFINED[field]})")
        elif value > limit:
            out.append(
                f"{field}: {what} {value:.4g}{unit} > {limit:g}{unit}" + _why(field, numbers)
            )
    limit = criteria.coverage_outside_max
    if limit is not None:
        share = numbers.outside_share
        if math.isnan(share):
            out.append("coverage_outside_max: the model keeps no training envelope to judge by")
        elif share > limit:
            out.append(
                f"coverage_outside_max: {share:.1%} of the samples outside the model's training"
                f" envelope > {limit:.1%}"
            )
    return out


def criteria_rows(
    criteria: Criteria, numbers: Numbers | None, faults: list[str]
) -> list[tuple[str, str, str, str]]:
    """Each criterion of the step with its limit, the measured value and whether it was met
    (`met`, `not met`, `not measured`): the test record's table (`failures` says why)."""
    allowed = TRANSPORT_FAULTS if criteria.faults == "transport" else frozenset()
    bad = [f for f in faults if f not in allowed]
    rows = [
        (
            "faults",
            "none" if criteria.faults == "none" else "transport faults only (re-armed)",
            ", ".join(faults) or "none",
            "not met" if bad else "met",
        )
    ]
    measured = {
        "et_max": ("Et", None if numbers is None else numbers.et, "", ".4f"),
        "peak_current_a_max": (
            "peak current", None if numbers is None else numbers.peak_current_a, " A", ".3f"
        ),
        "latency_p99_us_max": (
            "latency p99", None if numbers is None else numbers.latency_p99_us, " us", ".0f"
        ),
        "temperature_max_degc": (
            "temperature max", None if numbers is None else numbers.temperature_max_degc,
            " degC", ".1f",
        ),
        "coverage_outside_max": (
            "outside the training envelope", None if numbers is None else numbers.outside_share,
            "", ".1%",
        ),
    }  # fmt: skip
    for field, (what, value, unit, fmt) in measured.items():
        limit = getattr(criteria, field)
        if limit is None:
            continue
        limit_text = f"<= {limit:.1%}" if fmt == ".1%" else f"<= {limit:g}{unit}"
        if value is None or math.isnan(value):
            rows.append((what, limit_text, "n/a", "not measured"))
        else:
            met = "met" if value <= limit else "not met"
            rows.append((what, limit_text, f"{value:{fmt}}{unit}", met))
    return rows


# an Et failure with at least this share of forces against the motion says so
EXPLAIN_SHARE = 0.05


def _why(field: str, numbers: Numbers) -> str:
    if field != "et_max" or not numbers.opposed_share >= EXPLAIN_SHARE:
        return ""
    return (
        f" ({numbers.opposed_share:.1%} of the desired forces oppose the motion: a semi-active"
        " damper cannot give them at any current)"
    )
