"""`mrrig export` and `mrrig review` of a real run: the daemon against firmware_sim, recorded,
exported to Parquet and MDF4 and read back by pyarrow and asammdf with the recording's values,
units and UTC (a process module: the formats' other checks, on a synthetic recording, are
tests/test_export.py's, which hold the machine shared)."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from asammdf import MDF

from mrrig.export import COLUMNS, META_KEY, UTC_COLUMN
from mrrig.offline.review import read_recording
from tests.conftest import rig_config, start, stop
from tests.test_export import UNITS, _same, _started, _utc_ns, export, mrrig
from tests.test_lifecycle_errors import NO_MODEL


@pytest.fixture(scope="module")
def real_run(tmp_path_factory) -> tuple[Path, object]:
    """A 3 s armed run of the daemon against firmware_sim, recorded, and its read-back."""
    from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge

    tmp = tmp_path_factory.mktemp("export")
    port = find_free_port()
    bridge = start_bridge(port)
    channel = f"ws://127.0.0.1:{port}/"
    sim = start(["-m", "firmware_sim", "--config", "configs/sim.toml", "-c", channel])
    try:
        cfg = rig_config(tmp, channel, None, **NO_MODEL)
        rrd = tmp / "rig1-run.rrd"
        proc = mrrig("run", "--config", str(cfg), "--duration", "3", "--arm", "--record", str(rrd))
        assert proc.returncode == 0, proc.stdout + proc.stderr
    finally:
        stop(sim)
        stop_bridge(bridge)
    return rrd, read_recording(rrd)


@pytest.mark.process
def test_parquet_reads_back_with_pyarrow_with_the_values_units_and_utc(real_run):
    rrd, rec = real_run
    assert rec.samples.size > 1000 and rec.identity  # 3 s at 500 Hz, with its identity
    table = pq.read_table(export(rrd, "parquet"))
    assert table.num_rows == rec.samples.size
    assert table.column_names == [UTC_COLUMN] + [c.name for c in COLUMNS]
    for c in COLUMNS:
        assert _same(table.column(c.name).to_numpy(), rec.samples[c.field]), c.name
        meta = table.schema.field(c.name).metadata
        assert meta[b"unit"].decode() == c.unit and meta[b"field"].decode() == c.field
    for name, unit in UNITS.items():
        assert table.schema.field(name).metadata[b"unit"].decode() == unit
    utc = table.column(UTC_COLUMN).cast("int64").to_numpy()
    assert np.array_equal(utc, _utc_ns(_started(rec), rec.samples["t"]))
    meta = json.loads(table.schema.metadata[META_KEY.encode()])
    assert meta["utc_source"] == "run identity started_utc"
    assert meta["identity"]["run_id"] == rec.identity["run_id"]
    assert meta["summary"]["frames"] == rec.summary["frames"]


@pytest.mark.process
def test_mf4_reads_back_with_asammdf_with_the_values_units_and_utc(real_run):
    rrd, rec = real_run
    mdf = MDF(export(rrd, "mf4"))
    try:
        assert mdf.header.start_time.astimezone(dt.UTC) == _started(rec)
        for c in COLUMNS[1:]:
            sig = mdf.get(c.name)
            assert sig.samples.size == rec.samples.size, c.name
            assert _same(sig.samples, rec.samples[c.field]), c.name
            assert sig.unit == c.unit and sig.comment == c.description, c.name
            assert _same(sig.timestamps, rec.samples["t"]), c.name
        for name, unit in UNITS.items():
            if name != "t_s":
                assert mdf.get(name).unit == unit
        assert mdf.groups[0].channels[0].name == "t_s"
        utc = mdf.get("utc_unix_s").samples
        expected = _utc_ns(_started(rec), rec.samples["t"]) / 1e9
        assert np.abs(utc - expected).max() < 1e-6  # float64 Unix seconds: to a microsecond
    finally:
        mdf.close()


@pytest.mark.process
def test_review_of_the_parquet_and_mf4_gives_the_metrics_of_the_rrd(real_run):
    rrd, _ = real_run
    metrics = {}
    for path in (rrd, rrd.with_suffix(".parquet"), rrd.with_suffix(".mf4")):
        if not path.exists():
            export(rrd, path.suffix[1:])
        out = path.with_suffix(path.suffix + ".json")
        proc = mrrig("review", str(path), "--json", str(out))
        assert proc.returncode == 0, proc.stdout + proc.stderr
        metrics[path.suffix] = json.loads(out.read_text())
    assert metrics[".rrd"]["frames"] > 1000
    assert "et" in metrics[".rrd"]
    assert metrics[".parquet"] == metrics[".rrd"]
    assert metrics[".mf4"] == metrics[".rrd"]
