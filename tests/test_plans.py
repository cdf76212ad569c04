"""Test plans (`mrrig test`, mrrig/plans): plan errors, criteria on synthetic telemetry, the
JUnit and HTML reports read back, and plans run against firmware_sim and a daemon."""

from __future__ import annotations

import dataclasses
import html
import math
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from junitparser import Error, Failure, JUnitXml, Properties, Property

from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.offline.metrics import error_norm
from mrrig.plans.criteria import Criteria, failures, measure
from mrrig.plans.plan import MAX_PLAN_BYTES, MAX_STEPS, PlanError, load_plan
from mrrig.plans.report import Identity, write_html, write_junit
from mrrig.plans.runner import StepResult, floor_ratio, table
from mrrig.rigio.run_identity import file_sha256
from tests.conftest import REPO, OutputWatch, rig_config, start, stop, zenoh_configs
from tests.live_rig import live_rig
from tests.test_lifecycle_errors import NO_MODEL

RIG = "plans"

PLAN = """
[plan]
name = "two steps"

[[step]]
name = "constant current"
duration_s = {d1}
settle_s = 0.5
actuator = {{ waveform = "sine", amplitude_m = 0.005, frequency_hz = 1.0 }}
controller = {{ name = "constant", current_a = 0.5 }}
reference = {{ kind = "constant" }}
criteria = {{ faults = "transport", peak_current_a_max = 0.6 }}

[[step]]
name = "impossible Et"
duration_s = 2
settle_s = 0.5
controller = {{ name = "constant", current_a = 0.3 }}
reference = {{ kind = "sine", amplitude_n = 300.0, freq_hz = 1.0 }}
criteria = {{ et_max = 0.0001, faults = "transport" }}
"""


CRITERIA = 'et_max = 0.0001, faults = "transport"'


def write(tmp_path, text: str, name: str = "plan.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def mrrig(*args: str, timeout_s: float = 120.0, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mrrig", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout_s,
        **kw,
    )


# --- plan errors ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "where"),
    [
        (CRITERIA, "step 2 (impossible Et).criteria.et_max"),  # as it is: no error
        ('et_max = "small"', "step 2 (impossible Et).criteria.et_max: expected a number"),
        ('faults = "all"', "step 2 (impossible Et).criteria.faults: expected one of"),
        ("et_max = -1.0", "step 2 (impossible Et).criteria.et_max: must be > 0"),
        ("etmax = 0.1", "step 2 (impossible Et).criteria.etmax: unknown field"),
        # issue 40, finding 15: finite and in a physical range
        (
            "temperature_max_degc = -1e300",
            "step 2 (impossible Et).criteria.temperature_max_degc: -1e+300 is outside"
            " [-40, 250] degC",
        ),
        ("peak_current_a_max = 1e300", "criteria.peak_current_a_max: 1e+300 is outside [0, 5] A"),
    ],
)
def test_a_plan_error_names_the_step_and_the_field(tmp_path, change, where):
    path = write(tmp_path, PLAN.format(d1=1).replace(CRITERIA, change))
    if change == CRITERIA:
        assert load_plan(path).steps[1].criteria.et_max == 0.0001
        return
    with pytest.raises(PlanError) as err:
        load_plan(path)
    assert where in str(err.value) and str(path) in str(err.value)
    assert "\n" not in str(err.value)


def test_step_sections_are_checked_as_the_daemon_checks_them(tmp_path):
    bad = PLAN.format(d1=1).replace("amplitude_m = 0.005", "amplitude_m = 0.5")
    with pytest.raises(PlanError, match=r"step 1 \(constant current\)\.actuator\.amplitude_m"):
        load_plan(write(tmp_path, bad))
    bad = PLAN.format(d1=1).replace('name = "constant", current_a = 0.3', 'name = "pid"')
    with pytest.raises(PlanError, match=r"step 2 \(impossible Et\)\.controller\.name: unknown"):
        load_plan(write(tmp_path, bad))
    bad = PLAN.format(d1="-1")
    with pytest.raises(PlanError, match=r"step 1 \(constant current\)\.duration_s"):
        load_plan(write(tmp_path, bad))


def test_only_the_given_fields_are_sent_and_a_model_is_kept(tmp_path):
    plan = load_plan(
        write(
            tmp_path,
            """
            [plan]
            name = "p"
            [[step]]
            name = "ni"
            duration_s = 1
            controller = { name = "network_inversion", continuity = 0.03 }
            reference = { kind = "sine", amplitude_n = 100.0 }
            """,
        )
    )
    assert plan.steps[0].requests() == [
        {"cmd": "set_controller", "name": "network_inversion", "continuity": 0.03},
        {"cmd": "set_profile", "kind": "sine", "amplitude_n": 100.0},
    ]


def test_every_shipped_plan_parses():
    plans = sorted((REPO / "configs/plans").glob("*.toml"))
    names = {load_plan(p).name for p in plans}  # a PlanError names the file, step and field
    assert {"smoke", "heating"} <= names


