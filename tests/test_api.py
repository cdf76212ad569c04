"""The Python API (mrrig.api): Recording and runs() on real files, Rig against a live daemon and
firmware_sim as processes (telemetry, arm/disarm, a streamed force profile, the session closed
on exit)."""

from __future__ import annotations

import datetime as dt
import subprocess
import sys
import textwrap
import time
import uuid

import numpy as np
import pytest

from mrrig.api import Recording, Rig, RigError, runs
from mrrig.catalog import RunRecord, register_run
from mrrig.loop.samples import SAMPLE_DTYPE
from mrrig.loop.summary import summarize
from mrrig.offline.review import read_recording
from tests.conftest import REPO
from tests.live_rig import live_rig
from tests.test_recording import run_events, synthetic_run, write_recording
from tests.test_send_force import _transport_only

RIG = "api"


def test_recording_gives_samples_events_summary_and_a_unit_named_frame(tmp_path):
    path = tmp_path / "rig1-20260101T120000Z.rrd"
    s = synthetic_run(800)
    events = run_events(s)
    write_recording(path, s, events, summarize(s, events, {"frames_received": 800}))
    rec = Recording(path)
    want = read_recording(path)
    assert len(rec) == 800 and rec.samples.dtype == SAMPLE_DTYPE
    for name in SAMPLE_DTYPE.names:
        assert np.array_equal(
            rec.samples[name], want.samples[name], equal_nan=name not in ("state", "counter")
        )
    assert rec.events == want.events and rec.summary["frames"] == 800
    frame = rec.to_pandas()
    assert list(frame.columns[:4]) == ["utc", "t_s", "counter", "x_m"]
    assert {"force_n", "xd_m_s", "i_cmd_a", "latency_us", "temp_degc"} <= set(frame.columns)
    assert np.array_equal(frame["force_n"].to_numpy(), s["f_meas"])
    t0_ns = int(dt.datetime(2026, 1, 1, 12, tzinfo=dt.UTC).timestamp()) * 1_000_000_000
    utc_ns = np.array([ts.value for ts in frame["utc"]])  # pandas Timestamps: ns
    assert np.array_equal(utc_ns, t0_ns + np.round(s["t"] * 1e9).astype(np.int64))


def test_runs_gives_the_catalogs_runs_filtered_as_a_frame(tmp_path):
    catalog = tmp_path / "catalog.sqlite"
    t0 = dt.datetime(2026, 3, 1, 9, tzinfo=dt.UTC)
    for n, (rig, et) in enumerate([("rig1", 0.02), ("rig2", 0.005), ("rig1", 0.004)]):
        register_run(
            catalog,
            RunRecord(
                run_id=uuid.uuid5(uuid.NAMESPACE_URL, f"api-{n}"),
                rig=rig,
                started_utc=t0 + dt.timedelta(hours=n),
                specimen="SN1234",
                et=et,
            ),
        )
    frame = runs(catalog, rig="rig1")
    assert list(frame["et"]) == [0.02, 0.004] and set(frame["rig"]) == {"rig1"}
    assert frame["started_utc"].iloc[1] == t0 + dt.timedelta(hours=2)
    assert list(runs(catalog, where="et < 0.01")["rig"]) == ["rig2", "rig1"]
    assert runs(catalog, since=t0 + dt.timedelta(minutes=90))["et"].tolist() == [0.004]


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """firmware_sim and a daemon (force reference `zenoh`, telemetry at 20 Hz); yields the
    client's Zenoh config."""
    tmp = tmp_path_factory.mktemp("api")
    reference = {"kind": "zenoh", "timeout_s": 0.1}
    record = ("--record", str(tmp / "r.rrd"))
    with live_rig(tmp, RIG, reference=reference, daemon_args=record) as live:
        yield live.client_z


