"""The run summary in fixed memory: batch by batch it equals the whole run at once."""

from __future__ import annotations

import math
import re

import can
import numpy as np
import pytest

from mrrig.config import load_config
from mrrig.loop.daemon import Daemon
from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.loop.summary import (
    ERROR_BIN_N,
    LATENCY_BIN_US,
    Histogram,
    SummaryAccumulator,
    format_summary,
    summarize,
)
from mrrig.offline.metrics import error_norm
from tests.rig_harness import ScriptedRig, write_config


def _run(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = np.zeros(n, dtype=SAMPLE_DTYPE)
    s["t"] = np.cumsum(rng.choice([0.002, 0.002, 0.002, 0.013], n))
    s["f_des"] = 400.0 * np.sin(s["t"] * 12.0) + 100.0
    s["f_meas"] = s["f_des"] + rng.normal(0.0, 15.0, n)
    s["i_cmd"] = rng.uniform(0.0, 2.0, n)
    s["latency_us"] = rng.gamma(4.0, 40.0, n)
    s["latency_us"][::97] = np.nan  # frames without a measure
    s["state"] = np.where(rng.random(n) < 0.9, RigState.ARMED, RigState.IDLE)
    return s


def test_batches_give_the_numbers_of_the_whole_run():
    s = _run(20_000)
    whole = summarize(s, [])
    acc = SummaryAccumulator()
    for k in range(0, s.size, 10):
        acc.add(s[k : k + 10])
    parts = acc.result([])
    for key in ("duration_s", "last_frame_t_s", "frames", "armed_frames", "frame_gap_ms"):
        assert parts[key] == whole[key], key
    assert parts["et"] == pytest.approx(whole["et"], rel=1e-9)
    for group in ("tracking_error_n", "latency_us", "i_cmd_step_a"):
        assert parts[group] == whole[group], group  # integer counts: exactly equal
    for k, v in whole["i_cmd_a"].items():
        assert parts["i_cmd_a"][k] == pytest.approx(v, rel=1e-9), k


def test_numbers_match_the_exact_ones_to_the_bins():
    s = _run(20_000, seed=1)
    r = summarize(s, [{"kind": "fault", "t": 1.5, "reason": "x"}, {"kind": "info", "t": 2.0}])
    armed = s["state"] == RigState.ARMED
    assert r["et"] == pytest.approx(error_norm(s["f_des"][armed], s["f_meas"][armed]), rel=1e-9)
    assert r["i_cmd_a"]["std"] == pytest.approx(float(s["i_cmd"].std()), rel=1e-9)
    assert r["faults"] == [{"t": 1.5, "reason": "x"}]
    gaps = np.diff(s["t"]) * 1e3
    assert r["frame_gap_ms"] == {"max": gaps.max(), "over_10_ms": int((gaps > 10).sum())}
    for values, got, width in (
        (s["latency_us"][np.isfinite(s["latency_us"])], r["latency_us"], LATENCY_BIN_US),
        (np.abs(s["f_des"] - s["f_meas"])[armed], r["tracking_error_n"], ERROR_BIN_N),
    ):
        v = np.sort(values)
        for name, p in got.items():
            if name == "max":
                assert p == v[-1]
                continue
            rank = float(name[1:]) / 100.0 * (v.size - 1)
            lo, hi = v[math.floor(rank)], v[math.ceil(rank)]
            assert lo - width / 2 <= p <= hi + width / 2, (name, p, lo, hi)


def test_command_steps_count_only_between_armed_frames():
    s = np.zeros(8, dtype=SAMPLE_DTYPE)
    s["t"] = np.arange(8) * 0.002
    s["i_cmd"] = [0.0, 0.8, 0.9, 0.3, 1.9, 0.0, 1.2, 1.25]
    armed, idle = RigState.ARMED, RigState.IDLE
    s["state"] = [idle, armed, armed, armed, armed, idle, armed, armed]
    # armed pairs: 0.8->0.9, 0.9->0.3, 0.3->1.9, 1.2->1.25; arming (0 -> 0.8, 0 -> 1.2) and
    # disarming (1.9 -> 0) are not steps of the controller
    whole = summarize(s, [])["i_cmd_step_a"]
    assert whole["max"] == pytest.approx(1.6)
    assert whole["over_0.25_a"] == 2
    acc = SummaryAccumulator()
    for k in range(s.size):
        acc.add(s[k : k + 1])  # one frame a batch: the pairs across batches count the same
    assert acc.result([])["i_cmd_step_a"] == whole
    assert 0.6 <= whole["p99"] <= 1.6 + 0.0005  # between the two largest steps, to half a bin
    text = format_summary(summarize(s, []))
    assert f"i_cmd steps   p99 {whole['p99']:.4g} A, max 1.6 A, 2 over 0.25 A" in text


def test_histogram_overflow_reports_the_exact_max():
    h = Histogram(1.0, 10.0)
    h.add(np.array([1.2, 2.5, 50.0, 70.0, np.nan]))
    assert h.n == 4
    p = h.percentiles((25, 99))
    assert p["p25"] == 1.5  # the middle of the bin of 1.2 (rank 0.75 of 4 values)
    assert p["p99"] == 70.0 and p["max"] == 70.0  # in the overflow bin: the exact max
    assert math.isnan(Histogram(1.0, 10.0).percentiles((50,))["p50"])


def test_the_daemons_exit_summary_is_the_summary_of_its_samples(tmp_path):
    with ScriptedRig(tmp_path) as rig:
        for k in range(57):  # not a whole number of telemetry batches
            rig.exchange(x=0.001 * math.sin(k / 5), force=250.0 + 40.0 * k)
    d = rig.daemon
    s = np.concatenate(d.batches.handed_over())
    assert s.size == 57
    want = summarize(s, d.events)
    for key in ("frames", "armed_frames", "duration_s", "last_frame_t_s", "frame_gap_ms"):
        assert d.summary[key] == want[key], key
    assert d.summary["et"] == pytest.approx(want["et"], rel=1e-9, nan_ok=True)
    assert d.summary["latency_us"] == want["latency_us"]
    split = d.summary["latency_split_us"]
    # the latency is the wait plus the work, and the send() call is part of the work
    assert split["work"]["max"] <= d.summary["latency_us"]["max"]
    assert split["waited"]["max"] <= d.summary["latency_us"]["max"]
    assert split["send_call"]["max"] <= split["work"]["max"]
    text = format_summary(d.summary)
    assert "the spec's budget of the work per frame p99 <= 300 us" in text
    assert re.search(r"of it work  p50 [\d.]+ us", text), text


def test_a_daemon_without_kept_batches_holds_no_samples(tmp_path):
    cfg = load_config(write_config(tmp_path, "summary-bare", 50))
    d = Daemon(cfg)  # as `mrrig run` makes it
    d.bus = can.Bus(interface="virtual", channel="summary-bare")
    try:
        values = {"Displacement": 0.001, "Force": 250.0}
        values |= dict.fromkeys(("ActuatorEnabled", "LimitTripped", "EStop", "SensorFault"), 0)
        for k in range(25):  # the loop's own calls, 2.5 batches
            d.cycle(values, k % 16, d.t0 + 0.002 * k)
            d._last_sensor_t = d.t0 + 0.002 * k
        assert d.batches.chunks == [] and d.batches.summary.frames == 20
        with pytest.raises(RuntimeError, match="keep_batches"):
            d.batches.handed_over()
    finally:
        d.bus.shutdown()
