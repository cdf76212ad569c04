"""Displacement playback (issue 41, item 6; mrrig/hil/playback.py): a recorded stroke CSV read,
resampled to the loop's period and checked against the actuator's limits before arming (pure
numerics), the playback scenario it makes (a CSV or `kind = "playback"`), the daemon's refusal
at start, and the playback end to end: the real `Daemon` and firmware_sim's `Firmware` in
lockstep (tests/lockstep_rig.py), the stroke played through the simulated servo in STREAM and
judged with J1-J3 against the all-numerical reference. In-process; a few seconds."""

from __future__ import annotations

import numpy as np
import pytest

from mrrig.api import hil_tracking
from mrrig.api.hil import judge, playback_problem
from mrrig.config import load_config
from mrrig.hil.playback import (
    ActuatorLimits,
    StrokeFileError,
    infeasibility,
    parse_stroke_csv,
    read_stroke_csv,
    resample,
)
from mrrig.hil.reference import run_reference
from mrrig.hil.scenario import load_scenario
from mrrig.loop.hil_loop import build_scenario
from mrrig.plans.hil_step import step_scenario
from mrrig.plans.plan import PlanError, load_plan
from mrrig.typed_config import ConfigError
from tests.conftest import REPO, rig_config
from tests.lockstep_rig import lockstep_config, run_lockstep

DT = 0.002
LIMITS = ActuatorLimits(0.04, 1.0, 200.0)


def _csv(path, t, x, v=None, header="t_s,x_m"):
    cols = [t, x] if v is None else [t, x, v]
    if v is not None and header == "t_s,x_m":
        header = "t_s,x_m,v_m_s"
    rows = "\n".join(",".join(f"{c:.9g}" for c in row) for row in zip(*cols, strict=True))
    path.write_text((header + "\n" if header else "") + rows + "\n")
    return path


def _record(*cols):
    """A headless stroke CSV's record of these columns (t, x[, v])."""
    rows = zip(*(np.asarray(c, dtype=float).tolist() for c in cols), strict=True)
    return parse_stroke_csv("\n".join(",".join(repr(v) for v in row) for row in rows), "s")


def _sine(f_hz: float, amp_m: float, seconds: float, rate_hz: float, ramp_s: float = 0.25):
    """A sine with linear ramps in and out (it starts and ends at rest at stroke centre)."""
    t = np.arange(round(seconds * rate_hz) + 1) / rate_hz
    env = np.clip(np.minimum(t, seconds - t) / ramp_s, 0.0, 1.0)
    return t, amp_m * env * np.sin(2 * np.pi * f_hz * t)


# ---- the CSV ---------------------------------------------------------------------------


def test_columns_by_name_in_any_order_other_columns_ignored():
    text = "\ufeffnote,v_m_s,x_m,t_s\na,0.1,0.0,0.0\nb,0.1,0.001,0.01\n\nc,0.1,0.002,0.02\n"
    r = parse_stroke_csv(text.removeprefix("\ufeff"), "s.csv")
    np.testing.assert_array_equal(r.t_s, [0.0, 0.01, 0.02])
    np.testing.assert_array_equal(r.x_m, [0.0, 0.001, 0.002])
    np.testing.assert_array_equal(r.v_m_s, [0.1, 0.1, 0.1])
    headless = parse_stroke_csv("0,0\n0.5,0.001\n", "h.csv")
    assert headless.v_m_s is None and headless.duration_s == 0.5


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "s.csv: empty stroke file"),
        ("t_s,force_n\n0,1\n", "s.csv:1: header 't_s,force_n' has no column x_m"),
        ("t_s,x_m\n0,0\n0.1,abc\n", "s.csv:3: column 'x_m': 'abc' is not a number"),
        ("t_s,x_m\n0,0\n0.1,nan\n", "s.csv:3: column 'x_m': 'nan' is not finite"),
        ("t_s,x_m\n0,0\n0.1,0.001\n0.1,0.002\n", "s.csv:4: t_s must be strictly increasing"),
        ("t_s,x_m\n0,0\n0.1\n", "s.csv:3: column 'x_m': '' is not a number"),
        ("0,0,0,0\n", "s.csv:1: without a header 2 or 3 columns"),
        ("t_s,x_m\n0,0\n", "s.csv: 1 sample(s): a stroke needs at least 2"),
    ],
)
def test_a_bad_stroke_file_is_one_line_naming_file_line_and_column(text, expected):
    with pytest.raises(StrokeFileError) as err:
        parse_stroke_csv(text, "s.csv")
    assert str(err.value).startswith(expected) and "\n" not in str(err.value)


