"""Issue 32 (hostile input, round two), findings 4, 5 and 6: signals end a run as SIGTERM does,
a start-up that fails never touches the bus, and a stop is honoured within the spec's sensor
timeout whatever the config's. The simulator, the bridge and the daemons run as processes."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mrrig.offline.review import read_recording
from tests.conftest import REPO, OutputWatch, rig_config, zenoh_configs
from tests.stall_proof import explain

pytestmark = pytest.mark.process

SPEC_SENSOR_TIMEOUT_S = 3 * 0.002


def _sim(procs, bridge: str, stats: Path) -> subprocess.Popen:
    sim = procs(
        ["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge,
         "--measure-echo", "--stats", str(stats)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    out = OutputWatch(sim, "rig firmware on")
    assert out.seen.wait(30), out.text()
    return sim


def _sim_stats(sim: subprocess.Popen, stats: Path) -> dict:
    sim.send_signal(signal.SIGTERM)
    assert sim.wait(timeout=30) == 0
    return json.loads(stats.read_text())


def _daemon(procs, cfg: Path, *args: str) -> tuple[subprocess.Popen, OutputWatch]:
    daemon = procs(
        ["-m", "mrrig", "run", "--config", str(cfg), *args],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    out = OutputWatch(daemon, "loop running")
    assert out.seen.wait(60), out.text()
    return daemon, out


@pytest.mark.parametrize("signum", [signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2])
def test_finding4_a_signal_ends_an_armed_run_safe_with_its_summary(tmp_path, bridge, procs, signum):
    """SIGHUP (an ssh session that drops) and SIGUSR1 killed the daemon at once, its last
    command ACTIVE: no SAFE command, no actuator stop, no summary, the recording truncated."""
    stats = tmp_path / "sim.json"
    sim = _sim(procs, bridge, stats)
    cfg = rig_config(tmp_path, bridge, None, controller={"name": "constant", "current_a": 0.5})
    summary, rrd = tmp_path / "summary.json", tmp_path / "run.rrd"
    daemon, out = _daemon(procs, cfg, "--arm", "--record", str(rrd), "--summary-json", str(summary))
    time.sleep(2.0)  # armed after arm_settle_s
    daemon.send_signal(signum)
    rc = daemon.wait(timeout=30)
    out.join()
    st = _sim_stats(sim, stats)
    s = json.loads(summary.read_text())
    print(out.text()[-2000:])
    print(f"rc {rc}; stop_reason {s['stop_reason']}; faults {s['faults']}")
    assert s["stop_reason"] == signal.Signals(signum).name
    assert s["armed_frames"] > 0
    explained = explain(st, s["faults"], s["clock_t0_s"], s["kernel_stalls"])  # each measured
    assert rc == (1 if s["faults"] else 0), (rc, explained)
    rec = read_recording(rrd)
    assert rec.summary is not None and rec.summary["stop_reason"] == s["stop_reason"]
    events = [e["event"] for e in st["fault_events"]]
    print(events)
    assert not any("after ACTIVE commands" in e for e in events), events
    assert any("after SAFE commands" in e for e in events), events


def test_finding4_sigpipe_is_ignored(tmp_path):
    """SIGPIPE is the documented exception: a reader that went away is an error on that write,
    not a stop; the daemon runs on and stops on SIGTERM as ever."""
    cfg = tmp_path / "rig.toml"
    cfg.write_text(
        '[bus]\ninterface = "virtual"\nchannel = "sigpipe"\n[loop]\nrealtime = false\n'
        '[controller]\nname = "constant"\n'
    )
    daemon = subprocess.Popen(
        [sys.executable, "-m", "mrrig", "run", "--config", str(cfg), "--no-telemetry",
         "--no-record"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        out = OutputWatch(daemon, "loop running")
        assert out.seen.wait(60), out.text()
        daemon.send_signal(signal.SIGPIPE)
        time.sleep(0.5)
        assert daemon.poll() is None, out.text()
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=30) == 0, out.text()
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait()


def test_finding5_a_second_daemon_that_fails_to_start_leaves_the_running_rig_alone(
    tmp_path, bridge, procs
):
    """A second `mrrig run` of the same config (its Zenoh port taken) opened the bus and sent an
    ActuatorCommand STOP on its way out: the running daemon faulted (`foreign_command`), and a
    stray truncated recording was left. It now fails before it touches the bus."""
    stats = tmp_path / "sim.json"
    sim = _sim(procs, bridge, stats)
    zconf, _client, _port = zenoh_configs(tmp_path)
    cfg = rig_config(
        tmp_path,
        bridge,
        None,
        controller={"name": "constant", "current_a": 0.5},
        telemetry={"enabled": True, "zenoh_config": str(zconf)},
    )
    summary = tmp_path / "summary.json"
    first, out = _daemon(procs, cfg, "--arm", "--no-record", "--summary-json", str(summary))
    time.sleep(1.5)
    second_rrd = tmp_path / "second.rrd"
    second = subprocess.run(
        [sys.executable, "-m", "mrrig", "run", "--config", str(cfg), "--record",
         str(second_rrd)],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    print(second.stderr)
    assert second.returncode == 2, second.stderr
    assert second.stderr.strip().splitlines()[-1].startswith("error: "), second.stderr
    assert not second_rrd.exists(), "the failed start left a recording"
    time.sleep(0.5)
    first.send_signal(signal.SIGTERM)
    first.wait(timeout=30)
    out.join()
    st = _sim_stats(sim, stats)
    s = json.loads(summary.read_text())
    print(f"first daemon: faults {s['faults']}")
    assert not [f for f in s["faults"] if f["fault"] == "foreign_command"], s["faults"]
    explain(st, s["faults"], s["clock_t0_s"], s["kernel_stalls"])


def test_finding6_a_stop_is_honoured_within_the_spec_timeout_whatever_the_config(tmp_path):
    """timeout_periods = 500 (a 1 s sensor timeout, the most a config may set now; 1e8 made the
    daemon deaf to SIGTERM once the frames stopped): no frame comes, and the loop still ends
    within the spec's sensor timeout of the signal, plus the machine's scheduling."""
    cfg = tmp_path / "rig.toml"
    cfg.write_text(
        '[bus]\ninterface = "virtual"\nchannel = "deaf"\n[loop]\nrealtime = false\n'
        'timeout_periods = 500\n[controller]\nname = "constant"\n'
    )
    summary = tmp_path / "summary.json"
    daemon = subprocess.Popen(
        [sys.executable, "-m", "mrrig", "run", "--config", str(cfg), "--no-telemetry",
         "--no-record", "--summary-json", str(summary)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        out = OutputWatch(daemon, "loop running")
        assert out.seen.wait(60), out.text()
        time.sleep(0.3)
        t_signal = time.monotonic()
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=30) == 0, out.text()
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait()
    s = json.loads(summary.read_text())
    loop_end = s["clock_t0_s"] + s["loop_wall_s"]
    waited_s = loop_end - t_signal
    print(f"the loop ended {waited_s * 1e3:.1f} ms after SIGTERM (a 1 s configured timeout)")
    # the spec's 6 ms, and what a loaded 2-core machine adds to a wake-up; 1 to 2 s before
    assert waited_s < SPEC_SENSOR_TIMEOUT_S + 0.1
