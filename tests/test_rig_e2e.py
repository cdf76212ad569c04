"""The simulator and the daemon as separate processes over the python-can-remote bridge.

Each run is proved against the stalls the simulator measured and the daemon's own that the
kernel measured (`tests/stall_proof.py`): a fault that no measured stall explains fails the
test, whatever its reason.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mrrig.loop.realtime import WAKEUP_LATENCY_DEVICE
from mrrig.offline.review import read_recording
from tests.conftest import OutputWatch, holds_wakeup_latency, rig_config, stall
from tests.stall_proof import prove

pytestmark = pytest.mark.process


def run_rig(tmp_path: Path, bridge: str, procs, model: Path, duration_s: float, stop=None):
    """The daemon (armed, recording) first, then the simulator for `duration_s`; `stop` =
    (which: "simulator" or "daemon", after_s, for_s) holds that process up once, as the
    machine's scheduler would ("daemon-cpu": a busy process of a higher real-time priority
    on the daemon loop's CPU, the loop runnable behind it on the run queue). Returns
    (simulator stats, daemon summary, samples)."""
    cfg = rig_config(tmp_path, bridge, model)
    summary_path, rrd = tmp_path / "summary.json", tmp_path / "run.rrd"
    daemon = procs(
        ["-m", "mrrig", "run", "--config", str(cfg), "--arm", "--record", str(rrd),
         "--summary-json", str(summary_path)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    daemon_out = OutputWatch(daemon, "loop running")
    assert daemon_out.seen.wait(60), daemon_out.text()  # waiting for sensor frames
    if os.access(WAKEUP_LATENCY_DEVICE, os.W_OK):  # idle CPUs poll while its loop runs
        assert holds_wakeup_latency(daemon.pid) == 1, daemon_out.text()
    sim_stats = tmp_path / "sim.json"
    sim = procs(
        ["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge,
         "--measure-echo", "--stats", str(sim_stats), "--duration", str(duration_s)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    out = OutputWatch(sim, "rig firmware on")
    if stop is not None:
        which, after_s, for_s = stop
        assert out.seen.wait(30), out.text()  # streaming from now on
        time.sleep(after_s)
        if which == "daemon-cpu":
            occupy_cpu_of(daemon.pid, for_s)
        else:
            stall((sim if which == "simulator" else daemon).pid, for_s)
    assert sim.wait(timeout=60) == 0, out.text()
    out.join()
    print(out.text())
    daemon.send_signal(signal.SIGTERM)
    # exit code 1: it ended in FAULT, the sensor timeout once the simulator had stopped
    assert daemon.wait(timeout=30) == 1, daemon_out.text()
    daemon_out.join()
    st = json.loads(sim_stats.read_text())
    s = json.loads(summary_path.read_text())
    print(
        f"simulator: {st['sensor_frames_sent']} sensor frames, answers {st['answers']}, "
        f"on time {st['answers_on_time']}, watchdog trips {st['watchdog_trips']}, "
        f"answer latency {st['answer_latency_us']}"
    )
    print(
        f"daemon: Et {s['et']} over {s['armed_frames']} armed frames; latency {s['latency_us']}; "
        f"faults {s['faults']}"
    )
    faults = s["faults"]
    if faults and faults[-1]["reason"].startswith("no sensor frame"):
        # the simulator stopped first: the daemon's timeout after its last frame
        last_frame_t = st["clock_t0_s"] + duration_s - s["clock_t0_s"]
        if faults[-1]["t"] >= last_frame_t:
            faults = faults[:-1]
    return st, {**s, "faults": faults}, read_recording(rrd).samples


def occupy_cpu_of(pid: int, seconds: float) -> None:
    """Run a busy process for `seconds` on the CPU of `pid`'s main thread (the daemon's loop)
    at a SCHED_FIFO priority above its own: the loop waits on the run queue meanwhile."""
    (cpu,) = os.sched_getaffinity(pid)
    priority = os.sched_getparam(pid).sched_priority + 1
    busy = subprocess.run(
        [sys.executable, "-c", "import os, sys, time\n"
         f"os.sched_setaffinity(0, {{{cpu}}})\n"
         f"os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param({priority}))\n"
         f"end = time.monotonic() + {seconds}\n"
         "while time.monotonic() < end: pass"],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert busy.returncode == 0, busy.stderr


def test_ten_seconds_of_force_tracking_one_command_per_sensor_frame(
    tmp_path, bridge, procs, sim_model
):
    """Every sensor frame the simulator sent on time got exactly one valid command echoing its
    counter; every fault lies in a stall the simulator measured; Et outside them <= 0.1."""
    st, s, samples = run_rig(tmp_path, bridge, procs, sim_model, 10.0)
    assert st["sensor_frames_sent"] >= 4900
    assert st["max_commanded_current_a"] <= 2.0
    proof = prove(st, s["faults"], s["clock_t0_s"], samples, 0.1, s["kernel_stalls"])
    assert proof.et is not None


def test_a_stall_of_the_simulator_is_measured_and_explains_the_fault_it_causes(
    tmp_path, bridge, procs, sim_model
):
    """The simulator held up for 100 ms (SIGSTOP): the daemon faults (no sensor frame within
    its 20 ms timeout), the simulator measured the window, and the run is proved. The stall
    comes 2 s after arming: the daemon stays in FAULT after it, so Et is over those 2 s, not
    over the first second after arming alone (the controller's start)."""
    st, s, samples = run_rig(tmp_path, bridge, procs, sim_model, 6.0, stop=("simulator", 3.0, 0.1))
    proof = prove(st, s["faults"], s["clock_t0_s"], samples, 0.1, s["kernel_stalls"])
    assert proof.explained, s["faults"]
    assert any(w.kind == "simulator" and w.end_s - w.start_s >= 0.09 for w in proof.windows)


def test_a_fault_of_the_daemon_with_no_stall_of_the_simulator_fails_the_proof(
    tmp_path, bridge, procs, sim_model
):
    """The daemon held up for 60 ms: its commands stop, the firmware's watchdog trips and the
    daemon faults with a transport's reason; every frame still gets its one answer, late. The
    simulator and the bridge ran on time, and the daemon, stopped (SIGSTOP), neither waited on
    a run queue nor lost the time to the VM: no window explains the fault, the proof fails."""
    st, s, _ = run_rig(tmp_path, bridge, procs, sim_model, 5.0, stop=("daemon", 2.0, 0.06))
    assert s["faults"], "the daemon's stall faulted nothing"
    with pytest.raises(AssertionError, match="no measured stall explains"):
        prove(st, s["faults"], s["clock_t0_s"], kernel=s["kernel_stalls"])


def test_a_stall_of_the_daemon_on_its_run_queue_is_measured_by_the_kernel_and_explains_its_fault(
    tmp_path, bridge, procs, sim_model, capsys
):
    """A busy process above the loop's priority holds its CPU for 60 ms: the simulator ran on
    time and measured nothing, the daemon faults (a frame answered 60 ms old, the firmware's
    watchdog), and the kernel measured the loop's wait on the run queue: the proof attributes
    each fault to it and prints the figure; without the kernel's figures it fails."""
    st, s, samples = run_rig(
        tmp_path, bridge, procs, sim_model, 5.0, stop=("daemon-cpu", 2.0, 0.06)
    )
    assert s["faults"], "the daemon's stall faulted nothing"
    k = s["kernel_stalls"]
    assert k["measured"] and k["runq_max_ms"] >= 40.0, k
    proof = prove(st, s["faults"], s["clock_t0_s"], samples, 0.1, k)
    assert any(w.kind == "kernel" for _, w in proof.explained), proof.explained
    out = capsys.readouterr().out
    print(out)
    assert re.search(r"at t=[\d.]+ s: daemon waited [4-9]\d\.\d ms on the run queue", out), out
    with pytest.raises(AssertionError, match="no measured stall explains"):
        prove(st, s["faults"], s["clock_t0_s"])


def test_after_a_stall_of_the_daemon_no_stale_frame_is_answered_active(
    tmp_path, bridge, procs, sim_model
):
    """The daemon held up for 100 ms while armed (SIGSTOP): the frames that waited for it are
    answered SAFE, each once (the simulator counts no ACTIVE answer to a frame older than the
    configured age, 10 ms), the stall is a fault (stale_frame), and the summary's latency max,
    which includes the time a frame waited, shows it."""
    st, s, _ = run_rig(tmp_path, bridge, procs, sim_model, 5.0, stop=("daemon", 2.0, 0.1))
    a = st["answers"]
    assert st["stale_answer_age_s"] == 0.01
    assert a["active_to_stale"] == 0, a
    assert any("ms old when answered" in f["reason"] for f in s["faults"]), s["faults"]
    assert s["latency_us"]["max"] >= 90_000, s["latency_us"]