def settled(r: Rig, state: str, timeout_s: float = 5.0) -> dict:
    """The status once in `state` (the sidecar answers with the daemon's last published one,
    which may lag a request by a status period)."""
    deadline = time.monotonic() + timeout_s
    while (status := r.status())["state"] != state and time.monotonic() < deadline:
        time.sleep(0.05)
    assert status["state"] == state, status
    return status


@pytest.mark.process
def test_rig_status_telemetry_arm_and_a_streamed_force(rig):
    with Rig(RIG, zenoh_config=rig) as r:
        assert r.status()["state"] == "IDLE"
        tele = r.telemetry(duration_s=1.0)
        batches = list(tele)
        assert len(batches) >= 5 and all(b.dtype == SAMPLE_DTYPE for b in batches)
        frame = tele.to_pandas()
        assert len(frame) == tele.samples.size > 200  # about 500 samples a second
        assert (np.diff(frame["t_s"].to_numpy()) > 0).all() and "force_n" in frame
        # utc: the run's start (sent with each batch) plus t_s, a wall clock of about now
        assert list(frame.columns[:2]) == ["utc", "t_s"]
        age_s = (dt.datetime.now(dt.UTC) - frame["utc"].iloc[-1]).total_seconds()
        assert 0 < age_s < 60, age_s
        # armed without a force reference: the daemon faults (stale reference); reset clears it
        assert r.arm()["ok"]
        assert settled(r, "FAULT")["fault"] == "stale_reference"
        with pytest.raises(RigError, match="arm"):
            r.arm()  # refused in FAULT: the daemon's error, as a RigError
        assert r.reset()["ok"]
        settled(r, "IDLE")
        # a generator of unknown length: streamed until it ends, then the ramp and disarm
        result = r.stream_force((200.0 for _ in range(30)), rate_hz=100.0, arm=True, ramp_s=0.2)
        if result.faults and _transport_only([f.split(":")[0] for f in result.faults]):
            pytest.skip(f"a transport fault (a machine stall) during the profile: {result.faults}")
        assert result.armed_by_us and result.disarmed and not result.faults
        assert result.sent == 30 + result.ramp_samples  # sent: the profile and the ramp
        assert result.ramp_samples == 20
        settled(r, "IDLE")
        assert r.disarm()["ok"]
        with pytest.raises(ValueError, match="finite"):
            r.stream_force([100.0, float("nan")])
    with pytest.raises(RigError, match="closed"):
        r.status()


@pytest.mark.process
def test_an_unclosed_rig_does_not_keep_the_interpreter_from_exiting(rig):
    code = textwrap.dedent(
        f"""
        from mrrig.api import Rig
        r = Rig({RIG!r}, zenoh_config={str(rig)!r})
        r.me = r  # in a reference cycle, left to the interpreter's end
        batches = iter(r.telemetry(duration_s=5.0))
        next(batches)  # a subscriber declared, mid-iteration
        print(r.status()["state"], flush=True)
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=30
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() in ("IDLE", "ARMED", "FAULT")


def test_the_module_lists_what_it_documents():
    """Issue 42: `dir(mrrig.api)` did not list `Rig` (nor the other names it loads on first
    use), and the docstring named a `RunRecord` the module did not give."""
    import re

    import mrrig.api as api

    doc = api.__doc__ or ""
    assert sorted(dir(api)) == sorted(api.__all__)
    for name in api.__all__:
        assert getattr(api, name) is not None
        assert re.search(rf"`{name}[`(]", doc), f"{name} is exported but not documented"
    classes = [getattr(api, n) for n in api.__all__ if isinstance(getattr(api, n), type)]
    # every name the docstring calls is the module's, or a method of one of its classes
    for called in set(re.findall(r"`(\w+)\(", doc)):
        assert hasattr(api, called) or any(hasattr(c, called) for c in classes), called
    for type_name in set(re.findall(r"`([A-Z]\w*)[`(]", doc)):
        assert type_name in api.__all__, type_name
