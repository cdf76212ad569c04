"""Tuning (`mrrig tune`, mrrig/tune): the rule chooses the smallest measured Et and never a
faulted or unmeasured trial; `mrrig tune --sim` runs its trials on the simulated rig over the
bridge and writes the choice where the daemon reads it (tests/test_tune_sim.py, a process
module); the paper's validation cases as a force reference (`paper_case`) and as a plan
(configs/plans/paper-validation.toml)."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import threading
import time

import numpy as np
import pytest

from mrrig.interruption import stops_interrupt, what
from mrrig.loop.reference import PaperCase, paper_case_command
from mrrig.offline.datasets import dataset_a_validation
from mrrig.offline.metrics import error_norm
from mrrig.plans.plan import PlanError, load_plan
from mrrig.plans.runner import StepResult, table
from mrrig.tune import Candidate, Trial, TuneError, choose, grid
from mrrig.tune.trials import DEFAULT_PROFILE, TuneResult, write_trials
from tests.conftest import REPO

PAPER_PLAN = REPO / "configs/plans/paper-validation.toml"

# --- the rule (pure) -------------------------------------------------------------------------


def test_the_rule_chooses_the_smallest_measured_et():
    trials = [Trial(Candidate(mu), et) for mu, et in ((0.0, 0.02), (0.03, 0.011), (0.3, 0.05))]
    assert choose(trials).candidate.continuity == 0.03


def test_the_rule_never_chooses_a_faulted_or_unmeasured_trial():
    trials = [
        Trial(Candidate(0.0), 0.001, faults=("sensor_timeout",)),  # the smallest Et, faulted
        Trial(Candidate(0.01), math.nan),  # aborted before a measurement
        Trial(Candidate(0.03), 0.02),
        Trial(Candidate(0.3), 0.03),
    ]
    chosen = choose(trials)
    assert chosen.candidate.continuity == 0.03
    assert [t.usable for t in trials] == [False, False, True, True]


def test_the_rule_refuses_when_every_trial_faulted():
    with pytest.raises(TuneError, match="no usable trial among 2"):
        choose(
            [Trial(Candidate(0.0), 0.01, faults=("lost_frames",)), Trial(Candidate(1.0), math.nan)]
        )


def test_the_grid_is_every_combination_and_refuses_bad_values():
    g = grid([0.0, 0.1], [None, 0.002], [None, 2.0])
    assert (
        len(g) == 8 and g[0] == Candidate(0.0, None, None) and g[-1] == Candidate(0.1, 0.002, 2.0)
    )
    with pytest.raises(TuneError, match="continuity"):
        grid([-1.0])
    with pytest.raises(TuneError, match="feedback_tau_s"):
        grid([0.0], [20.0])


# --- the paper's validation cases as a force reference ---------------------------------------


def test_paper_case_command_is_data_set_a_validation_input():
    for k, case in enumerate(dataset_a_validation(), start=1):
        np.testing.assert_array_equal(paper_case_command(k), case.current, err_msg=case.name)


@pytest.mark.parametrize("k", [1, 4, 7])
def test_paper_case_reference_gives_the_papers_desired_force_for_the_cases_motion(k):
    """Driven by the case's own motion (1 ms, volts as the paper's plant takes them), the
    reference is the paper's desired force: the plant's force for that displacement and input."""
    case = dataset_a_validation()[k - 1]
    ref = PaperCase(k, 1.0, "paper-volt", 1e-3)
    ref.reset(10.0, case.x[0])  # any start time: the case's time runs from the reset
    f = np.array(
        [ref.force(10.0 + t, x, xd) for t, x, xd in zip(case.t, case.x, case.xd, strict=True)]
    )
    assert error_norm(case.force, f) < 1e-3  # 1e-5 to 6e-5 measured: the RK4 sub-steps differ


def test_the_paper_validation_plan_parses_with_the_seven_cases_and_their_figures():
    plan = load_plan(PAPER_PLAN)
    assert len(plan.steps) == 14
    cases, floors = plan.steps[:7], plan.steps[7:]
    assert [s.reference.kind for s in plan.steps] == ["paper_case"] * 14
    assert [s.reference.case for s in plan.steps] == list(range(1, 8)) * 2
    assert all(set(s.compare_et) == {"paper", "bench"} for s in cases)
    assert all(s.criteria.et_max == 0.010 for s in cases)
    # never tuned on: the tuning profile is not a validation case
    assert all(s.controller is None for s in cases)
    # then each case's floor: the same step with the case's own current as the command
    assert [s.floor_of for s in floors] == [s.name for s in cases]
    for case, floor in zip(cases, floors, strict=True):
        assert floor.controller.name == "reference_current"
        assert (floor.actuator, floor.reference) == (case.actuator, case.reference)
        assert (floor.duration_s, floor.settle_s) == (case.duration_s, case.settle_s)


def test_a_figure_beside_et_must_be_a_number_and_is_printed_in_the_table(tmp_path):
    text = PAPER_PLAN.read_text().replace("paper = 0.1335", 'paper = "x"')
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(PlanError, match=r"step 4 \(case 2\).*compare_et.paper: expected a number"):
        load_plan(bad)
    step = load_plan(PAPER_PLAN).steps[3]
    assert "(Et paper 0.1335, bench" in table([StepResult(step, "skipped")])


# --- mrrig tune --sim ------------------------------------------------------------------------


def _booted(sim: subprocess.Popen) -> float:
    """When firmware_sim's clock started (its fault injections count from there): its line
    before the first frame; its stderr drained after."""
    for line in sim.stderr:
        if "rig firmware on" in line:
            t_boot = time.monotonic()
            threading.Thread(target=sim.stderr.read, daemon=True).start()
            return t_boot
    raise AssertionError(f"firmware_sim exited at start (code {sim.wait()})")


def _result(interrupted: bool, ets: tuple[float, ...]) -> TuneResult:
    trials = [Trial(Candidate(0.01 * k), et) for k, et in enumerate(ets)]
    chosen = None if interrupted else choose(trials)
    return TuneResult(trials, chosen, "model.json", interrupted=interrupted)


def test_an_interrupted_tune_keeps_the_last_complete_table(tmp_path):
    """Issue 40, finding 15: an interrupted `mrrig tune` overwrote the last tune's table."""
    out = tmp_path / "model.tune.json"
    complete = _result(False, (0.02, 0.011))
    write_trials(complete, out, DEFAULT_PROFILE, "rig1")
    before = out.read_text(), out.with_suffix(".csv").read_text()
    for ets in ((0.5,), ()):  # interrupted in its second trial, and before its first
        cut = _result(True, ets)
        write_trials(cut, out, DEFAULT_PROFILE, "rig1")
        assert (out.read_text(), out.with_suffix(".csv").read_text()) == before
        kept = tmp_path / "model.tune.interrupted.json"
        assert cut.files["trials"] == str(kept) and json.loads(kept.read_text())["interrupted"]
        assert len(json.loads(kept.read_text())["trials"]) == len(ets)
    assert json.loads(out.read_text())["chosen"]["et"] == 0.011
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "model.tune.csv",
        "model.tune.interrupted.csv",
        "model.tune.interrupted.json",
        "model.tune.json",
    ]  # no temporary file left


@pytest.mark.parametrize(
    ("signum", "said"), [(signal.SIGTERM, "SIGTERM"), (signal.SIGINT, "Ctrl-C (SIGINT)")]
)
def test_a_stop_signal_is_named_not_taken_for_ctrl_c(signum, said):
    """Issue 40, finding 15: SIGTERM was reported as "interrupted (Ctrl-C)"."""
    with pytest.raises(KeyboardInterrupt) as caught, stops_interrupt():
        os.kill(os.getpid(), signum)
        time.sleep(5.0)  # the signal comes first
    assert what(caught.value) == said
