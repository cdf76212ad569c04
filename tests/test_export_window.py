"""`mrrig export --run ID` (a plan step's run: its rows only, found in the catalog) and
`--from/--until` (a time window on the recording's clock), read back with pyarrow."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from mrrig.api.catalog import register_run
from mrrig.export import META_KEY
from mrrig.rigio.recording import Recorder
from tests.test_lifecycle_errors import mrrig, one_error_line
from tests.test_recording import run_events, synthetic_run

T0 = dt.datetime(2026, 12, 6, 3, 0, 0, tzinfo=dt.UTC)


@pytest.fixture
def recorded(tmp_path: Path) -> tuple[Path, np.ndarray, list[dict]]:
    """A daemon's recording of 3 s (t 0.1-3.1 s) whose identity starts at T0."""
    path = tmp_path / "rig1-20261206T030000Z.rrd"
    s = synthetic_run(1500)
    events = run_events(s)
    identity = {"run_id": "d" * 32, "rig": "rig1", "started_utc": T0.isoformat()}
    with Recorder(path, "rig1", flush_interval_s=0.5, identity=identity) as rec:
        for k in range(0, s.size, 10):
            batch = s[k : k + 10]
            rec.add_samples(batch)
            for ev in events:
                if batch["t"][0] <= ev["t"] <= batch["t"][-1]:
                    extra = {k: v for k, v in ev.items() if k not in ("t", "level", "text")}
                    rec.add_event(ev["t"], ev["level"], ev["text"], **extra)
    return path, s, events


def test_a_run_of_the_catalog_exports_its_own_rows_only(recorded, tmp_path):
    path, s, events = recorded
    catalog = tmp_path / "catalog.sqlite"
    step = register_run(
        "rig1",
        T0 + dt.timedelta(seconds=1.0),
        ended_utc=T0 + dt.timedelta(seconds=2.0),
        catalog=catalog,
        recording=path,
        plan="campaign",
        step="sine 2 Hz",
    )
    out = tmp_path / "step.parquet"
    proc = mrrig(
        "export", "--run", str(step.run_id)[:8], "--catalog", str(catalog), "--to", "parquet",
        "--out", str(out),
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    table = pq.read_table(out)
    t = table.column("t_s").to_numpy()
    inside = s["t"][(s["t"] >= 1.0) & (s["t"] <= 2.0)]
    assert np.array_equal(t, inside) and 400 <= t.size <= 501
    meta = json.loads(table.schema.metadata[META_KEY.encode()])
    assert meta["identity"]["window"]["run"]["run_id"] == str(step.run_id)
    assert meta["identity"]["started_utc"] == T0.isoformat()  # the utc column's time zero
    utc = table.column("utc").to_numpy()
    assert utc[0] == np.datetime64(T0.replace(tzinfo=None)) + np.timedelta64(
        round(t[0] * 1e9), "ns"
    )
    assert all(1.0 <= ev["t"] <= 2.0 for ev in meta["events"])
    assert len(meta["events"]) < len(events)


def test_a_time_window_exports_its_rows_and_an_empty_one_is_one_error_line(recorded, tmp_path):
    path, s, _ = recorded
    out = tmp_path / "w.csv"
    proc = mrrig("export", str(path), "--to", "csv", "--out", str(out), "--from", "2.5")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"{(s['t'] >= 2.5).sum()} samples" in proc.stdout
    proc = mrrig("export", str(path), "--to", "csv", "--out", str(out), "--force",
                  "--from", "5", "--until", "6")  # fmt: skip
    assert "no sample between 5 s and 6 s (the recording has 0.100-3." in one_error_line(proc)


def test_a_run_outside_its_recording_or_unknown_is_one_error_line(recorded, tmp_path):
    path, _, _ = recorded
    catalog = tmp_path / "catalog.sqlite"
    late = register_run(
        "rig1", T0 + dt.timedelta(hours=1), catalog=catalog, recording=path, plan="p", step="s"
    )
    proc = mrrig("export", "--run", str(late.run_id), "--catalog", str(catalog), "--to", "csv",
                  "--out", str(tmp_path / "x.csv"))  # fmt: skip
    line = one_error_line(proc)
    assert f"run {late.run_id}" in line and "is not inside the recording" in line
    proc = mrrig("export", "--run", "abcdef12", "--catalog", str(catalog), "--to", "csv")
    assert "abcdef12" in one_error_line(proc)
