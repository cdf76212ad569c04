"""firmware_sim as a real process on the python-can-remote bridge; the test is the daemon.

Rates are checked by ratios of frame counts and loose wall-clock bounds only (noisy 2-core VM);
the simulator's own jitter and CPU numbers are printed, not asserted.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from firmware_sim.config import SimConfig
from firmware_sim.firmware import Firmware, Frame
from firmware_sim.runner import RunStats, _receive
from mrrig.rigio.canbus import Codec, find_free_port, open_bus, start_bridge, stop_bridge
from mrrig.rigio.canbus.profile import contract_profile

REPO = Path(__file__).resolve().parents[1]
CODEC = Codec()
SENSORS_ID = CODEC.layout("RigSensors").frame_id
STATUS_ID = CODEC.layout("RigStatus").frame_id
START_TIMEOUT_S = 10.0


@pytest.fixture
def bridge() -> Iterator[tuple[str, subprocess.Popen[bytes]]]:
    port = find_free_port()
    proc = start_bridge(port)
    try:
        yield f"ws://127.0.0.1:{port}/", proc
    finally:
        stop_bridge(proc)


def start_sim(url: str, tmp_path: Path, *extra: str) -> subprocess.Popen[bytes]:
    cmd = [
        sys.executable,
        "-m",
        "firmware_sim",
        "--config",
        "configs/sim.toml",
        "--bus-channel",
        url,
        "--stats",
        str(tmp_path / "stats.json"),
        *extra,
    ]
    return subprocess.Popen(
        cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=(tmp_path / "sim.log").open("wb")
    )


def wait_first_sensor_frame(bus, proc: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        assert proc.poll() is None, "simulator exited during start-up"
        msg = bus.recv(0.1)
        if msg is not None and msg.arbitration_id == SENSORS_ID:
            return
    pytest.fail("no RigSensors frame from the simulator")


def stop_sim(proc: subprocess.Popen[bytes]) -> int:
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(5.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise


def test_run_stats_count_each_sensor_frame_answered_once_unanswered_or_more_than_once():
    stats = RunStats()
    frames = [Frame(SENSORS_ID, b"", c, True) for c in range(5)]
    stats.on_sensor_sent(frames[0], 0.000, 0.0001)
    stats.on_command(0, 0.0006)  # answered once, 500 us
    stats.on_sensor_sent(frames[1], 0.002, 0.0021)  # unanswered
    stats.on_command(0, 0.0030)  # frame 0 again: answered twice
    stats.on_sensor_sent(frames[2], 0.004, 0.0041)
    stats.on_sensor_sent(frames[3], 0.006, 0.0061)
    stats.on_command(2, 0.0065)  # late (after frame 3) but answered once, 2400 us
    stats.on_command(3, 0.0066)  # answered once, 500 us
    stats.on_command(3, 0.0070, safe=True)  # the daemon's own SAFE after a timeout: no answer
    stats.on_sensor_sent(Frame(SENSORS_ID, b"", 9, False), 0.008, 0.0082)  # faulted frame
    stats.on_command(9, 0.0085)  # echoes a frame that awaits no answer
    stats.on_sensor_sent(frames[4], 0.010, 0.0101)  # the last frame
    stats.on_command(4, 0.0108)  # its answer, while `run` listens after the last frame
    stats.on_sensor_sent(Frame(SENSORS_ID, b"", 5, True), 0.012, 0.0121)
    stats.finish()  # the last frame is without an answer: unanswered
    assert (stats.answered_once, stats.unanswered, stats.answered_more_than_once) == (3, 2, 1)
    assert stats.answered_late == 1
    assert stats.unmatched_answers == 1 and stats.sensor_frames_faulted == 1
    assert stats.safe_repeats == 1
    assert list(stats.latency_us) == pytest.approx([500.0, 2400.0, 500.0, 700.0])
    assert list(stats.jitter_us) == pytest.approx([100.0, 100.0, 100.0, 100.0, 200.0, 100.0, 100.0])


def test_run_stats_count_active_answers_stale_from_the_frames_bus_timestamp():
    """A frame's age runs from its receive timestamp at the bus (spec/system.md), which the
    echo of the frame gives: a bus that took the frame in 50 ms late and an answer 2 ms after
    that is no stale answer; 20 ms after the bus took it in is one; without the echo the age
    runs from the send."""
    stats = RunStats(measure_echo=True, stale_answer_age_s=0.01)
    frames = [Frame(SENSORS_ID, b"", c, True) for c in range(3)]
    stats.on_sensor_sent(frames[0], 0.000, 0.000, sent_wall_s=100.000)
    stats.on_echo(0, 0.051, bus_ts_s=100.050)  # the bus held it up 50 ms
    stats.on_command(0, 0.053, bus_ts_s=100.052)  # 2 ms after the bus took it in
    stats.on_sensor_sent(frames[1], 0.060, 0.060, sent_wall_s=100.060)
    stats.on_echo(1, 0.061, bus_ts_s=100.061)
    stats.on_command(1, 0.082, bus_ts_s=100.081)  # 20 ms after: stale
    assert stats.active_answers_stale == 1
    stats.on_sensor_sent(frames[2], 0.090, 0.090, sent_wall_s=100.090)  # no echo
    stats.on_command(2, 0.103, bus_ts_s=100.102)  # 12 ms after its send: stale
    stats.on_command(2, 0.104, safe=True, bus_ts_s=100.103)  # SAFE: never stale
    assert stats.active_answers_stale == 2
    # when the bus took each in, on this process's clock
    assert np.allclose(stats.stale_answers, [[1, 0.061, 0.081], [2, 0.090, 0.102]])


def test_run_stats_count_active_commands_applied_to_a_stale_or_invalid_frame():
    """What the firmware applied (not late), timed on its own clock from the frame's send: an
    ACTIVE command applied 12 ms after its frame left, or answering a frame that awaits no
    answer (a faulted one), is counted; a late one (not applied) and a SAFE one are not."""
    stats = RunStats(stale_answer_age_s=0.01)
    stats.on_sensor_sent(Frame(SENSORS_ID, b"", 0, True), 0.000, 0.000)
    stats.on_command(0, 0.001, applied=True)  # 1 ms: fine
    stats.on_sensor_sent(Frame(SENSORS_ID, b"", 1, True), 0.002, 0.002)
    stats.on_command(1, 0.014, applied=True)  # applied 12 ms after its frame left
    stats.on_sensor_sent(Frame(SENSORS_ID, b"", 2, True), 0.016, 0.016)
    stats.on_command(2, 0.040)  # as late: not applied
    stats.on_sensor_sent(Frame(SENSORS_ID, b"", 3, False), 0.042, 0.042)  # faulted frame
    stats.on_command(3, 0.043, applied=True)
    stats.on_command(3, 0.0435, safe=True)
    assert (stats.active_applied_stale, stats.active_applied_invalid) == (1, 1)
    assert list(stats.applied_active_age_us) == pytest.approx([1000.0, 12000.0])


def test_the_loop_counts_as_applied_only_the_active_commands_the_firmware_did_not_drop():
    """The runner's receive path: the firmware is told when each frame left; an ACTIVE answer
    to the frame before the latest is late (dropped, counted by the firmware, not applied)."""
    fw = Firmware(SimConfig(), contract_profile())
    stats = RunStats(stale_answer_age_s=0.01)
    packer = CODEC.packer("DAEMON")
    damper_id = CODEC.layout("DamperCommand").frame_id

    def command(echo: int, t_s: float) -> None:
        msg = packer.message(
            "DamperCommand",
            {"Mode": "ACTIVE", "CurrentSetpoint": 1.0, "SensorCounterEcho": echo,
             "ControllerId": 1, "DesiredForce": 0.0},
        )  # fmt: skip
        _receive(fw, stats, msg, t_s, damper_id)

    sent = []
    for k in range(3):
        (frame,) = [f for f in fw.tick(0.002 * k) if f.frame_id == SENSORS_ID]
        fw.sent(frame, 0.002 * k)
        stats.on_sensor_sent(frame, 0.002 * k, 0.002 * k)
        sent.append(frame)
    command(sent[1].counter, 0.0045)  # the frame before the latest: late
    command(sent[2].counter, 0.0046)  # the latest: applied
    assert fw.late_commands == 1
    assert list(stats.applied_active_age_us) == pytest.approx([600.0])
    stats.finish()  # the late command still answers its frame, once
    assert (stats.answered_once, stats.unanswered, stats.active_applied_stale) == (2, 1, 0)


def test_run_stats_match_answers_in_turn_through_a_stall_longer_than_the_counter_wraps():
    # two frames answered at once, then a 36 ms stall: frames 2..19 leave (counters 2 and 3
    # twice) before their answers come, in order; a newest-first match would take the answer
    # to frame 2 for frame 18's and count frame 18 answered twice
    stats = RunStats()
    frames = [Frame(SENSORS_ID, b"", i % 16, True) for i in range(20)]
    for i in range(2):
        stats.on_sensor_sent(frames[i], 0.002 * i, 0.002 * i)
        stats.on_command(i, 0.002 * i + 0.0003)
    for i in range(2, 20):
        stats.on_sensor_sent(frames[i], 0.002 * i, 0.002 * i)
    for i in range(2, 20):
        stats.on_command(i % 16, 0.040 + 1e-5 * i)
    stats.finish()
    assert (stats.answered_once, stats.unanswered, stats.answered_more_than_once) == (20, 0, 0)
    assert stats.unmatched_answers == 0 and stats.answered_late == 17
    assert stats.latency_us[2] == pytest.approx(40020.0 - 4000.0)  # frame 2's own answer
    assert stats.latency_us[-1] == pytest.approx(40190.0 - 38000.0)


def test_run_stats_take_the_first_answer_after_a_silence_for_the_newest_frame():
    # the simulator streamed 100 ms before the daemon started: the daemon's first answer is
    # for the frame it received first, the newest with that counter, not 16 or 32 frames older
    stats = RunStats()
    for i in range(50):
        stats.on_sensor_sent(Frame(SENSORS_ID, b"", i % 16, True), 0.002 * i, 0.002 * i)
    stats.on_command(49 % 16, 0.0985)
    stats.finish()
    assert (stats.answered_once, stats.unanswered, stats.answered_late) == (1, 49, 0)
    assert list(stats.latency_us) == pytest.approx([500.0])


def test_run_stats_a_frame_sent_late_marks_a_window_of_the_simulator_and_is_not_on_time():
    stats = RunStats()
    frames = [Frame(SENSORS_ID, b"", c, True) for c in range(4)]
    stats.on_sensor_sent(frames[0], 0.000, 0.0001)
    stats.on_sensor_sent(frames[1], 0.002, 0.0300)  # held up 28 ms: the process did not run
    stats.on_sensor_sent(frames[2], 0.004, 0.0302)  # catching up, still late: same window
    stats.on_sensor_sent(frames[3], 0.032, 0.0321)  # on time again
    for c, t in ((0, 0.0005), (1, 0.0304), (2, 0.0306), (3, 0.0325)):
        stats.on_command(c, t)
    stats.finish()
    assert stats.stall_windows == [["simulator", 0.0001, 0.0302]]
    assert stats.on_time == {"frames": 2, "answered_once": 2, "unanswered": 0, "more_than_once": 0}
    assert stats.answered_once == 4


def test_run_stats_a_late_echo_of_its_own_frame_marks_a_window_of_the_transport():
    stats = RunStats(measure_echo=True)
    for i in range(3):
        stats.on_sensor_sent(Frame(SENSORS_ID, b"", i, True), 0.002 * i, 0.002 * i)
    stats.on_echo(0, 0.0003)
    stats.on_echo(1, 0.0250)  # the bridge held it 23 ms
    stats.on_echo(2, 0.0251)
    assert stats.stall_windows == [["transport", 0.002, 0.0251]]
    assert list(stats.echo_us) == pytest.approx([300.0, 23000.0, 21100.0])


def test_sim_streams_sensors_at_500_hz_answers_are_matched_watchdog_trips_and_sigterm_exits_0(
    bridge, tmp_path
):
    url, _ = bridge
    proc = start_sim(url, tmp_path)
    bus = open_bus("remote", url)
    try:
        wait_first_sensor_frame(bus, proc)
        parser = CODEC.parser()
        packer = CODEC.packer("DAEMON")
        sensor_counters: list[int] = []
        statuses: list[dict[str, float]] = []
        commands_sent = 0
        t_start = time.monotonic()
        while time.monotonic() - t_start < 3.0:
            msg = bus.recv(0.1)
            if msg is None:
                continue
            parsed = parser.parse_message(msg)
            assert parsed.ok, parsed.reason
            if msg.arbitration_id == SENSORS_ID:
                sensor_counters.append(parsed.counter)
                bus.send(
                    packer.message(
                        "DamperCommand",
                        {
                            "Mode": "ACTIVE",
                            "CurrentSetpoint": 1.0,
                            "SensorCounterEcho": parsed.counter,
                            "ControllerId": 1,
                            "DesiredForce": 500.0,
                        },
                    ),
                    timeout=0.01,
                )
                commands_sent += 1
            elif msg.arbitration_id == STATUS_ID:
                statuses.append(parsed.values)
        elapsed_s = time.monotonic() - t_start
        last_command_s = time.monotonic()

        steps = {(b - a) % 16 for a, b in zip(sensor_counters, sensor_counters[1:], strict=False)}
        assert steps == {1}, "RigSensors counters not consecutive"
        rate_hz = len(sensor_counters) / elapsed_s
        assert 400.0 < rate_hz < 600.0
        assert 50 * len(statuses) == pytest.approx(len(sensor_counters), abs=100)
        assert any(s["State"] == 2 and s["FaultCode"] == 0 for s in statuses)  # RUNNING
        # a stall of the VM may already have tripped the watchdog while we answered
        timeouts_before = statuses[-1]["CommandTimeouts"]

        # stop answering: the watchdog must show in RigStatus within 20 ms + a status period
        tripped_after_s = None
        while time.monotonic() - last_command_s < 1.0:
            msg = bus.recv(0.1)
            if msg is None or msg.arbitration_id != STATUS_ID:
                continue
            values = parser.parse_message(msg).values
            if values["State"] == 3 and values["CommandTimeouts"] > timeouts_before:
                tripped_after_s = time.monotonic() - last_command_s
                assert values["FaultCode"] == 1
                timeouts_after = values["CommandTimeouts"]
                # decaying from the 1 A setpoint (coil lag ~5 ms: the status that reports the
                # trip may come a ms after it); the next status, 100 ms on, has it at 0 A
                assert values["CoilCurrent"] < 1.0
                coil_a = next(
                    parser.parse_message(m).values["CoilCurrent"]
                    for m in iter(lambda: bus.recv(0.5), None)
                    if m.arbitration_id == STATUS_ID
                )
                assert coil_a < 0.01, coil_a
                break
        print(
            f"\nsensor rate {rate_hz:.1f} Hz; watchdog seen in RigStatus after {tripped_after_s} s"
        )
        # 20 ms watchdog + one status period + slack for the bridge on a busy VM
        assert tripped_after_s is not None and tripped_after_s < 0.020 + 0.100 + 0.150
    finally:
        bus.shutdown()
        rc = stop_sim(proc)
    assert rc == 0
    stats = json.loads((tmp_path / "stats.json").read_text())
    print(
        "simulator stats:",
        json.dumps(
            {
                k: stats[k]
                for k in ("answers", "answer_latency_us", "period_jitter_us", "cpu_fraction")
            }
        ),
    )
    assert stats["commands"]["damper_valid"] == commands_sent
    assert stats["commands"]["bad_crc"] == stats["commands"]["repeated_counter"] == 0
    answers = stats["answers"]
    assert answers["answered_more_than_once"] == 0
    # every command answers its own frame once (answered_late: after the next frame had gone)
    assert answers["answered_once"] + answers["unmatched"] == commands_sent
    assert answers["answered_once"] > 0.5 * commands_sent
    assert stats["watchdog_trips"] == timeouts_after
    assert stats["max_commanded_current_a"] == pytest.approx(1.0)


def test_sim_applies_command_line_fault_and_stops_after_duration(bridge, tmp_path):
    url, _ = bridge
    proc = start_sim(url, tmp_path, "--duration", "3", "--fault", "estop@1.0:0.5")
    bus = open_bus("remote", url)
    parser = CODEC.parser()
    estop_frames = 0
    try:
        wait_first_sensor_frame(bus, proc)
        while proc.poll() is None:
            msg = bus.recv(0.1)
            if msg is not None and msg.arbitration_id == SENSORS_ID:
                estop_frames += parser.parse_message(msg).values["EStop"]
        assert proc.wait(5.0) == 0
    finally:
        bus.shutdown()
        if proc.poll() is None:
            stop_sim(proc)
    assert estop_frames == pytest.approx(0.5 / 0.002, abs=5)
    events = [e["event"] for e in json.loads((tmp_path / "stats.json").read_text())["fault_events"]]
    assert "fault injection estop starts" in events and "fault injection estop ends" in events


def test_sim_exits_non_zero_with_one_error_line_when_the_bridge_dies(bridge, tmp_path):
    url, bridge_proc = bridge
    proc = start_sim(url, tmp_path)
    bus = open_bus("remote", url)
    try:
        wait_first_sensor_frame(bus, proc)
    finally:
        bus.shutdown()
    stop_bridge(bridge_proc)
    try:
        rc = proc.wait(5.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert rc == 1
    errors = [ln for ln in (tmp_path / "sim.log").read_text().splitlines() if " ERROR " in ln]
    assert len(errors) == 1 and "CAN bus error" in errors[0]
    assert (tmp_path / "stats.json").exists()
