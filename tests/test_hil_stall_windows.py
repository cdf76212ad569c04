"""J2 and J3 apart from the stalls a simulated HIL run measured (mrrig/hil/metrics.py,
mrrig/hil/measured_stalls.py): the actuator's dropped setpoints, the simulator's and the
transport's windows, the daemon's kernel-measured stalls. Pure numerics on synthetic data."""

from __future__ import annotations

import numpy as np
import pytest

from mrrig.hil.measured_stalls import DROPPED, counted, measured_windows
from mrrig.hil.metrics import (
    AFTER_STALL_S,
    StallWindow,
    merged_windows,
    too_fast,
    tracking,
    tracking_apart_from_windows,
)

DT = 0.002


def test_j3_apart_from_measured_windows_sets_aside_only_a_window_and_its_settling() -> None:
    """A setpoint dropped at 2.0005 s and a 3 mm error 10 ms later: set aside; a transport
    window [4.0005, 4.0065] s and a 2 mm error 19.5 ms after its end: set aside; a 1 mm error
    23.5 ms after it, past the settling: kept; a 0.5 mm error with no window: kept."""
    t = np.arange(4000) * DT
    x_c = 0.02 * np.sin(2 * np.pi * 1.0 * t)
    x_m = x_c.copy()
    x_m[1005] += 0.003  # 15 % of the 20 mm peak
    x_m[2013] -= 0.002  # t 4.026: 10 %
    x_m[2015] += 0.001  # t 4.030: 5 %
    x_m[3000] += 0.0005  # 2.5 %
    drop = StallWindow(DROPPED, 2.0005, 2.0005)
    windows = [drop, StallWindow("transport", 4.0005, 4.0065)]
    got = tracking_apart_from_windows(x_c, x_m, t, windows, DT)
    # 2.002 .. 2.020 s and 4.002 .. 4.026 s
    assert got.excluded == 10 + 13
    assert AFTER_STALL_S == pytest.approx(0.02)
    assert got.j3_pct == pytest.approx(5.0, rel=1e-6) and got.kept_peak_t_s == pytest.approx(4.03)
    assert got.peak_t_s == pytest.approx(t[1005]) and got.peak_window == drop
    assert tracking(x_c, x_m, DT).j3_pct == pytest.approx(15.0, rel=1e-6)  # the raw J3
    left = np.delete(x_m - x_c, np.r_[1001:1011, 2001:2014])
    assert got.j2_pct == pytest.approx(100 * np.std(left) / np.std(x_c), rel=1e-9)
    # nothing measured: nothing set aside, the peak explained by none
    none = tracking_apart_from_windows(x_c, x_m, t, [], DT)
    assert none.excluded == 0 and none.peak_window is None
    assert none.j3_pct == pytest.approx(15.0, rel=1e-6)
    assert none.j2_pct == pytest.approx(tracking(x_c, x_m, DT).j2_pct, rel=1e-12)
    with pytest.raises(ValueError, match="nothing left"):
        tracking_apart_from_windows(x_c, x_m, t, [StallWindow("kernel", -1.0, 9.0)], DT)


def test_windows_that_touch_merge_and_keep_their_kinds() -> None:
    ws = [
        StallWindow(DROPPED, 2.0015, 2.0015),
        StallWindow("transport", 1.995, 2.000),
        StallWindow(DROPPED, 2.003, 2.003),  # within a period of the one before
        StallWindow("kernel", 3.0, 3.004),  # apart
    ]
    assert merged_windows(ws, DT) == (
        StallWindow(f"transport+{DROPPED}", 1.995, 2.003),
        StallWindow("kernel", 3.0, 3.004),
    )
    assert counted(ws) == f"2 {DROPPED}, 1 transport, 1 kernel"
    assert counted([]) == "none"


def test_measured_windows_sets_each_process_s_stalls_on_the_run_s_clock() -> None:
    """Both processes on CLOCK_MONOTONIC: the simulator's times from its clock_t0_s, the
    daemon's from its own; the run's clock starts at its first streamed frame."""
    sim = {
        "clock_t0_s": 100.0,
        "late_setpoint_times": [{"t_s": 5.0, "echo": 3}],
        "stall_windows": [{"kind": "transport", "start_s": 6.0, "end_s": 6.01}],
    }
    daemon = {"clock_t0_s": 98.0, "kernel_stalls": {"windows": [[10.0, 10.004, 1.0, 2.0, 0.0]]}}
    got = measured_windows(sim, daemon, run_t0_s=3.0)
    assert [w.kind for w in got] == [DROPPED, "transport", "kernel"]
    starts_ends = [t for w in got for t in (w.start_s, w.end_s)]
    assert starts_ends == pytest.approx([4.0, 4.0, 5.0, 5.01, 7.0, 7.004])
    # a daemon whose stalls were not measured, a simulator without --measure-echo
    assert measured_windows({"clock_t0_s": 100.0}, {"clock_t0_s": 98.0}, 3.0) == []


def test_too_fast_names_where_a_stroke_asks_more_speed_than_the_actuator_has() -> None:
    """A 2 Hz stroke whose peak speed is 1.2 m/s, against a 1 m/s actuator."""
    t = np.arange(500) * DT
    x_c = 1.2 / (2 * np.pi * 2.0) * np.sin(2 * np.pi * 2.0 * (t + 0.125))  # 1.2 m/s peak
    fast = too_fast(x_c, DT, 1.0)
    assert fast is not None and fast.peak_m_s == pytest.approx(1.2, rel=1e-3)
    # at a zero crossing of the stroke, within a frame (the samples' speeds there tie)
    assert min(abs(fast.peak_t_s - p) for p in (0.125, 0.375, 0.625, 0.875)) <= DT
    # |cos| > 1 / 1.2 on 2 arccos(1/1.2) / pi of each half period: the frames over 1 m/s
    share = 2 * np.arccos(1 / 1.2) / np.pi
    assert fast.frames == pytest.approx(share * t.size, abs=4)
    assert too_fast(x_c, DT, 1.25) is None