def test_a_steps_adaptation_resets_it_then_frees_or_freezes_it(tmp_path):
    step = """
        [[step]]
        name = "{name}"
        duration_s = 1
        controller = {{ name = "network_inversion" }}
        adaptation = {value}
        """
    text = "[plan]\nname = 'p'\n" + "".join(
        textwrap.dedent(step.format(name=n, value=v)) for n, v in (("on", '"on"'), ("off", '"off"'))
    )
    on, off = load_plan(write(tmp_path, text)).steps
    ni = {"cmd": "set_controller", "name": "network_inversion"}
    assert on.requests() == [
        ni,
        {"cmd": "reset_adaptation"},
        {"cmd": "freeze_adaptation", "frozen": False},
    ]
    assert off.requests()[1:] == [
        {"cmd": "reset_adaptation"},
        {"cmd": "freeze_adaptation", "frozen": True},
    ]
    with pytest.raises(PlanError, match=r"step 2 \(off\)\.adaptation: expected one of 'on', 'off'"):
        load_plan(write(tmp_path, text.replace('adaptation = "off"', "adaptation = true")))


def test_adaptation_is_an_option_of_the_simulated_rig_only(tmp_path):
    out = mrrig("test", "configs/plans/smoke.toml", "--rig", "nobody", "--adaptation", "on")
    assert out.returncode == 2
    assert "--adaptation: only with --sim" in out.stderr


def test_a_plan_error_exits_2_with_one_line(tmp_path):
    path = write(tmp_path, PLAN.format(d1=1).replace("settle_s = 0.5", "settle_s = true", 1))
    out = mrrig("test", str(path), "--rig", "nobody")
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        f"error: {path}: step 1 (constant current).settle_s: expected a number, got True"
    ]


def test_a_compare_et_that_is_not_an_et_is_a_plan_error(tmp_path):
    """Issue 40, finding 15: `compare_et = nan` was accepted."""
    for value, shown in (("nan", "nan"), ("-1e300", "-1e+300"), ("inf", "inf")):
        text = PLAN.format(d1=1).replace(
            CRITERIA, CRITERIA + f" }}\ncompare_et = {{ paper = {value}"
        )
        path = write(tmp_path, text)
        with pytest.raises(PlanError) as err:
            load_plan(path)
        assert f"step 2 (impossible Et).compare_et.paper: {shown} is not an Et" in str(err.value)


FLOOR = '\nfloor_of = "constant current"'


@pytest.mark.parametrize(
    ("floor_of", "error"),
    [
        ("no such step", "no other step of the plan has this name"),
        ("impossible Et", "no other step of the plan has this name"),  # itself
    ],
)
def test_a_floor_names_another_step_of_the_plan(tmp_path, floor_of, error):
    path = write(tmp_path, PLAN.format(d1=1) + f'floor_of = "{floor_of}"\n')
    with pytest.raises(PlanError) as err:
        load_plan(path)
    assert str(err.value) == f"{path}: step 2 (impossible Et).floor_of: {floor_of!r}: {error}"


def test_a_floor_of_a_floor_is_a_plan_error(tmp_path):
    text = (
        PLAN.format(d1=1).replace(
            "peak_current_a_max = 0.6 }", 'peak_current_a_max = 0.6 }\nfloor_of = "impossible Et"'
        )
        + FLOOR
    )
    path = write(tmp_path, text)
    with pytest.raises(PlanError) as err:
        load_plan(path)
    assert str(err.value) == (
        f"{path}: step 1 (constant current).floor_of: 'impossible Et': that step is itself a"
        " floor (of 'constant current')"
    )


def test_the_table_prints_each_steps_floor_and_their_ratio(tmp_path):
    """Issue 43, item 4: the paper's cases, each beside its ideal controller's Et (a step
    whose `floor_of` names it), and their ratio."""
    plan = load_plan(write(tmp_path, PLAN.format(d1=1) + FLOOR))
    assert plan.steps[1].floor_of == "constant current"
    s = synthetic()
    n = measure(s, 0.2)
    results = [
        StepResult(plan.steps[0], "passed", numbers=dataclasses.replace(n, et=0.0130)),
        StepResult(plan.steps[1], "failed", numbers=dataclasses.replace(n, et=0.0100)),
    ]
    first, second = table(results).splitlines()[2:]
    assert first.endswith("-  floor 0.0100 (step 2), Et/floor 1.30"), first
    assert "floor" not in second
    aborted = [results[0], StepResult(plan.steps[1], "aborted", ["a fault"])]
    assert table(aborted).splitlines()[2].endswith("floor nan (step 2), Et/floor nan")
    assert math.isnan(floor_ratio(results[0], aborted[1]))


def _many_steps(tmp_path, n: int, padding: int = 0):
    step = '[[step]]\nname = "s{k}"\nduration_s = 1\nreference = {{ kind = "constant" }}\n'
    text = (
        '[plan]\nname = "big"\n'
        + "#" * padding
        + "\n"
        + "".join(step.format(k=k) for k in range(n))
    )
    return write(tmp_path, text, f"big{n}.toml")


