"""The simulator and the daemon as separate processes over the python-can-remote bridge."""

from __future__ import annotations

import json
import signal
import time

import pytest

from mrrig.canbus.codec import Codec
from tests.conftest import rig_config

pytestmark = pytest.mark.slow

SENSORS, COMMAND = 0x110, 0x210


def decode_log(frames):
    """The bus log as [("S", counter, values) | ("C", echo, values)], invalid frames dropped."""
    parser = Codec().parser()
    out = []
    rejected: dict[str, int] = {}
    for t, fid, data in frames:
        if fid not in (SENSORS, COMMAND):
            continue
        p = parser.parse(fid, data, t)
        assert p.ok or fid == SENSORS, f"daemon sent an invalid frame: {p.reason}"
        if not p.ok:
            key = p.reason.split(":")[1].split("(")[0].strip() if ":" in p.reason else p.reason
            rejected[key] = rejected.get(key, 0) + 1
        if p.ok:
            key = "S" if fid == SENSORS else "C"
            out.append(
                (key, p.counter if key == "S" else int(p.values["SensorCounterEcho"]), p.values)
            )
    print("sensor frames rejected by the listener:", rejected)
    return out


def test_ten_seconds_of_force_tracking_one_command_per_sensor_frame(
    tmp_path, bridge, procs, sim_model
):
    """The daemon runs first; the simulator streams for 10 s and counts the answers itself:
    every sensor frame it sent must have got exactly one valid command echoing its counter."""
    cfg = rig_config(tmp_path, bridge, sim_model)
    summary_path = tmp_path / "summary.json"
    daemon = procs(
        ["-m", "mrrig", "run", "--config", str(cfg), "--arm", "--summary-json", str(summary_path)]
    )
    time.sleep(3.0)  # the daemon is up and waiting for sensor frames
    assert daemon.poll() is None
    sim_stats = tmp_path / "sim.json"
    sim = procs(
        [
            "-m",
            "firmware_sim",
            "--config",
            "configs/sim.toml",
            "--bus-channel",
            bridge,
            "--stats",
            str(sim_stats),
            "--duration",
            "10",
        ]
    )
    assert sim.wait(timeout=60) == 0
    daemon.send_signal(signal.SIGTERM)
    assert daemon.wait(timeout=30) == 0
    st = json.loads(sim_stats.read_text())
    s = json.loads(summary_path.read_text())
    a = st["answers"]
    print(
        f"simulator: {st['sensor_frames_sent']} sensor frames, answers {a}, "
        f"watchdog trips {st['watchdog_trips']}, answer latency {st['answer_latency_us']}"
    )
    print(
        f"daemon: tracking Et {s['et']:.4f} over {s['armed_frames']} armed frames; "
        f"|error| p95 {s['tracking_error_n']['p95']:.1f} N; latency {s['latency_us']}; "
        f"faults {s['faults']}"
    )
    assert st["sensor_frames_sent"] >= 4900
    assert a["answered_once"] == st["sensor_frames_sent"] - 1  # all but the one in flight
    assert a["unanswered"] == 0 and a["answered_more_than_once"] == 0 and a["unmatched"] == 0
    assert st["max_commanded_current_a"] <= 2.0
    assert s["et"] <= 0.1
    # No fault while the simulator streamed (the sensor timeout after it stopped is expected),
    # except a firmware watchdog trip when the bridge itself held an answer past 20 ms: the
    # python-can-remote bridge's round trip reaches tens of ms on this 2-core VM (the
    # simulator measures it); every frame was still answered once, checked above.
    bridge_stalled = st["answer_latency_us"]["max"] > 20_000
    faults = s["faults"]
    if faults and faults[-1]["reason"].startswith("no sensor frame"):
        faults = faults[:-1]  # the simulator stopped first
    during = faults
    unexplained = [f for f in during if not (bridge_stalled and "watchdog" in f["reason"])]
    assert unexplained == []
    assert st["watchdog_trips"] == 0 or bridge_stalled


def test_killed_daemon_the_simulator_watchdog_zeroes_the_current(tmp_path, bridge, buslog, procs):
    cfg = rig_config(tmp_path, bridge, None, controller={"name": "constant", "current_a": 1.0})
    sim_stats = tmp_path / "sim.json"
    sim = procs(
        [
            "-m",
            "firmware_sim",
            "--config",
            "configs/sim.toml",
            "--bus-channel",
            bridge,
            "--stats",
            str(sim_stats),
        ]
    )
    time.sleep(1.0)
    daemon = procs(["-m", "mrrig", "run", "--config", str(cfg), "--arm"])
    time.sleep(4.0)
    assert daemon.poll() is None
    daemon.send_signal(signal.SIGKILL)
    daemon.wait(timeout=5)
    time.sleep(0.5)
    sim.send_signal(signal.SIGTERM)
    assert sim.wait(timeout=10) == 0
    log = decode_log(buslog.frames)
    parser = Codec().parser()
    statuses = [(t, parser.parse(fid, data, t)) for t, fid, data in buslog.frames if fid == 0x111]
    t_last_cmd = max(t for t, fid, _ in buslog.frames if fid == COMMAND)
    after = [(t, p.values) for t, p in statuses if p.ok and t > t_last_cmd]
    assert after, "no RigStatus after the daemon died"
    # the first status after the trip says FAULT, command timeout, and the coil at 0 A soon after
    fault = [(t, v) for t, v in after if v["State"] == 3 and v["FaultCode"] == 1]
    assert fault, f"no FAULT/command-timeout status after the kill: {after[:3]}"
    assert fault[0][0] - t_last_cmd < 0.020 + 0.100 + 0.05  # watchdog + one status period
    assert fault[-1][1]["CoilCurrent"] < 0.01
    stats = json.loads(sim_stats.read_text())
    trips = [e["event"] for e in stats["fault_events"] if e["event"].startswith("watchdog: no")]
    assert trips, stats["fault_events"]
    gap_ms = float(trips[-1].split("for ")[1].split(" ms")[0])
    print(f"watchdog tripped {gap_ms} ms after the last command; statuses after: {len(after)}")
    assert 20.0 < gap_ms <= 22.5  # more than 20 ms, within one sensor period of it
    assert any(k == "C" for k, _, _ in log)