def test_an_unreadable_or_binary_stroke_file_is_one_line(tmp_path):
    with pytest.raises(StrokeFileError, match=r"missing.csv: cannot read the stroke file"):
        read_stroke_csv(tmp_path / "missing.csv")
    (tmp_path / "b.csv").write_bytes(b"t_s,x_m\n0,\xff\n")
    with pytest.raises(StrokeFileError, match=r"b.csv: not UTF-8 text: byte 0xff"):
        read_stroke_csv(tmp_path / "b.csv")


# ---- resampling ------------------------------------------------------------------------


def test_a_sine_recorded_at_1_khz_resampled_to_the_loop_keeps_stroke_velocity_acceleration():
    w = 2 * np.pi * 5.0
    t = np.arange(0, 2.0 + 1e-9, 0.001)
    r = resample(_record(t, 0.01 * np.sin(w * t)), DT)
    tk = np.arange(r.x_m.size) * DT
    assert r.x_m.size == 1001 and r.duration_s == pytest.approx(2.0)
    inner = slice(5, -5)  # the spline's end conditions aside
    np.testing.assert_allclose(r.x_m[inner], 0.01 * np.sin(w * tk[inner]), atol=1e-7)
    np.testing.assert_allclose(r.v_m_s[inner], 0.01 * w * np.cos(w * tk[inner]), atol=2e-4)
    np.testing.assert_allclose(r.a_m_s2[inner], -0.01 * w**2 * np.sin(w * tk[inner]), atol=0.05)


def test_a_coarse_record_with_velocities_is_the_hermite_cubic_between_them():
    """Recorded every 3 ms (not a multiple of the loop's 2 ms) with its velocity: a cubic
    polynomial comes back exactly, its stroke, velocity and acceleration."""
    t = np.arange(0, 0.3 + 1e-12, 0.003)
    x, v = 0.5 * t**3 - 0.2 * t**2, 1.5 * t**2 - 0.4 * t
    r = resample(_record(t, x, v), DT)
    tk = np.arange(r.x_m.size) * DT
    assert tk[-1] <= t[-1] + 1e-12 and r.x_m.size == 151
    np.testing.assert_allclose(r.x_m, 0.5 * tk**3 - 0.2 * tk**2, atol=1e-12)
    np.testing.assert_allclose(r.v_m_s, 1.5 * tk**2 - 0.4 * tk, atol=1e-10)
    np.testing.assert_allclose(r.a_m_s2, 3.0 * tk - 0.4, atol=1e-7)


# ---- the feasibility check -------------------------------------------------------------


def test_a_playable_stroke_passes_and_each_limit_names_its_first_frame():
    t, x = _sine(2.0, 0.01, 2.0, 1000.0)
    ok = resample(_record(t, x), DT)
    assert infeasibility(ok, LIMITS, "ok.csv") is None
    # |v| = 0.01 * 2 pi 2 = 0.126 m/s; |a| = 1.58 m/s^2: each limit just under its peak
    v_peak, a_peak = np.abs(ok.v_m_s).max(), np.abs(ok.a_m_s2).max()
    for limits, what, k in (
        (ActuatorLimits(0.009, 1.0, 200.0), "|x|", np.flatnonzero(np.abs(ok.x_m) > 0.009)[0]),
        (
            ActuatorLimits(0.04, 0.9 * v_peak, 200),
            "|v|",
            np.flatnonzero(np.abs(ok.v_m_s) > 0.9 * v_peak)[0],
        ),  # fmt: skip
        (
            ActuatorLimits(0.04, 1.0, 0.9 * a_peak),
            "|a|",
            np.flatnonzero(np.abs(ok.a_m_s2) > 0.9 * a_peak)[0],
        ),  # fmt: skip
    ):
        why = infeasibility(ok, limits, "ok.csv")
        assert why.startswith(f"ok.csv: not playable: frame {k} (t {k * DT:.4f} s): {what} ")
        assert "beyond the actuator's" in why and "\n" not in why


