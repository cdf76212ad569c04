"""Issue 23's findings about the parts that run as processes, one test (or a few) each: the
telemetry sidecar's answers to hostile requests, failing recordings, a killed sidecar or
bridge (a process module: the loop's findings, stepped frame by frame in a thread, are
tests/test_hostile_input.py's, which hold the machine shared)."""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mrrig.cli.review import main as review_main
from mrrig.loop.safety import Fault
from mrrig.loop.samples import RigState
from mrrig.offline.review import ReviewError
from mrrig.rigio.client import query
from mrrig.rigio.ipc import LoopEnd, Msg, make_channel
from mrrig.rigio.rig_topics import keys
from tests.conftest import REPO, rig_config, wait_until
from tests.rig_harness import ScriptedRig
from tests.test_hostile_input import SAFE
from tests.test_sidecar import RIG, _samples, running_sidecar


# ---- 1. one request kills the control plane ------------------------------------------------
@pytest.mark.process
def test_finding1_a_deeply_nested_request_gets_an_error_and_the_sidecar_lives(tmp_path):
    nested = '{"cmd": "status", "x": ' + "[" * 1000 + "]" * 1000 + "}"
    with running_sidecar(tmp_path) as r:
        replies = list(r.observer.get(keys(RIG)["control"], payload=nested, timeout=3.0))
        reply = json.loads(replies[0].ok.payload.to_bytes())
        assert reply == {"ok": False, "error": "request nested deeper than 4 levels"}
        # still serving: a valid request goes on to the loop
        list(r.observer.get(keys(RIG)["control"], payload='{"cmd": "arm"}', timeout=0.2))
        request_id, raw = r.poll_until(Msg.REQUEST)
        assert json.loads(raw) == {"cmd": "arm"}
        assert r.proc.poll() is None


# ---- 5. request bursts: the sidecar answers status itself ----------------------------------
@pytest.mark.process
def test_finding5_status_requests_are_answered_by_the_sidecar_not_the_loop(tmp_path):
    with running_sidecar(tmp_path) as r:
        for k in range(50):
            # as the loop sends it, every 0.1 s
            r.loop.send_status({"state": "ARMED", "armed": True, "frames_received": k})
            time.sleep(0.02)
            reply = query(r.observer, RIG, {"cmd": "status"}, 2.0)
            assert reply["ok"] and reply["status"]["state"] == "ARMED", reply
        assert [m for m, _ in r.loop.poll() if m == Msg.REQUEST] == []


@pytest.mark.process
def test_finding5_more_requests_in_flight_than_allowed_get_busy_but_disarm_goes_on(tmp_path):
    with running_sidecar(tmp_path) as r:
        control = keys(RIG)["control"]
        pending = [
            r.observer.get(control, payload='{"cmd": "arm"}', timeout=3.0) for _ in range(12)
        ]
        disarm = r.observer.get(control, payload='{"cmd": "disarm"}', timeout=3.0)
        errors = [json.loads(next(iter(p)).ok.payload.to_bytes())["error"] for p in pending]
        assert errors.count("busy: 8 requests in flight") == 4, errors
        assert errors.count("daemon did not answer") == 8
        assert json.loads(next(iter(disarm)).ok.payload.to_bytes())["error"] == (
            "daemon did not answer"  # forwarded, though 8 were in flight
        )


# ---- 6. failures silent or misreported -----------------------------------------------------
@pytest.mark.process
def test_finding6_a_one_megabyte_request_gets_an_error_reply(tmp_path):
    big = json.dumps({"cmd": "status", "pad": "x" * 1_000_000})
    with running_sidecar(tmp_path) as r:
        replies = list(r.observer.get(keys(RIG)["control"], payload=big, timeout=3.0))
        reply = json.loads(replies[0].ok.payload.to_bytes())
        assert reply["ok"] is False
        assert reply["error"].startswith("request too large: 1000028 bytes (limit 2048)")


def _limited_sidecar(path: Path, fsize: int) -> tuple[subprocess.Popen, LoopEnd]:
    """A recording-only sidecar process whose files may not grow past `fsize` bytes: a full
    disk as the writer sees it (EFBIG on write)."""
    fds = make_channel()
    loop = LoopEnd(*fds.loop_fds())
    cmd = [sys.executable, "-m", "mrrig.rigio.sidecar_process", "--rig", RIG, "--zenoh-config", ""]
    cmd += ["--record", str(path), "--rx-fd", str(fds.sidecar_rx), "--tx-fd", str(fds.sidecar_tx)]

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

    proc = subprocess.Popen(cmd, pass_fds=fds.sidecar_fds(), preexec_fn=limit, cwd=REPO)
    os.close(fds.sidecar_rx)
    os.close(fds.sidecar_tx)
    return proc, loop


