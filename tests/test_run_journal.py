"""Issue 40, findings 6 and 13: runs are never lost, and a crashed run is never `ok`.

The sidecar is a real process (recording only, no Zenoh) that the test feeds as the daemon's
loop does: samples, the summary (or none: the daemon killed), STOP or EOF. Its catalog is
locked by another process holding an exclusive transaction, or is a corrupt file: the run is
journalled beside its recording, then registered by `mrrig runs` or by the next run's
registration. `mrrig runs register REC` registers a run from the identity the recording
carries, once."""

from __future__ import annotations

import datetime as dt
import json
import subprocess
import sys
import threading
import uuid
from pathlib import Path

import numpy as np
import pytest

from mrrig.catalog import find_runs
from mrrig.catalog.finished import verdict_of
from mrrig.catalog.store import open_catalog
from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.rigio.ipc import LoopEnd, make_channel
from mrrig.rigio.run_identity import file_sha256
from mrrig.rigio.sidecar_process import start_sidecar
from tests.conftest import REPO
from tests.rig_harness import ScriptedRig

pytestmark = pytest.mark.process

RIG = "journalrig"
MRRIG = [sys.executable, "-m", "mrrig"]
# another process's exclusive transaction on the catalog, held until its stdin closes
LOCKER = """
import sqlite3, sys
db = sqlite3.connect(sys.argv[1], isolation_level=None)
db.execute("BEGIN EXCLUSIVE")
db.execute("SELECT count(*) FROM runs").fetchall()
print("locked", flush=True)
sys.stdin.read()
"""


def identity(catalog: Path | None) -> dict:
    """A run's identity as `mrrig.rigio.run_identity.run_identity` makes it."""
    return {
        "run_id": str(uuid.uuid4()),
        "rig": RIG,
        "host": "bench",
        "specimen": "SN-7",
        "operator": "alice",
        "tags": [],
        "started_utc": dt.datetime.now(dt.UTC).isoformat(),
        "controller": "constant",
        "controller_params": {"current_a": 0.5},
        "model_path": None,
        "model_sha256": None,
        "config_sha256": None,
        "dbc_sha256": file_sha256(REPO / "configs" / "mrrig.dbc"),
        "mrrig_version": "test",
        "catalog": str(catalog) if catalog is not None else None,
        "catalog_spool": None,
    }


def samples(n: int = 200) -> np.ndarray:
    arr = np.zeros(n, SAMPLE_DTYPE)
    arr["t"] = np.arange(n) * 0.002
    arr["counter"] = np.arange(n) % 16
    arr["state"] = RigState.ARMED
    return arr


def sidecar_run(capfd, rrd: Path, ident: dict, summary: dict | None) -> str:
    """One run through a real sidecar process; its log (`capfd`: the process writes to this
    one's stderr). `summary` None: the loop ends without one (EOF, as a killed daemon's)."""
    capfd.readouterr()
    fds = make_channel()
    loop = LoopEnd(*fds.loop_fds())
    proc = start_sidecar(RIG, None, fds, record=rrd, identity=ident)
    try:
        loop.send_samples(samples())
        if summary is not None:
            loop.send_summary(summary)
            loop.send_stop()
    finally:
        loop.close()  # EOF
    rc = proc.wait(timeout=60)
    err = capfd.readouterr().err
    assert rc == 0, err
    return err


def runs_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*MRRIG, "runs", *args], capture_output=True, text=True, timeout=120)


SUMMARY = {"exit_code": 0, "et": 0.02, "faults": [], "latency_us": {"p50": 50.0, "p99": 90.0}}