def test_the_first_infeasible_frame_is_named_whatever_limit_it_breaks():
    """A velocity excess at frame 40 before a stroke excess at frame 60: frame 40."""
    x = np.zeros(101)
    x[40:] = np.linspace(0.0, 0.05, 61)  # 0.05 m in 60 frames: 0.417 m/s; past 40 mm at 88
    x[60:] = 0.05
    r = resample(_record(np.arange(x.size) * DT, x), DT)
    why = infeasibility(r, ActuatorLimits(0.04, 0.3, 1e9), "r.csv")
    k = np.flatnonzero(np.abs(r.v_m_s) > 0.3)[0]
    assert 35 <= k <= 41 and why.startswith(f"r.csv: not playable: frame {k} ")
    assert "|v|" in why


def test_a_record_that_starts_off_centre_is_refused_as_a_step_from_rest():
    r = resample(parse_stroke_csv("0,0.005\n1,0.005\n", "s"), DT)
    why = infeasibility(r, LIMITS, "off.csv")
    assert why == (
        "off.csv: not playable: frame 0 (t 0.0000 s): the step from rest at 0 to x 5.000 mm "
        "in one frame is 2.5 m/s, beyond the actuator's 1 m/s (start the record at stroke centre)"
    )


# ---- the scenario, the daemon, the client ----------------------------------------------


def test_a_stroke_csv_is_a_playback_scenario_of_its_length(tmp_path):
    t, x = _sine(2.0, 0.01, 1.5, 1000.0)
    path = _csv(tmp_path / "sweep.csv", t, x)
    s = load_scenario(path)
    assert (s.kind, s.law, s.duration_s, s.steps) == ("playback", "passive-soft", 1.5, 750)
    assert load_scenario(path, law="passive-hard").law == "passive-hard"
    with pytest.raises(ConfigError, match=r"law: 'skyhook' needs a numerical model; a playback"):
        load_scenario(path, law="skyhook")
    toml = tmp_path / "p.toml"
    toml.write_text('kind = "playback"\nduration_s = 2.0\n[playback]\nfile = "sweep.csv"\n')
    with pytest.raises(ConfigError) as err:
        load_scenario(toml)
    assert str(err.value) == (
        f"{toml}: duration_s: 2 s is longer than the record (1.5 s of {tmp_path / 'sweep.csv'})"
    )
    toml.write_text('kind = "playback"\n[playback]\nfile = "sweep.csv"\n')  # beside the toml
    assert load_scenario(toml).steps == 750
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,x_m\n0,0\n0.1,abc\n")
    with pytest.raises(ConfigError) as err:  # a CSV given as the scenario: named once
        load_scenario(bad)
    assert str(err.value) == f"{bad}:3: column 'x_m': 'abc' is not a number"
    toml.write_text('kind = "playback"\n[playback]\nfile = "none.csv"\n')
    with pytest.raises(ConfigError, match=r"none.csv: cannot read the stroke file"):
        load_scenario(toml)


def test_the_daemon_refuses_at_start_a_playback_its_actuator_cannot_play(tmp_path):
    t, x = _sine(30.0, 0.01, 1.0, 2000.0)  # 1.88 m/s and 355 m/s^2 at 30 Hz
    path = _csv(tmp_path / "fast.csv", t, x)
    config = rig_config(tmp_path, "unused", None, hil={"scenario": str(path)})
    with pytest.raises(ConfigError) as err:
        build_scenario(load_config(config))
    why = str(err.value)
    assert f"hil.scenario: {path}: not playable: frame " in why and "\n" not in why
    assert "|a| " in why and "beyond the actuator's 200 m/s^2 ([hil] limits)" in why
    # the rig's [hil] limits are the check's: a 1 m/s valve refuses it by its velocity
    slow = rig_config(
        tmp_path,
        "unused",
        None,
        hil={
            "scenario": str(path),
            "max_setpoint_velocity_m_s": 1.0,
            "max_setpoint_acceleration_m_s2": 1000.0,
        },
    )
    with pytest.raises(ConfigError, match=r"\|v\| 1\.0\d* m/s beyond the actuator's 1 m/s"):
        build_scenario(load_config(slow))
    # a duration beyond the record (`mrrig run --hil-duration`, [hil] duration_s): one line
    longer = rig_config(tmp_path, "unused", None, hil={"scenario": str(path), "duration_s": 5.0})
    with pytest.raises(ConfigError) as err:
        build_scenario(load_config(longer))
    assert str(err.value) == (
        f"{longer}: hil.duration_s: {path}: duration_s: 5 s is longer than the record (1 s of "
        f"{path})"
    )
    # within them, it loads
    ok = rig_config(
        tmp_path,
        "unused",
        None,
        hil={"scenario": str(path), "max_setpoint_acceleration_m_s2": 400.0},
    )
    assert build_scenario(load_config(ok)).kind == "playback"