@pytest.mark.process
def test_finding6_a_recording_that_cannot_be_written_is_reported_and_review_says_so(tmp_path):
    path = tmp_path / "run.rrd"
    proc, loop = _limited_sidecar(path, 200_000)
    try:
        notice = None
        end = time.monotonic() + 60
        k = 0
        while time.monotonic() < end:
            batch = _samples(40)
            batch["t"] = k * 0.08 + batch["t"] - batch["t"][0]
            k += 1
            loop.send_samples(batch)
            time.sleep(0.01)
            got = [p for m, p in loop.poll() if m == Msg.NOTICE]
            if got:
                notice = got[0]
                break
        assert notice is not None, "no recording_failed notice"
        assert notice["kind"] == "recording_failed"
        assert "truncated" in notice["reason"] and str(path) in notice["reason"]
        assert proc.poll() is None  # telemetry goes on
        loop.send_stop()
        assert proc.wait(timeout=15) == 0
    finally:
        loop.close()
        if proc.poll() is None:
            proc.kill()
    try:
        rc = review_main([str(path)])
    except ReviewError as exc:  # cut where nothing can be read: the CLI's error line, exit 2
        assert "truncated" in str(exc)
    else:
        assert rc == 1  # readable, but without its end-of-run summary
        assert review_main([str(path), "--partial"]) == 0


@pytest.mark.process
def test_finding6_the_loop_faults_when_its_recording_fails(tmp_path):
    # the telemetry process the daemon starts inherits a file size limit of 200 kB: its
    # writes then fail as on a full disk (the limit is this process's only while it starts)
    old_limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, old_limit[1]))
    try:
        rig = ScriptedRig(tmp_path, timeout_periods=500, record_path=tmp_path / "run.rrd")
        rig.__enter__()
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, old_limit)
        signal.signal(signal.SIGXFSZ, old_handler)
    try:
        end = time.monotonic() + 60
        while rig.daemon.supervisor.fault is not Fault.RECORDING_FAILED:
            assert time.monotonic() < end, rig.daemon.events[-3:]
            rig.exchange()
        assert rig.exchange()["Mode"] == SAFE
        assert rig.daemon.status()["recording"].startswith("failed: ")
        assert "truncated" in rig.daemon.supervisor.reason
    finally:
        rig.__exit__(None, None, None)


@pytest.mark.process
def test_finding6_a_killed_sidecar_is_a_fault_restarted_once_then_the_daemon_stops(tmp_path):
    rig = ScriptedRig(
        tmp_path,
        timeout_periods=500,  # starting a process of this test's size holds the loop up
        overrides={"telemetry": {"heartbeat_timeout_s": 0.5}, "loop": {"max_frame_age_s": 1.0}},
        record_path=tmp_path / "run.rrd",
    )
    with rig:
        wait_until(lambda: rig.exchange() and rig.daemon.sidecar.link is not None)
        first = rig.daemon.sidecar.proc
        first.kill()
        while rig.daemon.supervisor.fault is not Fault.TELEMETRY_LOST:
            rig.exchange()
        assert "telemetry process exited" in rig.daemon.supervisor.reason
        assert rig.exchange()["Mode"] == SAFE
        # restarted once, into a file of its own
        wait_until(lambda: rig.exchange() and rig.daemon.sidecar.proc is not first, 30.0)
        assert rig.daemon.sidecar.record_paths[-1].name == "run.restart1.rrd"
        assert rig.request({"cmd": "reset"})["ok"]  # the fault acknowledged, then armed
        assert rig.request({"cmd": "arm"})["ok"]
        # a stopped (stuck) one: no heartbeat for 0.5 s is the same fault
        second = rig.daemon.sidecar.proc
        wait_until(lambda: rig.exchange() and rig.daemon.sidecar.link is not None, 30.0)
        end = time.monotonic() + 2.0  # its first heartbeats come
        while time.monotonic() < end:
            rig.exchange()
        os.kill(second.pid, signal.SIGSTOP)
        try:
            while rig.thread.is_alive() and rig.daemon.supervisor.state is RigState.ARMED:
                rig.exchange()
            assert "no heartbeat" in rig.daemon.supervisor.reason
        finally:
            os.kill(second.pid, signal.SIGCONT)
        rig.thread.join(timeout=20)
        assert not rig.thread.is_alive()
    assert rig.daemon.exit_code == 4


@pytest.mark.process
def test_finding6_a_killed_bridge_ends_mrrig_run_with_exit_code_3(tmp_path, sim_model):
    from mrrig.rigio.canbus.bus import find_free_port, start_bridge

    port = find_free_port()
    bridge = start_bridge(port)
    cfg = rig_config(tmp_path, f"ws://127.0.0.1:{port}/", sim_model)
    daemon = subprocess.Popen(
        [sys.executable, "-m", "mrrig", "run", "--config", str(cfg)],
        cwd=REPO,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        time.sleep(4.0)
        assert daemon.poll() is None
        bridge.kill()
        bridge.wait()
        _, err = daemon.communicate(timeout=30)
    finally:
        if daemon.poll() is None:
            daemon.kill()
        if bridge.poll() is None:
            bridge.kill()
    assert daemon.returncode == 3, err[-2000:]
    assert "remote CAN bus" in err and "exit code 3" in err


# ---- 7. values that should be refused ------------------------------------------------------
@pytest.mark.process
def test_finding7_nan_over_zenoh_is_named_not_taken_for_none(tmp_path):
    with running_sidecar(tmp_path) as r:
        payload = '{"cmd": "set_profile", "kind": "sine", "amplitude_n": NaN}'
        replies = list(r.observer.get(keys(RIG)["control"], payload=payload, timeout=3.0))
        reply = json.loads(replies[0].ok.payload.to_bytes())
        assert reply == {
            "ok": False,
            "error": "amplitude_n: not a finite number (NaN and Infinity are refused)",
        }