def test_a_plan_is_bounded_in_steps_and_bytes_with_one_line(tmp_path):
    """Issue 40, finding 15: a 1,000,000-step plan took 2 min and 916 MB before it found that
    no daemon answered: the plan's size is bounded before anything else."""
    assert len(load_plan(_many_steps(tmp_path, MAX_STEPS)).steps) == MAX_STEPS
    with pytest.raises(PlanError, match=f"step: {MAX_STEPS + 1} steps, over the limit of"):
        load_plan(_many_steps(tmp_path, MAX_STEPS + 1))
    huge = _many_steps(tmp_path, 1, padding=MAX_PLAN_BYTES)
    with pytest.raises(PlanError, match=f"bytes, over the limit of {MAX_PLAN_BYTES}"):
        load_plan(huge)
    out = mrrig("test", str(_many_steps(tmp_path, MAX_STEPS + 1)), "--rig", "nobody")
    assert out.returncode == 2
    (line,) = out.stderr.strip().splitlines()
    assert f"{MAX_STEPS + 1} steps, over the limit of {MAX_STEPS}" in line


def test_a_name_that_is_not_one_printable_line_is_a_plan_error(tmp_path):
    """Issue 40, finding 14: a step's name goes to the terminal, the JUnit and the catalog."""
    for bad in ("two\\nlines", "red\\u001b[31m"):
        path = write(tmp_path, PLAN.format(d1=1).replace('"impossible Et"', f'"{bad}"'))
        with pytest.raises(PlanError, match=r"step 2 \(.*\)\.name: .*one printable line"):
            load_plan(path)
    path = write(tmp_path, PLAN.format(d1=1).replace('"impossible Et"', '"$x$ and a$b"'))
    assert load_plan(path).steps[1].name == "$x$ and a$b"


# --- criteria on synthetic telemetry -------------------------------------------------------


def synthetic(n: int = 1000, idle: int = 200, error: float = 0.02) -> np.ndarray:
    """`idle` IDLE samples (a huge error that must not count), then armed ones at 500 Hz."""
    s = np.zeros(n, SAMPLE_DTYPE)
    s["t"] = np.arange(n) * 0.002
    s["f_des"] = 500.0 * np.sin(2 * np.pi * s["t"])
    s["f_meas"] = s["f_des"] * (1 + error)
    s["f_meas"][:idle] = 0.0
    s["state"] = RigState.ARMED
    s["state"][:idle] = RigState.IDLE
    s["i_cmd"] = 0.4
    if idle + 10 < n:
        s["i_cmd"][idle + 10] = 1.7  # within the settling time: not counted
    s["i_cmd"][-1] = 1.2
    s["latency_us"] = np.linspace(100.0, 1100.0, n)
    s["temp_degc"] = 30.0
    return s


def test_measure_counts_armed_samples_after_settling_only():
    s = synthetic()
    numbers = measure(s, settle_s=0.199)
    judged = s[300:]  # 200 idle, then 100 samples (0.2 s) of settling
    assert numbers.samples == 700
    assert numbers.et == pytest.approx(error_norm(judged["f_des"], judged["f_meas"]))
    assert numbers.et == pytest.approx(0.02, rel=0.05)  # a 2 % gain error
    assert numbers.peak_current_a == 1.2
    assert numbers.latency_p99_us == pytest.approx(np.percentile(judged["latency_us"], 99))
    assert numbers.temperature_max_degc == 30.0


def test_failures_name_each_criterion_not_met():
    numbers = measure(synthetic(), settle_s=0.2)
    assert failures(Criteria(et_max=0.05, peak_current_a_max=1.5), numbers, []) == []
    reasons = failures(
        Criteria(et_max=0.01, peak_current_a_max=1.0, latency_p99_us_max=500.0), numbers, []
    )
    assert [r.split(":")[0] for r in reasons] == [
        "et_max",
        "peak_current_a_max",
        "latency_p99_us_max",
    ]
    assert re.fullmatch(r"et_max: Et 0\.02\d* > 0\.01", reasons[0])
    # a transport fault is allowed only with faults = "transport"; another fault never
    assert failures(Criteria(faults="transport"), numbers, ["sensor_timeout"]) == []
    assert failures(Criteria(), numbers, ["sensor_timeout"]) == [
        "faults: sensor_timeout (allowed: none)"
    ]
    assert failures(Criteria(faults="transport"), numbers, ["overcurrent"])[0].startswith(
        "faults: overcurrent"
    )


def test_a_constant_force_has_no_et_and_an_et_criterion_on_it_fails():
    s = synthetic()
    s["f_des"] = 200.0
    numbers = measure(s, settle_s=0.2)
    assert math.isnan(numbers.et)
    assert failures(Criteria(), numbers, []) == []
    assert "undefined" in failures(Criteria(et_max=0.1), numbers, [])[0]
    never_armed = measure(synthetic(idle=1000), settle_s=0.0)
    assert never_armed.samples == 0 and failures(Criteria(), never_armed, [])


def test_a_temperature_criterion_on_a_rig_without_a_temperature_says_so():
    """The tutorial's walk (a lab profile without damper_temperature, the first-day plan with a
    temperature limit): every step failed with 'temperature max is undefined (a desired force
    without spread?)' and numpy's All-NaN warning on the console."""
    s = synthetic()
    s["temp_degc"] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        numbers = measure(s, settle_s=0.2)
    assert math.isnan(numbers.temperature_max_degc) and numbers.et == pytest.approx(0.02, rel=0.05)
    (reason,) = failures(Criteria(temperature_max_degc=80.0), numbers, [])
    assert reason.startswith("temperature_max_degc: temperature max is undefined (the rig")
    assert "maps no damper_temperature" in reason and "spread" not in reason


# --- reports -------------------------------------------------------------------------------