def test_the_client_checks_a_playback_against_the_rig_s_limits_before_arming(tmp_path):
    t, x = _sine(2.0, 0.02, 1.0, 1000.0)
    scenario = load_scenario(_csv(tmp_path / "s.csv", t, x))
    hil = {"envelope_m": 0.04, "max_setpoint_velocity_m_s": 3.0}
    hil["max_setpoint_acceleration_m_s2"] = 200.0
    assert playback_problem(scenario, hil) is None
    why = playback_problem(scenario, hil | {"envelope_m": 0.015})
    assert why.startswith(f"{tmp_path / 's.csv'}: not playable: frame ") and "|x| " in why


# ---- end to end: the daemon streams the record through firmware_sim's servo -----------


def test_a_playback_streams_through_the_simulated_servo_and_is_judged(tmp_path):
    """The daemon (passive-hard, 1 A) plays a 2 Hz, 10 mm stroke through firmware_sim's
    servo in STREAM (its seeded actuator: b1 427 1/s, b2 1.18e5 1/s^2, 1.72 ms transport), the
    model compensation leading by the known record: the run plays out without a fault, and
    J1-J3 and the damper force against the reference meet issue 41's bounds for a HIL run
    (measured: J1 0.12 ms, J2 0.34 %, J3 0.85 %, force RMS +0.01 %)."""
    t, x = _sine(2.0, 0.01, 3.0, 1000.0, ramp_s=0.5)
    scenario_file = tmp_path / "p.toml"
    _csv(tmp_path / "stroke.csv", t, x)
    scenario_file.write_text(
        'kind = "playback"\nlaw = "passive-hard"\n[playback]\nfile = "stroke.csv"\n'
        "[damper]\ni_max_a = 1.0\n"
    )
    config = lockstep_config(
        tmp_path,
        controller={"name": "constant", "current_a": 0.0},
        hil={"scenario": str(scenario_file)},
    )
    run = run_lockstep(
        config, ("STOP", 0.0, 0.0), seconds=3.6, preroll_s=0.2, arm=True, actuator_commands=True
    )
    s = run.samples
    assert not np.any(s["state"] == 2), "the run faulted"
    played = s[np.isfinite(s["hil_k"])]
    assert played.size == 1500 and np.all(played["i_cmd"][:-1] == 1.0)  # the last: SAFE
    reference = run_reference(load_scenario(scenario_file))
    frames, missing, tracking, errors, figures = judge(s, reference)
    assert (frames, missing) == (1500, 0)
    assert hil_tracking(s) == tracking  # mrrig.api's J1-J3 of a run's samples
    assert abs(tracking.j1_ms) <= 0.5 and tracking.j2_pct <= 2.0 and tracking.j3_pct <= 5.0
    assert set(errors) == {"force_n"} and abs(errors["force_n"].rms_of_rms_pct) <= 3.0
    assert figures["force_n"][1] == pytest.approx(424, rel=0.01)  # passive-hard at 1 A


def test_a_plan_plays_a_record_in_a_hil_step_and_refuses_one_longer_than_it(tmp_path):
    """The how-to's plan step (docs/howto/hil-playback.md) on the shipped playback scenario."""
    scenario_file = REPO / "configs/hil/playback-sweep.toml"
    step = (
        '[plan]\nname = "p"\n[[step]]\nname = "sweep at 1 A"\nduration_s = {d}\n'
        f'hil = {{ scenario = "{scenario_file}", law = "passive-hard" }}\n'
        "criteria = { j2_pct_max = 2.0, agreement_pct_max = 3.0 }\n"
    )
    path = tmp_path / "plan.toml"
    path.write_text(step.replace("{d}", "8.0"))
    plan = load_plan(path)
    scenario = step_scenario(plan.steps[0])
    assert (scenario.kind, scenario.law, scenario.steps) == ("playback", "passive-hard", 4000)
    path.write_text(step.replace("{d}", "9.0"))
    with pytest.raises(PlanError) as err:
        load_plan(path)
    assert str(err.value) == (
        f"{path}: step 1 (sweep at 1 A).duration_s: 9 s is longer than the record (8 s of "
        f"{REPO / 'configs/hil/strokes/sweep-0.5-5hz.csv'})"
    )
