"""Benchmarks' verdicts on the spec's budget and on the paper's table (the runs themselves are
benchmarks)."""

from __future__ import annotations

from mrrig.bench.loop import budget_verdict


def _run(p99: float, p999: float, unanswered: int) -> dict:
    return {"latency_us": {"p99": p99, "p99.9": p999}, "frames_without_command": unanswered}


def test_budget_is_met_only_when_every_part_of_it_is() -> None:
    assert budget_verdict(_run(300.0, 1000.0, 0)).startswith("MET: p99 300.0 <= 300 us")
    assert budget_verdict(_run(300.5, 200.0, 0)).startswith("MISSED: p99 300.5 > 300 us")
    assert "p99.9 1001.0 > 1000 us" in budget_verdict(_run(100.0, 1001.0, 0))
    missed = budget_verdict(_run(100.0, 200.0, 1))
    assert missed.startswith("MISSED") and missed.endswith("1 frames without a command")


def test_bench_paper_counts_the_cases_at_or_below_each_reference() -> None:
    from mrrig.bench.paper import acceptance_lines

    paper = [0.04, 0.04, 0.04, 0.13, 0.12, 0.20, 0.13]
    table = {
        "network_inversion": [0.08] * 7,  # the gradient solve, the paper's loop
        "network_inversion_exact": [0.08, 0.07, 0.2, 0.08, 0.1, 0.1, 0.09],
        "network_inversion_feedback": [0.04, 0.03, 0.17, 0.01, 0.03, 0.03, 0.02],
    }
    text = "\n".join(acceptance_lines(table, paper))
    # by hand: 0.17 > 0.04 is the one case above, 0.17 / 0.04 = 4.25
    assert (
        "exact (default) + feedback             6 of 7 cases at or below, worst ratio 4.25" in text
    )
    assert "root" not in text  # rows the table lacks are left out
    # 0.08 and 0.07 and 0.08 at or below 0.08; 0.2 / 0.08 = 2.5
    assert "no feedback          3 of 7 cases at or below, worst ratio 2.50" in text
    assert "flow" not in text  # rows the table lacks are left out