def junit_cases(path) -> dict:
    (suite,) = JUnitXml.fromfile(str(path))
    return {case.name: case for case in suite}


def case_properties(case) -> dict[str, str]:
    """A testcase's <properties> (junitparser reads a testsuite's, not a testcase's)."""
    (props,) = case.iterchildren(Properties)
    return {p.name: p.value for p in props.iterchildren(Property)}


def results_of(tmp_path) -> tuple[object, list[StepResult]]:
    plan = load_plan(write(tmp_path, PLAN.format(d1=1)))
    s = synthetic()
    ok = StepResult(plan.steps[0], "passed", numbers=measure(s, 0.2), samples=s, wall_s=1.5)
    bad_numbers = measure(s, 0.2)
    reasons = failures(plan.steps[1].criteria, bad_numbers, [])
    bad = StepResult(plan.steps[1], "failed", reasons, bad_numbers, samples=s, wall_s=2.5)
    return plan, [ok, bad]


def test_junit_is_read_back_with_the_failed_step_and_its_numbers(tmp_path):
    plan, results = results_of(tmp_path)
    ident = Identity.of(plan.path, "rig1", "1.2.3", "2026-12-04T20:00:00+00:00")
    path = tmp_path / "report.xml"
    write_junit(path, plan.name, ident, results)
    (suite,) = JUnitXml.fromfile(str(path))
    cases = {c.name: c for c in suite}
    assert list(cases) == ["constant current", "impossible Et"]
    assert cases["constant current"].is_passed
    failed = cases["impossible Et"]
    assert not failed.is_passed
    (failure,) = failed.result
    assert isinstance(failure, Failure) and re.fullmatch(
        r"et_max: Et 0\.02\d* > 0\.0001", failure.message
    )
    props = case_properties(failed)
    assert float(props["et"]) == pytest.approx(results[1].numbers.et, rel=1e-5)
    assert float(props["peak_current_a"]) == 1.2
    assert props["verdict"] == "failed"
    suite_props = {p.name: p.value for p in suite.properties()}
    assert suite_props["rig"] == "rig1" and len(suite_props["plan_sha256"]) == 64


def test_junit_marks_an_aborted_step_as_an_error(tmp_path):
    plan, results = results_of(tmp_path)
    results[1] = StepResult(plan.steps[1], "aborted", ["fault overcurrent: 2.3 A"])
    path = tmp_path / "report.xml"
    write_junit(path, plan.name, Identity.of(plan.path, "r", "v", "t"), results)
    (error,) = junit_cases(path)["impossible Et"].result
    assert isinstance(error, Error) and error.message == "fault overcurrent: 2.3 A"


def test_html_holds_the_identity_the_table_and_one_plot_per_step(tmp_path):
    plan, results = results_of(tmp_path)
    ident = Identity.of(plan.path, "rig1", "1.2.3", "2026-12-04T20:00:00+00:00")
    path = tmp_path / "report.html"
    write_html(path, plan.name, ident, results)
    text = path.read_text()
    assert text.count("src='data:image/png;base64,") == 2
    assert ident.plan_sha256 in text and "rig1" in text and ident.operator in text
    assert "<h1>mrrig test: two steps: failed</h1>" in text


def test_html_is_a_test_record_criteria_limits_values_rig_operator_and_model(tmp_path):
    """Issue 42: the plan's HTML named the operator `root` where the daemon ran with
    `--operator walk`, printed Et as `nan` or `0.0116904`, and showed no criterion."""
    plan, results = results_of(tmp_path)
    for r in results:
        r.identity = {"operator": "walk", "specimen": "SN-MR-042", "run_id": "r-1",
                      "model_path": "models/m.json", "model_sha256": "cd" * 32}  # fmt: skip
    results[0].numbers = dataclasses.replace(results[0].numbers, et=math.nan)
    path = tmp_path / "report.html"
    ident = Identity.of(plan.path, "rig1", "1.2.3", "2026-12-04T20:00:00+00:00")
    write_html(path, plan.name, ident, results)
    text = path.read_text()
    operator = html.escape(f"walk (the rig's run; the plan run by {ident.operator})")
    assert f"<td>{operator}</td>" in text
    assert "<td>SN-MR-042</td>" in text and f"models/m.json ({'cd' * 6})" in text
    assert ">nan<" not in text and "<td>n/a</td>" in text
    et = results[1].numbers.et
    assert f"<td>{et:.4f}</td>" in text and f"{et:.6g}" not in text
    # the failed step's criteria: Et against its limit, not met; faults met
    assert (
        f"<tr class='failed'><td>Et</td><td>&lt;= 0.0001</td><td>{et:.4f}</td>"
        "<td>not met</td></tr>" in text
    )
    assert text.count("<td>faults</td>") == 2 and "<th>criterion</th>" in text


def _renamed(results: list[StepResult], names: list[str]) -> list[StepResult]:
    return [
        dataclasses.replace(r, step=dataclasses.replace(r.step, name=n))
        for r, n in zip(results, names, strict=True)
    ]