def test_a_run_whose_catalog_is_locked_is_journalled_then_registered_by_mrrig_runs(tmp_path, capfd):
    catalog, rrd = tmp_path / "catalog.sqlite", tmp_path / "run.rrd"
    open_catalog(catalog)
    locker = subprocess.Popen(
        [sys.executable, "-c", LOCKER, str(catalog)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert locker.stdout.readline() == "locked\n"
        ident = identity(catalog)
        log = sidecar_run(capfd, rrd, ident, SUMMARY)
        assert f"run {ident['run_id']} not registered" in log and "database is locked" in log
        assert f"journalled in {rrd}.journal" in log, log
        journal = json.loads(Path(f"{rrd}.journal").read_text())
        assert journal["run"]["run_id"] == ident["run_id"] and journal["catalog"] == str(catalog)
        assert find_runs(catalog) == []  # a reader is not blocked: the run is not there
    finally:
        locker.stdin.close()
        locker.wait(timeout=10)
    listed = runs_cli("--catalog", str(catalog), "--json")
    assert listed.returncode == 0, listed.stderr
    assert "note: 1 journalled run registered" in listed.stderr
    (run,) = json.loads(listed.stdout)
    assert (run["run_id"], run["verdict"], run["et"]) == (ident["run_id"], "ok", 0.02)
    assert run["recording_sha256"] == file_sha256(rrd)
    assert not Path(f"{rrd}.journal").exists()
    again = runs_cli("--catalog", str(catalog), "--json")  # replayed once
    assert len(json.loads(again.stdout)) == 1 and "journalled" not in again.stderr


def test_a_run_whose_catalog_is_corrupt_is_journalled_then_registered_by_the_next_run(
    tmp_path, capfd
):
    catalog = tmp_path / "catalog.sqlite"
    catalog.write_bytes(b"this is not a database " * 200)
    first, second = identity(catalog), identity(catalog)
    log = sidecar_run(capfd, tmp_path / "a.rrd", first, SUMMARY)
    assert "file is not a database" in log and "journalled in" in log, log
    assert Path(tmp_path / "a.rrd.journal").is_file()
    catalog.rename(tmp_path / "catalog.sqlite.corrupt")  # the operator puts it aside
    sidecar_run(capfd, tmp_path / "b.rrd", second, SUMMARY)  # the next run registers both
    assert {str(r.run_id) for r in find_runs(catalog)} == {first["run_id"], second["run_id"]}
    assert sorted(p.name for p in tmp_path.glob("*.journal")) == []


def test_runs_register_adds_the_run_a_recording_carries_once(tmp_path, capfd):
    catalog, rrd = tmp_path / "catalog.sqlite", tmp_path / "run.rrd"
    ident = identity(None)  # the run was never registered (catalog off, or its record lost)
    sidecar_run(capfd, rrd, ident, SUMMARY)
    assert not catalog.exists()
    out = runs_cli("register", str(rrd), "--catalog", str(catalog))
    assert out.returncode == 0, out.stderr
    short = ident["run_id"][:8]
    assert out.stdout == f"{rrd}: run {short} registered (verdict ok) in the catalog {catalog}\n"
    out = runs_cli("register", str(rrd), "--catalog", str(catalog))
    assert out.stdout == f"{rrd}: run {short} already there in the catalog {catalog}\n"
    (run,) = find_runs(catalog)
    assert (str(run.run_id), run.verdict, run.et, run.specimen) == (
        ident["run_id"],
        "ok",
        0.02,
        "SN-7",
    )
    assert run.recording_sha256 == file_sha256(rrd)
    bad = runs_cli("register", str(tmp_path / "none.rrd"), "--catalog", str(catalog))
    assert bad.returncode == 2 and bad.stderr.startswith("error: ") and bad.stderr.count("\n") == 1


# finding 13: a run whose daemon crashed is not catalogued `ok`


def test_a_run_whose_daemon_sent_no_summary_is_registered_crashed(tmp_path, capfd):
    catalog, rrd = tmp_path / "catalog.sqlite", tmp_path / "run.rrd"
    ident = identity(catalog)
    log = sidecar_run(capfd, rrd, ident, None)  # the daemon killed: EOF, no summary
    assert "the daemon ended without a summary" in log
    (run,) = find_runs(catalog)
    assert str(run.run_id) == ident["run_id"] and run.verdict == "crashed"
    # and from its recording, which has no summary either
    other = tmp_path / "other.sqlite"
    out = runs_cli("register", str(rrd), "--catalog", str(other))
    assert "registered (verdict crashed)" in out.stdout, out.stdout + out.stderr


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_daemon_that_raises_in_its_loop_sends_a_summary_that_is_not_ok(tmp_path, capfd):
    rig = ScriptedRig(tmp_path)
    answer, failed, frames = rig.daemon.on_frame, threading.Event(), []

    def broken(*args) -> None:  # a bug in the frame path, on the third frame
        frames.append(args)
        if len(frames) == 3:
            failed.set()
            raise RuntimeError("a bug in the loop")
        answer(*args)

    rig.daemon.on_frame = broken
    with rig:
        for _ in range(3):
            rig.sensors()
            rig.bus.recv(timeout=1)  # its answer
        assert failed.wait(10)
        rig.thread.join(timeout=10)
    summary = rig.daemon.summary
    assert summary["crashed"] == "RuntimeError: a bug in the loop"
    assert summary["exit_code"] == 0  # what the exit code alone says: hence `crashed`
    assert verdict_of(summary) == "crashed"
    catalog, rrd = tmp_path / "catalog.sqlite", tmp_path / "run.rrd"
    ident = identity(catalog)
    sidecar_run(capfd, rrd, ident, {k: v for k, v in summary.items() if k != "latency_split_us"})
    (run,) = find_runs(catalog)
    assert run.verdict == "crashed"
    assert {"fault": "crashed", "reason": "RuntimeError: a bug in the loop"} in run.faults
