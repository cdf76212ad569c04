"""`mrrig bench fuzz`'s observer misuse part (mrrig/offline/bench/fuzz_observer.py): random
observer actions against the real sidecar on the shipped access control, mutual TLS, on
127.0.0.1; none reaches the rig or the others, and the part sees the operator's traffic."""

from __future__ import annotations

import random
from pathlib import Path

from mrrig.offline.bench import fuzz_observer


def test_no_observer_action_reaches_the_rig(tmp_path: Path):
    part = fuzz_observer.run(tmp_path, random.Random(3), minutes=0.8)  # about 5 s
    assert part["observer_actions"] > 100, part
    assert set(part["observer_actions_by_kind"]) == set(fuzz_observer.ACTIONS), part
    assert fuzz_observer.failures(part) == [], fuzz_observer.report(part)
    assert part["observer_reached"] == {}