def test_junit_with_control_characters_in_names_and_messages_is_well_formed(tmp_path):
    """Issue 40, finding 14: control characters in a step's name or a reason made the JUnit
    file ill-formed XML; each is escaped as visible text, the file parses."""
    plan, results = results_of(tmp_path)
    results = _renamed(results, ["bell\x07 step\nsecond line", "esc\x1b[31m\x00nul"])
    results[1].reasons = ["fault \x0c form feed", "claimed host pc\x01"]
    path = tmp_path / "report.xml"
    write_junit(path, "plan\x02", Identity.of(plan.path, "r\x03", "v", "t"), results)
    ET.parse(path)  # well-formed
    cases = junit_cases(path)
    assert list(cases) == ["bell\\x07 step\\x0asecond line", "esc\\x1b[31m\\x00nul"]
    (failure,) = cases["esc\\x1b[31m\\x00nul"].result
    assert failure.message == "fault \\x0c form feed; claimed host pc\\x01"


def test_a_dollar_in_a_step_name_is_text_in_the_html_report(tmp_path):
    """Issue 40, finding 12: matplotlib read a `$` in a step's name as mathtext: `$x^$` broke
    the report, `$x$` was typeset. The names are in the report and its figures as written."""
    import matplotlib.cbook

    from mrrig.safe_text import plot_literal

    plan, results = results_of(tmp_path)
    names = ["$x$ and a$b", "$x^$ $\\frac$"]
    results = _renamed(results, names)
    path = tmp_path / "report.html"
    write_html(path, plan.name, Identity.of(plan.path, "rig1", "v", "t"), results)
    text = path.read_text()
    assert text.count("src='data:image/png;base64,") == 2
    assert all(f"<td>{html.escape(n)}</td>" in text for n in names)
    assert not any(matplotlib.cbook.is_math_text(plot_literal(n)) for n in names)


# --- against the simulated rig -------------------------------------------------------------


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """firmware_sim and a daemon (constant controller, telemetry); yields the client's Zenoh
    config."""
    tmp = tmp_path_factory.mktemp("plans")
    with live_rig(tmp, RIG, rate_hz=50.0, daemon_args=("--no-record",)) as live:
        yield live.client_z


@pytest.mark.process
def test_a_failing_criterion_exits_1_and_its_step_fails_in_the_reports(rig, tmp_path):
    plan = write(tmp_path, PLAN.format(d1=2))
    junit, html = tmp_path / "r.xml", tmp_path / "r.html"
    args = ["--rig", RIG, "--zenoh-config", str(rig), "--junit", str(junit), "--html", str(html)]
    out = mrrig("test", str(plan), *args)
    assert out.returncode == 1, out.stdout + out.stderr
    cases = junit_cases(junit)
    props = {n: case_properties(c) for n, c in cases.items()}
    if any(p["faults"] for p in props.values()):
        print(f"transport faults during the plan (re-armed): {props}")
    assert props["constant current"]["verdict"] == "passed", out.stdout
    assert float(props["constant current"]["peak_current_a"]) == pytest.approx(0.5)
    failed = cases["impossible Et"]
    (failure,) = failed.result
    assert isinstance(failure, Failure) and failure.message.startswith("et_max: Et ")
    assert float(props["impossible Et"]["et"]) > 0.0001
    assert int(props["impossible Et"]["samples"]) > 500  # about 1.5 s at 500 Hz
    assert "step 2/2 impossible Et: FAILED: et_max" in out.stdout
    assert html.read_text().count("src='data:image/png;base64,") == 2


@pytest.mark.process
def test_a_fault_aborts_its_step_and_the_next_step_resets_it_first(rig, tmp_path):
    plan = write(
        tmp_path,
        """
        [plan]
        name = "a fault"
        [[step]]
        name = "no force stream"
        duration_s = 3
        settle_s = 0.5
        controller = { name = "constant", current_a = 0.3 }
        reference = { kind = "zenoh", timeout_s = 0.1 }
        criteria = { faults = "transport" }
        [[step]]
        name = "after the reset"
        duration_s = 1.5
        settle_s = 0.5
        reference = { kind = "constant" }
        criteria = { faults = "transport", peak_current_a_max = 0.4 }
        """,
    )
    junit = tmp_path / "r.xml"
    out = mrrig("test", str(plan), "--rig", RIG, "--zenoh-config", str(rig), "--junit", str(junit))
    assert out.returncode == 1, out.stdout + out.stderr
    cases = junit_cases(junit)
    (error,) = cases["no force stream"].result
    # armed with no force streamed: the daemon's stale-reference FAULT, which no stall explains
    assert isinstance(error, Error) and error.message.startswith("fault stale_reference"), (
        out.stdout
    )
    assert cases["after the reset"].is_passed, out.stdout
    assert float(case_properties(cases["after the reset"])["peak_current_a"]) == pytest.approx(0.3)


@pytest.mark.process
def test_sim_starts_the_rig_and_a_failed_step_exits_1(tmp_path):
    """`mrrig test --sim` (as .ci/run runs the smoke plan): bridge, firmware_sim and a daemon
    started and stopped by the command; a failed step is exit 1, so CI fails."""
    daemon_z, client_z, _ = zenoh_configs(tmp_path)
    cfg = rig_config(
        tmp_path,
        "ws://127.0.0.1:1/",  # --sim gives the daemon its bridge's channel
        None,
        rig={"name": "plans-sim"},
        telemetry={"enabled": True, "zenoh_config": str(daemon_z)},
        **NO_MODEL,
    )
    plan = write(tmp_path, PLAN.format(d1=1))
    args = ["--sim", "--config", str(cfg), "--zenoh-config", str(client_z)]
    out = mrrig("test", str(plan), *args, "--junit", str(tmp_path / "r.xml"))
    assert out.returncode == 1, out.stdout + out.stderr
    assert "step 2/2 impossible Et: FAILED: et_max" in out.stdout
    cases = junit_cases(tmp_path / "r.xml")
    assert cases["constant current"].is_passed and cases["impossible Et"].is_failure


