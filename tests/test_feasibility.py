"""A force profile's feasibility for a semi-active damper (mrrig/loop/feasibility.py): the
share of samples that ask for force against the motion, predicted before arming from a plan
step (mrrig/plans/feasibility.py) and measured in the step's numbers and the run summary."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest

from mrrig.loop.feasibility import (
    F_DEADBAND_N,
    PHASES,
    V_DEADBAND_M_S,
    opposed,
    opposed_share,
    predicted_shares,
)
from mrrig.loop.reference import BoucWenReference, Constant, Sine
from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.loop.summary import format_summary, summarize
from mrrig.plans.criteria import Criteria, failures, measure
from mrrig.plans.feasibility import before_arming
from mrrig.plans.plan import load_plan
from tests.conftest import REPO

DT = 0.002


def test_a_force_against_the_velocity_beyond_both_deadbands_is_opposed():
    f = np.array([200.0, -200.0, 200.0, -200.0, 40.0, 200.0, np.nan, 200.0])
    v = np.array([0.1, 0.1, -0.1, -0.1, -0.1, -0.004, -0.1, np.nan])
    assert opposed(f, v).tolist() == [False, True, True, False, False, False, False, False]
    assert opposed_share(f, v) == pytest.approx(2 / 8)
    assert math.isnan(opposed_share(np.empty(0), np.empty(0)))
    # the deadbands are strict: at them a sample is not counted
    assert not opposed(np.array([F_DEADBAND_N]), np.array([-1.0]))[0]
    assert not opposed(np.array([-1000.0]), np.array([V_DEADBAND_M_S]))[0]


def test_a_sine_force_on_a_sine_stroke_of_its_frequency_depends_on_the_phase():
    shares = predicted_shares(lambda: Sine(0.0, 300.0, 1.0), 0.01, 1.0, 10.0, DT)
    assert shares.shape == (PHASES,)
    # in phase with the velocity (a quarter period ahead of the stroke): none against it;
    # in antiphase nearly all (the deadbands leave out the zero crossings)
    assert shares.min() < 0.01 and shares.max() > 0.85


def test_a_constant_force_on_a_sine_stroke_opposes_it_half_the_time_whatever_the_phase():
    shares = predicted_shares(lambda: Constant(300.0), 0.01, 1.0, 10.0, DT)
    # |xd| > 5 mm/s for all but asin(5 / 62.8) / (pi / 2) of the time, against it half of that
    expected = 0.5 * (1 - math.asin(V_DEADBAND_M_S / (0.01 * 2 * math.pi)) / (math.pi / 2))
    assert shares == pytest.approx(expected, abs=0.005)
    no_stroke = predicted_shares(lambda: Constant(300.0), 0.0, 0.0, 10.0, DT)
    assert (no_stroke == 0).all()


def test_the_bouc_wen_reference_damper_asks_little_against_the_motion():
    """Its force is a damper's own: against the motion only at the reversals (hysteresis)."""

    def make():
        return BoucWenReference("rig-current", 0.8, 0.5, 0.5, DT)

    shares = predicted_shares(make, 0.01, 1.0, 10.0, DT)
    print(f"Bouc-Wen reference, 10 mm 1 Hz: {shares.min():.2%} to {shares.max():.2%}")
    assert shares.max() < 0.02


def samples(f_des: np.ndarray, xd: np.ndarray) -> np.ndarray:
    s = np.zeros(f_des.size, SAMPLE_DTYPE)
    s["t"] = np.arange(f_des.size) * DT
    s["f_des"], s["xd"] = f_des, xd
    s["f_meas"] = 0.5 * f_des
    s["state"] = RigState.ARMED
    s["temp_degc"] = 30.0
    return s


def test_the_step_numbers_and_the_run_summary_measure_it_on_the_frames():
    t = np.arange(5000) * DT
    xd = 0.0628 * np.cos(2 * np.pi * t)
    f_des = 300.0 + 100.0 * np.sin(2 * np.pi * t)  # always in tension: against every return
    s = samples(f_des, xd)
    expected = opposed_share(f_des, xd)
    assert 0.4 < expected < 0.5
    assert measure(s, settle_s=0.0).opposed_share == pytest.approx(expected)
    # the summary counts the frames whose force answers an armed command (all but the first)
    d = summarize(s, [])
    against = d["force_against_motion"]
    assert against["frames"] == int(opposed(f_des[1:], xd[1:]).sum())
    assert against["share"] == pytest.approx(against["frames"] / (s.size - 1))
    assert "ask force against the motion" in format_summary(d)


