"""`mrrig export`: a recording as Parquet, CSV and MDF4, read back by pyarrow, pandas and
asammdf with the recording's values, units and sample count and an absolute UTC time; `mrrig
review` and the training/evaluate loader read the Parquet and MDF4 files back (on a synthetic
recording; a real run's export: tests/test_export_of_a_rig_run.py)."""

from __future__ import annotations

import datetime as dt
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from mrrig.export import COLUMNS, META_KEY, UTC_COLUMN, read_any
from mrrig.loop.samples import SAMPLE_DTYPE
from mrrig.loop.summary import summarize
from mrrig.offline.review import read_recording
from mrrig.offline.training.data import load_file
from tests.conftest import REPO
from tests.test_lifecycle_errors import one_error_line
from tests.test_recording import run_events, synthetic_run, write_recording

UNITS = {
    "t_s": "s",
    "x_m": "m",
    "xd_m_s": "m/s",
    "xdd_m_s2": "m/s^2",
    "force_n": "N",
    "f_des_n": "N",
    "f_model_n": "N",
    "i_cmd_a": "A",
    "i_meas_a": "A",
    "latency_us": "us",
    "temp_degc": "degC",
}


def mrrig(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mrrig", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def export(rrd: Path, fmt: str) -> Path:
    out = rrd.with_suffix(f".{fmt}")
    proc = mrrig("export", str(rrd), "--to", fmt, "--out", str(out), "--force")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"{out}: " in proc.stdout
    return out


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> tuple[Path, object]:
    """A recording without run identity, its name holding the recorder's UTC start."""
    path = tmp_path_factory.mktemp("export_syn") / "rig1-20260101T120000Z.rrd"
    s = synthetic_run(1500)
    events = run_events(s)
    write_recording(path, s, events, summarize(s, events, {"frames_received": 1500}))
    return path, read_recording(path)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))


def _started(rec) -> dt.datetime:
    return dt.datetime.fromisoformat(rec.identity["started_utc"]).astimezone(dt.UTC)


def _utc_ns(t0: dt.datetime, t: np.ndarray) -> np.ndarray:
    base = int(t0.timestamp()) * 1_000_000_000 + t0.microsecond * 1000
    return base + np.round(t * 1e9).astype(np.int64)


def test_csv_has_unit_named_columns_a_commented_preamble_and_the_values(synthetic, tmp_path):
    rrd, rec = synthetic
    csv = export(rrd, "csv")
    preamble = [line for line in csv.read_text().splitlines() if line.startswith("#")]
    assert any(line.startswith("# force_n [N]: load-cell force") for line in preamble)
    meta = json.loads(preamble[1].removeprefix(f"# {META_KEY}: "))
    assert meta["columns"]["xd_m_s"] == {"unit": "m/s", "field": "xd"}
    frame = pd.read_csv(csv, comment="#")
    assert list(frame.columns) == [UTC_COLUMN] + [c.name for c in COLUMNS]
    assert len(frame) == rec.samples.size
    for c in COLUMNS:
        assert _same(frame[c.name].to_numpy(), rec.samples[c.field]), c.name


def test_without_identity_the_utc_comes_from_the_file_name_and_says_so(synthetic):
    rrd, rec = synthetic
    assert rec.identity is None
    table = pq.read_table(export(rrd, "parquet"))
    meta = json.loads(table.schema.metadata[META_KEY.encode()])
    assert meta["utc_source"].startswith("file name")
    t0 = dt.datetime(2026, 1, 1, 12, 0, 0, tzinfo=dt.UTC)
    utc = table.column(UTC_COLUMN).cast("int64").to_numpy()
    assert np.array_equal(utc, _utc_ns(t0, rec.samples["t"]))


def test_the_training_and_evaluate_loader_reads_the_exports_as_the_rrd(synthetic):
    rrd, _ = synthetic
    want = load_file(rrd)
    for fmt in ("parquet", "mf4"):
        got = load_file(export(rrd, fmt))
        for name in ("t", "x", "xd", "xdd", "current", "force", "run_id"):
            assert _same(getattr(got, name), getattr(want, name)), (fmt, name)