@pytest.mark.process
def test_ctrl_c_in_a_step_leaves_the_rig_safe_and_the_step_aborted(rig, tmp_path):
    from mrrig.api import Rig

    plan = write(tmp_path, PLAN.format(d1=30))
    junit = tmp_path / "r.xml"
    args = ["--rig", RIG, "--zenoh-config", str(rig), "--junit", str(junit)]
    proc = start(["-m", "mrrig", "test", str(plan), *args], stdout=subprocess.PIPE, text=True)
    try:
        with Rig(RIG, zenoh_config=rig) as r:
            deadline = time.monotonic() + 20
            while r.status()["state"] != "ARMED":
                assert time.monotonic() < deadline, "the plan never armed the rig"
                time.sleep(0.05)
            time.sleep(1.0)
            proc.send_signal(signal.SIGINT)
            t0 = time.monotonic()
            stdout, _ = proc.communicate(timeout=30)
            # the plan's tool disarmed the rig before it exited: a constant-current step on a
            # constant reference stays ARMED for ever otherwise (no fault of its own ends it);
            # the status is the loop's latest, sent every 0.1 s
            while (state := r.status()["state"]) == "ARMED" and time.monotonic() - t0 < 5.0:
                time.sleep(0.01)
            print(f"the rig left ARMED {time.monotonic() - t0:.3f} s after Ctrl-C (seen)")
            assert state == "IDLE", state
    finally:
        stop(proc)
    assert proc.returncode == 1, stdout
    cases = junit_cases(junit)
    (error,) = cases["constant current"].result
    assert isinstance(error, Error) and "interrupted" in error.message
    assert cases["impossible Et"].result[0].message.startswith("not run")