def test_an_et_failure_says_when_the_profile_asks_force_against_the_motion():
    t = np.arange(5000) * DT
    xd = 0.0628 * np.cos(2 * np.pi * t)
    infeasible = measure(samples(300.0 + 100.0 * np.sin(2 * np.pi * t), xd), 0.0)
    (reason,) = failures(Criteria(et_max=0.1), infeasible, [])
    assert reason.startswith("et_max: Et ") and "oppose the motion" in reason
    feasible = measure(samples(100.0 * np.cos(2 * np.pi * t), xd), 0.0)
    assert feasible.opposed_share == 0.0
    (reason,) = failures(Criteria(et_max=0.1), feasible, [])
    assert "oppose" not in reason


PLAN = """
[plan]
name = "feasibility"

[[step]]
name = "{name}"
duration_s = 10
{fields}
"""


def step_of(tmp_path, name: str, fields: str):
    path = tmp_path / "plan.toml"
    path.write_text(textwrap.dedent(PLAN.format(name=name, fields=textwrap.dedent(fields))))
    return load_plan(path).steps[0]


def test_before_arming_a_step_of_a_known_reference_and_stroke_is_judged(tmp_path):
    sine = step_of(
        tmp_path,
        "sine on sine",
        """
        actuator = { waveform = "sine", amplitude_m = 0.01, frequency_hz = 1.0 }
        reference = { kind = "sine", amplitude_n = 300.0, freq_hz = 1.0 }
        """,
    )
    p = before_arming(sine)
    assert p.low < 0.01 and p.high > 0.85
    assert "with the phase between reference and stroke" in p.text()
    constant = step_of(
        tmp_path,
        "tension",
        """
        actuator = { waveform = "sine", amplitude_m = 0.01, frequency_hz = 1.0 }
        reference = { kind = "sine", offset_n = 300.0, amplitude_n = 100.0, freq_hz = 0.5 }
        """,
    )
    p = before_arming(constant)
    assert 0.4 < p.low <= p.high < 0.5
    assert p.text().startswith("force against the motion: 4")


def test_the_smoke_plans_bouc_wen_step_is_judged_feasible():
    plan = load_plan(REPO / "configs/plans/smoke.toml")
    bouc_wen = next(s for s in plan.steps if s.reference and s.reference.kind == "bouc_wen")
    p = before_arming(bouc_wen)
    print(p.text())
    assert p.high < 0.02


@pytest.mark.parametrize(
    ("fields", "why"),
    [
        (
            """
            actuator = { waveform = "sine", amplitude_m = 0.01, frequency_hz = 1.0 }
            reference = { kind = "zenoh" }
            """,
            "known only as it comes",
        ),
        (
            """
            actuator = { waveform = "random", amplitude_m = 0.01, frequency_hz = 5.0 }
            reference = { kind = "sine", amplitude_n = 100.0 }
            """,
            "RANDOM stroke",
        ),
        ('reference = { kind = "sine", amplitude_n = 100.0 }', "keeps the daemon's actuator"),
        (
            """
            actuator = { waveform = "sine", amplitude_m = 0.01, frequency_hz = 1.0 }
            reference = { kind = "csv", path = "no/such/profile.csv" }
            """,
            "no/such/profile.csv",
        ),
    ],
)
def test_before_arming_what_is_not_known_ahead_is_unknown(tmp_path, fields, why):
    p = before_arming(step_of(tmp_path, "unknown", fields))
    assert p.low is None and p.high is None
    assert p.text().startswith("force against the motion: unknown (") and why in p.text()


def test_a_paper_case_reference_is_judged_before_arming(tmp_path):
    step = step_of(
        tmp_path,
        "case 1, k=2",
        """
        actuator = { waveform = "sine", amplitude_m = 0.01, frequency_hz = 2.0 }
        reference = { kind = "paper_case", case = 2 }
        """,
    )
    p = before_arming(step)
    assert p.low is not None and p.high < 0.05  # the reference damper's own force
    assert "paper_case on 10 mm 2 Hz sine stroke" in p.text()