def test_read_any_gives_the_recording_of_the_rrd(synthetic):
    rrd, rec = synthetic
    for fmt in ("parquet", "mf4"):
        back = read_any(export(rrd, fmt))
        assert back.samples.dtype == SAMPLE_DTYPE
        for name in SAMPLE_DTYPE.names:
            assert _same(back.samples[name], rec.samples[name]), (fmt, name)
        assert back.events == rec.events and back.identity == rec.identity
        assert json.dumps(back.summary) == json.dumps(rec.summary)


def test_a_parquet_file_of_another_tool_is_one_error_line(tmp_path):
    other = tmp_path / "other.parquet"
    pq.write_table(pa.table({"a": [1.0, 2.0]}), other)
    proc = mrrig("review", str(other))
    assert one_error_line(proc) == f"error: {other}: not an mrrig export (no 'mrrig' metadata)"


def test_export_onto_the_recording_itself_is_refused(synthetic, tmp_path):
    rrd, _ = synthetic
    parquet = export(rrd, "parquet")
    before = parquet.read_bytes()
    proc = mrrig("export", str(parquet), "--to", "parquet")
    assert proc.returncode == 2 and "is the recording itself" in proc.stderr
    assert parquet.read_bytes() == before


# issue 40, finding 7: `--out` overwrote the catalog and followed a symbolic link


def test_an_existing_out_is_refused_without_force_and_replaced_with_it(synthetic, tmp_path):
    rrd, rec = synthetic
    out = tmp_path / "mine.csv"
    out.write_text("someone's notes\n")
    proc = mrrig("export", str(rrd), "--to", "parquet", "--out", str(out))
    assert one_error_line(proc) == f"error: {out} is there already: --force to replace it"
    assert out.read_text() == "someone's notes\n"
    proc = mrrig("export", str(rrd), "--to", "parquet", "--out", str(out), "--force")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert read_any(out.rename(tmp_path / "mine.parquet")).samples.size == rec.samples.size
    assert [p.name for p in tmp_path.iterdir()] == ["mine.parquet"]  # no temporary left


@pytest.mark.parametrize("force", [False, True])
def test_out_never_follows_a_symbolic_link(synthetic, tmp_path, force):
    rrd, _ = synthetic
    victim, link = tmp_path / "victim.txt", tmp_path / "out.parquet"
    victim.write_text("not yours\n")
    link.symlink_to(victim)
    dangling = tmp_path / "dangling.parquet"
    dangling.symlink_to(tmp_path / "nowhere.txt")
    for out in (link, dangling):
        proc = mrrig("export", str(rrd), "--to", "parquet", "--out", str(out),
                     *(["--force"] if force else []))  # fmt: skip
        assert "is a symbolic link" in one_error_line(proc)
        assert out.is_symlink()
    assert victim.read_text() == "not yours\n"
    assert not (tmp_path / "nowhere.txt").exists()


def test_out_never_writes_over_a_catalog_or_a_recording_even_with_force(synthetic, tmp_path):
    from mrrig.api import register_run, run_records

    rrd, _ = synthetic
    catalog = tmp_path / "catalog.sqlite"
    register_run("rig1", dt.datetime.now(dt.UTC), catalog=catalog)
    other = tmp_path / "other.rrd"
    other.write_bytes(rrd.read_bytes())
    for out in (catalog, other):
        before = out.read_bytes()
        proc = mrrig("export", str(rrd), "--to", "csv", "--out", str(out), "--force")
        assert "an export never writes over one, --force or not" in one_error_line(proc)
        assert out.read_bytes() == before
    assert len(run_records(catalog)) == 1
    # the catalog `mrrig runs` reads ($MRRIG_CATALOG), not there yet, is refused as well
    env_catalog = tmp_path / "lab.sqlite"
    proc = subprocess.run(
        [sys.executable, "-m", "mrrig", "export", str(rrd), "--to", "csv", "--out",
         str(env_catalog)],
        cwd=REPO, capture_output=True, text=True, timeout=120,
        env={**os.environ, "MRRIG_CATALOG": str(env_catalog)},
    )  # fmt: skip
    assert "which holds runs" in one_error_line(proc)
    assert not env_catalog.exists()