@pytest.mark.process
def test_a_double_ctrl_c_still_writes_the_reports_and_the_catalog_rows(tmp_path):
    """Issue 40, finding 8: two SIGINTs 50 ms apart in a step of `mrrig test --sim` left no
    JUnit, HTML or catalog row (the second one cut the step's ending and the reports)."""
    from mrrig.catalog import find_runs

    daemon_z, client_z, _ = zenoh_configs(tmp_path)
    cfg = rig_config(
        tmp_path,
        "ws://127.0.0.1:1/",  # --sim gives the daemon its bridge's channel
        None,
        rig={"name": "plans-ctrl-c", "specimen": "SN-MR-042"},
        telemetry={"enabled": True, "zenoh_config": str(daemon_z)},
        **NO_MODEL,
    )
    plan = write(tmp_path, PLAN.format(d1=30))
    junit, html, catalog = tmp_path / "r.xml", tmp_path / "r.html", tmp_path / "c.sqlite"
    args = ["--sim", "--config", str(cfg), "--zenoh-config", str(client_z), "--junit",
            str(junit), "--html", str(html), "--catalog", str(catalog)]  # fmt: skip
    proc = start(
        ["-m", "mrrig", "test", str(plan), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    out = OutputWatch(proc, "/30.5 s ")  # the step's progress: it is running
    try:
        assert out.seen.wait(120), out.text()
        proc.send_signal(signal.SIGINT)
        time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=60)
    finally:
        stop(proc)
    out.join()
    text = out.text()
    assert proc.returncode == 1, text
    assert "plan two steps: FAILED (interrupted)" in text and "Traceback" not in text, text
    cases = junit_cases(junit)
    (error,) = cases["constant current"].result
    assert isinstance(error, Error) and "interrupted" in error.message
    assert cases["impossible Et"].result[0].message.startswith("not run")
    assert "constant current" in html.read_text()
    (row,) = find_runs(catalog)
    assert (row.plan, row.step, row.verdict) == ("two steps", "constant current", "aborted")
    # issue 42: traceable to the specimen, the settings and the files in force at its start
    assert (row.specimen, row.config_sha256) == ("SN-MR-042", file_sha256(cfg))
    assert row.dbc_sha256 == file_sha256(REPO / "configs" / "mrrig.dbc")
    assert row.controller_params["current_a"] == 0.5, row.controller_params
    assert row.campaign is not None and row.campaign.startswith("two steps 20")  # its UTC start


@pytest.mark.process
def test_sigterm_in_a_step_is_named_as_sigterm(rig, tmp_path):
    """Issue 40, finding 15: a SIGTERM was reported as "interrupted (Ctrl-C)"."""
    from mrrig.api import Rig

    plan = write(tmp_path, PLAN.format(d1=30))
    junit = tmp_path / "r.xml"
    args = ["--rig", RIG, "--zenoh-config", str(rig), "--junit", str(junit)]
    proc = start(
        ["-m", "mrrig", "test", str(plan), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        with Rig(RIG, zenoh_config=rig) as r:
            deadline = time.monotonic() + 20
            while r.status()["state"] != "ARMED":
                assert time.monotonic() < deadline, "the plan never armed the rig"
                time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        stdout, _ = proc.communicate(timeout=30)
    finally:
        stop(proc)
    assert proc.returncode == 1, stdout
    (error,) = junit_cases(junit)["constant current"].result
    assert error.message == "interrupted (SIGTERM): the rig disarmed", stdout
    assert "Ctrl-C" not in stdout


@pytest.mark.process
def test_force_against_the_motion_is_judged_before_arming_and_measured(rig, tmp_path):
    """A force that stays in tension on a sine stroke asks the damper to push back on every
    return (about 45 % of the samples): said before arming, measured from the frames, and
    given as the reason of the Et it cannot reach."""
    plan = write(
        tmp_path,
        """
        [plan]
        name = "against the motion"
        [[step]]
        name = "tension only"
        duration_s = 3
        settle_s = 1
        actuator = { waveform = "sine", amplitude_m = 0.005, frequency_hz = 1.0 }
        controller = { name = "constant", current_a = 0.5 }
        reference = { kind = "sine", offset_n = 300.0, amplitude_n = 100.0, freq_hz = 0.5 }
        criteria = { et_max = 0.5, faults = "transport" }
        """,
    )
    junit = tmp_path / "r.xml"
    out = mrrig("test", str(plan), "--rig", RIG, "--zenoh-config", str(rig), "--junit", str(junit))
    assert out.returncode == 1, out.stdout + out.stderr
    before = re.search(r"force against the motion: ([\d.]+)% of the samples", out.stdout)
    assert before, out.stdout
    case = junit_cases(junit)["tension only"]
    props = case_properties(case)
    measured = float(props["against_motion_share"])
    print(f"force against the motion: {before.group(1)} % before arming, {measured:.1%} measured")
    assert 0.4 < float(before.group(1)) / 100 < 0.5
    assert measured == pytest.approx(float(before.group(1)) / 100, abs=0.05)
    (failure,) = case.result
    assert failure.message.startswith("et_max: Et ") and "oppose the motion" in failure.message


# --- markers in the recording, and review's budget verdict on it ----------------------------


@pytest.mark.parametrize(
    ("req", "error"),
    [
        ({"text": "step 1: start", "data": {"step": 1}}, None),
        ({"data": {}}, "text: a mark needs a text"),
        ({"text": "  "}, "text: a mark needs a text"),
        ({"text": "x" * 201}, "text: 201 characters, over the limit of 200"),
        ({"text": "two\nlines"}, "text: a control character"),
        ({"text": "t", "data": [1, 2]}, "data: expected a JSON object, got list"),
        ({"text": "t", "data": {"s": "x" * 1300}}, "data: 1309 characters of JSON, over the limit"),
        ({"text": "t", "level": "error"}, "level: unknown field of mark (known: text, data)"),
    ],
)
def test_a_mark_is_one_bounded_line_with_a_json_object(req, error):
    from mrrig.rigio.control import RequestError, check_mark, check_request

    req = check_request({"cmd": "mark", **req})  # a known command of the control plane
    if error is None:
        assert check_mark(req) == ("step 1: start", {"step": 1})
        return
    with pytest.raises(RequestError) as err:
        check_mark(req)
    assert str(err.value).startswith(error)


def test_the_budget_verdict_without_the_work_is_never_over_on_the_latency_alone():
    """The latency from the bus's receive holds the wait before the loop's read: over the
    budget it proves nothing about the work (the daemon's measure), within it it bounds it."""
    from mrrig.loop.summary import format_summary, summarize

    s = synthetic()
    d = summarize(s, [])  # latency 100 to 1100 us: p99 over 300 us
    assert "budget of the work per frame p99 <= 300 us, p99.9 <= 1000 us: not judged" in (
        format_summary(d)
    )
    s["latency_us"] = 120.0
    assert "within it (the latency, which holds the work)" in format_summary(summarize(s, []))
    work = {"work": {"p50": 80.0, "p99": 350.0, "p99.9": 400.0, "max": 500.0}}
    d = summarize(s, [], {"latency_split_us": work})
    assert "OVER it at p99 (its work)" in format_summary(d)


RECORDED = "plans-rec"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """The two-step plan run by `mrrig test` on a daemon that records, then stopped: (the
    recording, what the daemon printed, what `mrrig test` printed)."""
    tmp = tmp_path_factory.mktemp("recorded")
    rrd, printed = tmp / "run.rrd", tmp / "daemon.txt"
    record = ("--record", str(rrd))
    with (
        printed.open("w") as out,
        live_rig(tmp, RECORDED, rate_hz=50.0, daemon_args=record, daemon_stdout=out) as live,
    ):
        plan = write(tmp, PLAN.format(d1=1))
        ran = mrrig("test", str(plan), "--rig", RECORDED, "--zenoh-config", str(live.client_z))
    assert ran.returncode == 1, ran.stdout + ran.stderr  # step 2's Et criterion
    return rrd, printed.read_text(), ran.stdout


@pytest.mark.process
def test_each_step_leaves_its_start_and_end_marks_with_its_settings_in_the_recording(recorded):
    from mrrig.offline.review import read_recording

    rrd, _, _ = recorded
    rec = read_recording(rrd)
    marks = [e for e in rec.events if e.get("kind") == "mark"]
    where = ["plan two steps: step 1/2 constant current", "plan two steps: step 2/2 impossible Et"]
    assert [m["text"] for m in marks] == [
        f"{where[0]}: start",
        f"{where[0]}: end, passed",
        f"{where[1]}: start",
        f"{where[1]}: end, failed",
    ], [e["text"] for e in rec.events]
    settings = marks[0]["data"]["settings"]
    assert settings["set_controller"] == {"name": "constant", "current_a": 0.5}
    assert settings["actuator"]["amplitude_m"] == 0.005 and marks[0]["data"]["settle_s"] == 0.5
    assert marks[3]["data"]["verdict"] == "failed" and marks[3]["data"]["et"] > 0.0001
    assert marks[3]["data"]["reasons"].startswith("et_max: Et ")
    # each step's armed frames lie between its marks (a mark's time is the latest sensor
    # time the recording's writer had: a telemetry batch, 20 ms, may still be on its way)
    armed = rec.samples[rec.samples["state"] == RigState.ARMED]["t"]
    for begin, end in (marks[0:2], marks[2:4]):
        inside = armed[(armed >= begin["t"]) & (armed <= end["t"] + 0.1)]
        assert inside.size > 500, (begin["t"], end["t"])  # over a second at 500 Hz
    assert armed[armed < marks[0]["t"]].size == 0
    assert armed[(armed > marks[1]["t"] + 0.1) & (armed < marks[2]["t"])].size == 0
    audits = [e for e in rec.events if e.get("kind") == "audit" and "control mark" in e["text"]]
    assert len(audits) == 4 and all("accepted" in a["text"] for a in audits)


@pytest.mark.process
def test_review_of_a_recording_gives_the_daemons_latency_budget_verdict(recorded):
    rrd, daemon_printed, _ = recorded
    reviewed = mrrig("review", str(rrd))
    assert reviewed.returncode == 0, reviewed.stderr

    def budget(text: str) -> str:
        (line,) = [ln.strip() for ln in text.splitlines() if "the spec's budget" in ln]
        return line

    print(f"daemon: {budget(daemon_printed)}\nreview: {budget(reviewed.stdout)}")
    assert budget(reviewed.stdout) == budget(daemon_printed)
    assert budget(daemon_printed).endswith("(its work)")


@pytest.mark.parametrize("command", ["test", "control"])
def test_help_lists_the_controllers_by_name(command):
    from mrrig.loop.controllers import CONTROLLERS

    out = mrrig(command, "--help")
    assert out.returncode == 0, out.stderr
    listed = re.findall(r"^  ([a-z_]+)  +\S", out.stdout.split("controllers (")[1], re.M)
    assert listed == list(CONTROLLERS)
    assert "network_inversion  The paper's inverse model" in out.stdout


def _sidecar_of(config: str) -> int:
    """The pid of the telemetry process of the daemon started with `config`."""
    procs = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            cmd = (d / "cmdline").read_bytes().split(b"\0")
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        procs[int(d.name)] = (cmd, ppid)
    daemons = {pid for pid, (cmd, _) in procs.items() if config.encode() in cmd}
    (sidecar,) = [
        pid
        for pid, (cmd, ppid) in procs.items()
        if ppid in daemons and b"mrrig.rigio.sidecar_process" in cmd
    ]
    return sidecar


@pytest.mark.process
def test_a_stalled_control_plane_is_waited_for_not_fatal_to_the_plan(rig, tmp_path):
    """The machine stalls the rig's telemetry process for 3 s in the middle of a step: its
    telemetry and its answers pause, the daemon runs on; the step waits for them (up to
    runner.CONTROL_PATIENCE_S) and passes, where 2 s without telemetry had aborted it (and a
    status query's timeout ended the whole plan without a report: the heating plan's first
    run)."""
    plan = write(tmp_path, PLAN.format(d1=8))
    junit = tmp_path / "r.xml"
    args = ["--rig", RIG, "--zenoh-config", str(rig), "--junit", str(junit)]
    sidecar = _sidecar_of(str(rig.parent / "rig.toml"))
    proc = start(["-m", "mrrig", "test", str(plan), *args], stdout=subprocess.PIPE, text=True)
    try:
        from mrrig.api import Rig

        with Rig(RIG, zenoh_config=rig) as r:
            deadline = time.monotonic() + 20
            while r.status()["state"] != "ARMED":
                assert time.monotonic() < deadline, "the plan never armed the rig"
                time.sleep(0.05)
        time.sleep(2.0)
        os.kill(sidecar, signal.SIGSTOP)
        time.sleep(3.0)
        os.kill(sidecar, signal.SIGCONT)
        stdout, _ = proc.communicate(timeout=60)
    finally:
        os.kill(sidecar, signal.SIGCONT)
        stop(proc)
    assert proc.returncode == 1, stdout  # step 2's impossible Et, as always
    cases = junit_cases(junit)
    assert cases["constant current"].is_passed, stdout
    assert cases["impossible Et"].is_failure, stdout


def test_the_guide_lists_the_controllers_by_name():
    from mrrig.loop.controllers import CONTROLLERS

    text = (REPO / "docs" / "guide.md").read_text()
    listed = text.split("A step's `controller.name` is one of the registry's: ")[1].split(" (")[0]
    assert re.findall(r"`([a-z_]+)`", listed) == list(CONTROLLERS)
