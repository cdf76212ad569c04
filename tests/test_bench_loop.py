"""`mrrig bench loop`'s verdict on the spec's budget (the runs themselves are benchmarks)."""

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
