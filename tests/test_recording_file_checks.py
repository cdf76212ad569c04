"""The recording's file is checked while it is written (issue 32, finding 7): `rm -rf` of the
recordings directory mid-run left the sidecar writing to an unlinked file, logging "recording
closed" with 5001 frames and exit 0, and nothing existed; the status's `recording` was null
even in a healthy run."""

from __future__ import annotations

import shutil
import time

import pytest

from mrrig.loop.safety import Fault
from mrrig.rigio.client import query
from mrrig.rigio.ipc import Msg
from tests.conftest import wait_until
from tests.rig_harness import ScriptedRig
from tests.test_sidecar import RIG, _samples, running_sidecar

pytestmark = pytest.mark.process
SAFE = 0  # DamperCommand Mode


def _feed(loop, k: int) -> int:
    """40 samples (80 ms of sensor time) after the `k` batches before; returns k + 1."""
    batch = _samples(40)
    batch["t"] = k * 0.08 + batch["t"] - batch["t"][0]
    loop.send_samples(batch)
    return k + 1


def test_the_status_shows_the_recording_and_a_removed_directory_is_a_recording_failed(tmp_path):
    path = tmp_path / "recordings" / "run.rrd"
    with running_sidecar(tmp_path, record=path) as r:
        k = 0
        end = time.monotonic() + 3.0  # past two of the sidecar's checks of the file
        while time.monotonic() < end:
            k = _feed(r.loop, k)
            time.sleep(0.02)
        r.loop.send_status({"state": "IDLE", "recording": None})
        time.sleep(0.1)
        recording = query(r.observer, RIG, {"cmd": "status"}, timeout_s=3.0)["status"]["recording"]
        assert recording["path"] == str(path)
        assert recording["frames"] > 0
        assert 0 < recording["bytes"] <= path.stat().st_size

        shutil.rmtree(path.parent)  # as `rm -rf recordings` did, the writer still writing
        notice = None
        end = time.monotonic() + 10.0
        while notice is None and time.monotonic() < end:
            k = _feed(r.loop, k)
            time.sleep(0.02)
            notice = next((p for m, p in r.loop.poll() if m == Msg.NOTICE), None)
        assert notice is not None, "no recording_failed notice for a removed recording"
        assert notice["kind"] == "recording_failed"
        assert str(path) in notice["reason"] and "gone" in notice["reason"], notice
        assert r.proc.poll() is None  # telemetry goes on
        r.loop.send_stop()
        assert r.proc.wait(timeout=15) == 0
    assert not path.exists()


def test_the_loop_faults_when_its_recordings_directory_is_removed(tmp_path):
    path = tmp_path / "recordings" / "run.rrd"
    with ScriptedRig(tmp_path, timeout_periods=500, record_path=path) as rig:
        assert wait_until(path.exists, timeout_s=10.0)
        shutil.rmtree(path.parent)
        end = time.monotonic() + 30
        while rig.daemon.supervisor.fault is not Fault.RECORDING_FAILED:
            assert time.monotonic() < end, rig.daemon.events[-3:]
            rig.exchange()
        assert rig.exchange()["Mode"] == SAFE
        assert rig.daemon.status()["recording"].startswith(f"failed: {path}: the file is gone")
