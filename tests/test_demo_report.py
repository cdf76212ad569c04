"""The demo's progress numbers and verdict (pure: no processes)."""

from __future__ import annotations

import numpy as np
import pytest

from mrrig.cli.demo_report import RunningEt, verdict
from mrrig.loop.samples import RigState
from mrrig.offline.metrics import error_norm


def test_running_et_over_batches_is_the_papers_et_over_the_armed_samples():
    rng = np.random.default_rng(1)
    f_des = 800 * np.sin(np.linspace(0, 20, 3000))
    f_meas = f_des + rng.normal(0, 20, f_des.size)
    state = np.full(f_des.size, RigState.ARMED)
    state[:300] = RigState.IDLE
    et = RunningEt()
    for k in range(0, f_des.size, 25):  # as telemetry batches come
        sl = slice(k, k + 25)
        et.add(
            {
                "state": state[sl].tolist(),
                "f_des": f_des[sl].tolist(),
                "f_meas": f_meas[sl].tolist(),
            }
        )
    armed = state == RigState.ARMED
    assert et.et() == pytest.approx(error_norm(f_des[armed], f_meas[armed]), rel=1e-9)
    assert et.armed == armed.sum() and et.n == f_des.size


def _summary(et, armed, faults=()):
    return {"et": et, "frames": 1000, "armed_frames": armed, "faults": list(faults)}


@pytest.mark.parametrize(
    ("summary", "ok", "failing"),
    [
        (_summary(0.03, 900), True, []),
        (_summary(0.15, 900), False, ["Et"]),
        (_summary(0.03, 400), False, ["armed"]),
        (_summary(0.03, 900, [{"t": 1.0, "reason": "r", "fault": "sensor_timeout"}]), True, []),
        (_summary(0.03, 900, [{"t": 1.0, "reason": "r", "fault": "range"}]), False, ["faults"]),
        (_summary(None, 0), False, ["Et", "armed"]),
    ],
)
def test_verdict_checks_each_bound(summary, ok, failing):
    got, text = verdict(summary)
    assert got is ok and text.splitlines()[0] == f"demo: {'PASS' if ok else 'FAIL'}"
    failed = [line.split()[1] for line in text.splitlines()[1:] if line.startswith("  FAIL")]
    assert failed == failing, text
