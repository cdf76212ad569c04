"""Benchmarks' verdicts on the spec's budget and on the paper's table (the runs themselves are
benchmarks)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mrrig.offline.bench.loop import budget_verdict, hil_args, hil_lines


def _run(p99: float, p999: float, unanswered: int) -> dict:
    return {"latency_us": {"p99": p99, "p99.9": p999}, "frames_without_command": unanswered}


def test_budget_is_met_only_when_every_part_of_it_is() -> None:
    assert budget_verdict(_run(300.0, 1000.0, 0)).startswith("MET: p99 300.0 <= 300 us")
    assert budget_verdict(_run(300.5, 200.0, 0)).startswith("MISSED: p99 300.5 > 300 us")
    assert "p99.9 1001.0 > 1000 us" in budget_verdict(_run(100.0, 1001.0, 0))
    missed = budget_verdict(_run(100.0, 200.0, 1))
    assert missed.startswith("MISSED") and missed.endswith("1 frames without a command")


def test_bench_paper_counts_the_cases_at_or_below_each_reference() -> None:
    from mrrig.offline.bench.paper_report import acceptance_lines

    paper = [0.04, 0.04, 0.04, 0.13, 0.12, 0.20, 0.13]
    table = {
        "network_inversion": [0.08] * 7,  # the gradient solve, the paper's loop
        "network_inversion_exact": [0.08, 0.07, 0.2, 0.08, 0.1, 0.1, 0.09],
        "network_inversion_feedback": [0.04, 0.03, 0.17, 0.01, 0.03, 0.03, 0.02],
    }
    starts = {"network_inversion": {"mean": [0.07] * 7, "min": [0.06] * 7, "max": [0.09] * 7}}
    text = "\n".join(acceptance_lines(table, paper, starts))
    # by hand: 0.17 > 0.04 is the one case above, 0.17 / 0.04 = 4.25
    assert (
        "exact, present instant + feedback      6 of 7 cases at or below, worst ratio 4.25" in text
    )
    assert "root" not in text  # rows the table lacks are left out
    # 0.08 and 0.07 and 0.08 at or below 0.08; 0.2 / 0.08 = 2.5
    assert "no feedback          3 of 7 cases at or below, worst ratio 2.50" in text
    # over all the cases at once: mean 0.72 / 7 against 0.08, largest 0.2 against 0.08
    assert "mean Et 0.1029 against 0.0800, largest 0.2000 against 0.0800" in text
    # against the mean of the random starts: only 0.07 <= 0.07; 0.2 / 0.07 = 2.86
    assert "the mean of its random starts        1 of 7 cases at or below, worst ratio 2.86" in text
    assert "flow" not in text  # rows the table lacks are left out


def test_bench_paper_continuity_sweep_lines_count_and_take_the_smallest_per_case() -> None:
    from mrrig.offline.bench.paper_report import sweep_lines

    gradient = [0.05, 0.05, 0.05]
    sweep = {"mu 0": [0.04, 0.06, 0.05], "mu 1": [0.06, 0.03, 0.07]}
    lines = sweep_lines("title", sweep, gradient)
    assert lines[0] == "title"
    assert lines[1].startswith("  mu 0 ") and lines[1].endswith("2 of 3")
    assert lines[2].startswith("  mu 1 ") and lines[2].endswith("1 of 3")
    assert lines[3].split()[-3:] == ["0.0400", "0.0300", "0.0500"]
    assert lines[4].split()[-3:] == ["0.0500", "0.0500", "0.0500"]
    # without the smallest row (the descent sweep): the rows, then the gradient
    lines = sweep_lines("title", sweep, gradient, smallest=False)
    assert len(lines) == 4 and lines[3].startswith("  the gradient solve")


def test_bench_help_is_the_named_benchmarks_own(capsys) -> None:
    import pytest

    from mrrig.offline.bench.cli import main

    with pytest.raises(SystemExit) as done:
        main(["loop", "--help"])
    assert done.value.code == 0
    assert "usage: mrrig bench loop" in capsys.readouterr().out
    with pytest.raises(SystemExit) as done:
        main(["fly"])
    assert done.value.code == 2
    assert "invalid choice: 'fly'" in capsys.readouterr().err


def test_bench_paper_prints_table_6_with_the_daemons_default_and_keeps_the_rest_for_detail():
    from mrrig.offline.bench.paper_report import TABLE_ROWS, format_report, labels

    choice = {"feedback": {"feedback_tau_s": 0.0, "continuity": 0.03}, "open": {"continuity": 0.1}}
    names = [*TABLE_ROWS, "default_flow", "default_gradient", "network_inversion_root"]
    row = {n: [0.01 * (k + 1)] * 7 for k, n in enumerate(names)}
    lab = labels(choice, 0.3, 0.03)
    assert [n for n in lab if "default" in lab[n]] == ["default"]  # only the daemon's
    r = {
        "cases": [f"c{k}" for k in range(7)],
        "dt_s": 1e-3,
        "vmax_v": 12.0,
        "table6": row,
        "paper_table6": {"heaviside": [0.5] * 7},
        "random_starts": {},
        "labels": lab,
        "default_settings": {"method": "exact", "feedback_tau_s": 0.0, "continuity": 0.03},
        "inversion_cost": {
            "step_ahead_feedback_us_median": 40.0,
            "step_ahead_feedback_us_p99": 80.0,
            "step_flow_us_median": 30.0,
            "step_gradient_us_median": 9000.0,
            "step_adaptation_us_median": 45.0,
        },
    }
    text = format_report(r)
    assert lab["default"] in text and lab["default_adaptation"] in text
    assert lab["network_inversion_root"] not in text  # exploratory: only with --detail
    # the measurement's pick: the smallest mean Et of the three solves (exact here)
    assert "the measurement picks exact (the default)." in text
    assert "  paper" in text and "what differs from the paper" in text


def test_bench_drift_sets_aside_the_half_second_after_a_stall_or_an_arming():
    from mrrig.offline.bench.drift import _after_stalls

    t = np.arange(0, 3.0, 0.002)
    t[1000:] += 0.05  # a 52 ms gap at t = 2 s
    armed = np.ones(t.size, bool)
    armed[:100] = False  # armed at 0.2 s
    out = _after_stalls(t, armed)
    expect = ((t >= 0.2) & (t < 0.7)) | ((t >= t[1000]) & (t < t[1000] + 0.5))
    np.testing.assert_array_equal(out, expect)


def test_bench_loop_sets_the_hybrid_simulation_s_work_beside_the_force_tracking_loop_s() -> None:
    def run(p50: float, p99: float) -> dict:
        return {"latency_split_us": {"work": {"p50": p50, "p99": p99, "p99.9": 2 * p99}}}

    lines = hil_lines({"off": run(150.0, 240.0), "hil": run(190.0, 310.0)})
    assert lines[0] == (
        "hybrid simulation: work per frame p50 190  p99 310  p99.9 620 us (p99 > 300 us)"
    )
    assert lines[1].endswith("the hybrid simulation adds +40 us at p50, +70 us at p99")
    assert hil_lines({"hil": run(190.0, 300.0)}) == [
        "hybrid simulation: work per frame p50 190  p99 300  p99.9 600 us (p99 <= 300 us)"
    ]
    # the scenario streams a second longer than the simulator: never played out early
    assert hil_args(Path("s.toml"), 60.0) == ("--hil", "s.toml", "--hil-duration", "61.0")


def test_bench_loop_prints_the_compiled_work_beside_the_python_work_and_the_target() -> None:
    from mrrig.offline.bench.loop import compiled_beside_python

    def run(p50: float, p99: float, p999: float) -> dict:
        work = {"p50": p50, "p99": p99, "p99.9": p999}
        return {"latency_split_us": {"work": work, "send_call": {"p50": 20.0}}}

    text = compiled_beside_python(run(20.0, 50.0, 150.0), run(80.0, 200.0, 600.0))
    assert "python / compiled: p50 4.00  p99 4.00  p99.9 4.00" in text
    assert text.endswith("MET (send() call p50 20 us of it)")
    assert "MISSED" in compiled_beside_python(run(20.0, 50.5, 100.0), run(80.0, 200.0, 600.0))
