"""The run catalog (mrrig.catalog, `mrrig runs`) against SQLite and a real PostgreSQL server
started here in a temporary data directory (Debian's `postgresql` package; skipped with its
reason where no server is installed)."""

from __future__ import annotations

import glob
import hashlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import textwrap
import time
import uuid
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa

from mrrig.catalog import (
    CatalogError,
    CatalogUnreachable,
    QueryError,
    RecordError,
    RunRecord,
    find_runs,
    get_run,
    parse_since,
    parse_where,
    register_run,
    register_runs,
    summary_numbers,
    sync,
)
from mrrig.catalog.schema import SCHEMA_REVISION, metadata
from mrrig.catalog.schema import runs as runs_table
from mrrig.catalog.store import open_catalog
from mrrig.cli.main import main as mrrig_main
from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.loop.summary import summarize
from mrrig.rigio.canbus.bus import find_free_port

MRRIG = [sys.executable, "-m", "mrrig"]
T0 = datetime(2026, 12, 1, 8, 0, tzinfo=UTC)


def _pg_bin() -> Path | None:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    return Path(found[-1]).parent if found else None


def _as_postgres(args: list[str]) -> list[str]:
    """initdb and the server refuse to run as root: as root, run them as the postgres user."""
    return ["runuser", "-u", "postgres", "--", *args] if os.geteuid() == 0 else args


@pytest.fixture(scope="session")
def pg_server() -> Iterator[str]:
    """A PostgreSQL server on 127.0.0.1 for this session: the URL of its admin database."""
    bin_dir = _pg_bin()
    if bin_dir is None:
        pytest.skip("no PostgreSQL server installed (Debian's postgresql package)")
    base = Path(tempfile.mkdtemp(prefix="mrrig-pg-"))
    data, port = base / "data", find_free_port()
    if os.geteuid() == 0:
        shutil.chown(base, "postgres", "postgres")
    subprocess.run(
        _as_postgres(
            [str(bin_dir / "initdb"), "-D", str(data), "-A", "trust", "-U", "postgres"]
            + ["--no-sync", "-E", "UTF8", "--locale=C"]
        ),
        check=True,
        capture_output=True,
    )
    options = f"-p {port} -k {base} -c listen_addresses=127.0.0.1 -c fsync=off"
    subprocess.run(
        _as_postgres(
            [str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(base / "log"), "-w"]
            + ["-t", "60", "-o", options, "start"]
        ),
        check=True,
        capture_output=True,
    )
    try:
        yield f"postgresql://postgres@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run(
            _as_postgres([str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "immediate", "stop"]),
            capture_output=True,
        )
        shutil.rmtree(base, ignore_errors=True)


def _new_pg_database(admin_url: str) -> str:
    name = f"catalog_{uuid.uuid4().hex[:12]}"
    engine = sa.create_engine(
        admin_url.replace("postgresql://", "postgresql+psycopg://"), isolation_level="AUTOCOMMIT"
    )
    with engine.connect() as conn:
        conn.exec_driver_sql(f"CREATE DATABASE {name}")
    engine.dispose()
    return admin_url.rsplit("/", 1)[0] + f"/{name}"


@pytest.fixture(params=["sqlite", "postgresql"])
def url(request, tmp_path) -> str:
    """An empty catalog: an SQLite file, or a fresh database on the session's server."""
    if request.param == "sqlite":
        return str(tmp_path / "recordings" / "catalog.sqlite")
    return _new_pg_database(request.getfixturevalue("pg_server"))


def run(n: int = 0, **fields) -> RunRecord:
    """The n-th run of a test: a deterministic id, started n hours after T0."""
    values = dict(
        run_id=uuid.uuid5(uuid.NAMESPACE_URL, f"mrrig-test-run-{n}"),
        rig="rig1",
        host="bench-host",
        operator="tester",
        started_utc=T0 + timedelta(hours=n),
        ended_utc=T0 + timedelta(hours=n, seconds=20),
        controller="inversion",
        controller_params={"lam": 0.5, "window": [1, 2]},
        mrrig_version="0.1.0",
        et=0.01 * (n + 1),
        faults_count=n % 3,
        latency_p50_us=40.0 + n,
        latency_p99_us=90.0 + n,
        peak_current_a=1.5,
    )
    return RunRecord(**(values | fields))


def test_a_run_reads_back_as_it_was_registered(url):
    full = run(
        specimen="SN1234",
        plan="heating",
        step="3",
        model_path="models/forward.pt",
        model_sha256="a" * 64,
        config_sha256="B" * 64,
        dbc_sha256="c" * 64,
        faults=[{"t": 1.5, "reason": "overcurrent", "fault": "overcurrent"}],
        faults_count=1,
        temp_max_degc=41.5,
        verdict="pass",
        recording_path="recordings/rig1-20261201T080000Z.rrd",
        recording_size_bytes=123456789012,
        recording_sha256="d" * 64,
        tags=["campaign 7", "cold start"],
        campaign="SN1234 qualification",
    )
    register_run(url, full)
    back = get_run(url, full.run_id)
    assert back == full
    assert back.started_utc.tzinfo is UTC and back.config_sha256 == "b" * 64
    assert back.duration_s == pytest.approx(20.0)


def test_registering_a_run_again_keeps_one_row_with_the_newest_values(url):
    first = register_run(url, run(0, et=0.5))
    again = register_run(url, run(0, et=0.25, verdict="pass"))
    assert (first.new, again.new) == (True, False)
    (only,) = find_runs(url)
    assert (only.et, only.verdict) == (0.25, "pass")
    assert register_runs(url, [run(0), run(1), run(1)]) == 1
    assert len(find_runs(url)) == 2


def test_undefined_numbers_are_kept_as_none():
    assert run(et=float("nan"), latency_p99_us=float("inf")).et is None
    with pytest.raises(RecordError, match="started_utc: a naive time"):
        run(started_utc=datetime(2026, 12, 1))
    with pytest.raises(RecordError, match="model_sha256: expected 64 hex digits"):
        run(model_sha256="abc")
    with pytest.raises(RecordError, match="not a UUID"):
        run(run_id="run-7")


def test_filters_select_the_runs_that_match_every_one(url):
    register_runs(
        url,
        [
            run(0, rig="rig1", specimen="SN1", plan="p", controller="inversion"),
            run(1, rig="rig2", specimen="SN1", plan="p", controller="heaviside"),
            run(2, rig="rig2", specimen="SN2", controller="inversion"),
            run(3, rig="rig3", specimen="SN2", controller="inversion", et=float("nan")),
        ],
    )

    def ns(**kw):
        return [int(r.started_utc.hour - T0.hour) for r in find_runs(url, **kw)]

    assert ns() == [0, 1, 2, 3]
    assert ns(rig="rig2") == [1, 2]
    assert ns(specimen="SN1") == [0, 1]
    assert ns(plan="p", controller="inversion") == [0]
    assert ns(since=T0 + timedelta(hours=2)) == [2, 3]
    assert ns(until=T0 + timedelta(hours=1)) == [0]
    assert ns(where="et < 0.025") == [0, 1]
    assert ns(where="et >= 0.03 and et <= 0.03 or faults_count == 1") == [1, 2]
    assert ns(where="not (et < 0.025)") == [2]  # run 3 has no Et: it matches no comparison
    assert ns(where="0.025 > et") == [0, 1]
    assert ns(where="latency_p99_us != 91 and duration_s == 20") == [0, 2, 3]
    assert ns(limit=2) == [2, 3]
    assert ns(rig="nowhere") == []


@pytest.mark.parametrize(
    "text",
    [
        "et < 0.01; DROP TABLE runs",
        "et < 0.01 -- comment",
        "et < 0.01 or 1 = 1",
        "rig == 1",
        "et < abc",
        "et <",
        "(et < 1",
        "et < 1)",
        "et < 1e999",
        "et ~ 1",
        "et < 0.01 union select 1",
        "__import__('os').system('true')",
        "et < '0.01'",
        "and < 1",
        "",
    ],
)
def test_where_refuses_anything_outside_the_grammar(text):
    with pytest.raises(QueryError, match="^--where: "):
        parse_where(text)


def test_where_numbers_are_bound_parameters_not_sql_text():
    sql = str(parse_where("et < 0.0123 and latency_p99_us >= 250").compile())
    assert "0.0123" not in sql and "250" not in sql
    assert "runs.et <" in sql and "runs.latency_p99_us >=" in sql


def test_since_takes_spans_and_iso_dates():
    now = datetime(2026, 12, 8, 12, 0, tzinfo=UTC)
    assert parse_since("7d", now) == datetime(2026, 12, 1, 12, 0, tzinfo=UTC)
    assert parse_since("12h", now) == datetime(2026, 12, 8, 0, 0, tzinfo=UTC)
    assert parse_since("90s", now) == datetime(2026, 12, 8, 11, 58, 30, tzinfo=UTC)
    assert parse_since("2w", now) == datetime(2026, 11, 24, 12, 0, tzinfo=UTC)
    assert parse_since("2026-12-01") == datetime(2026, 12, 1, tzinfo=UTC)
    assert parse_since("2026-12-01T10:00+02:00") == datetime(2026, 12, 1, 8, tzinfo=UTC)
    for bad in ("yesterday", "7 days", "-3d", "7y"):
        with pytest.raises(QueryError, match="^--since: "):
            parse_since(bad, now)


def test_summary_numbers_come_from_the_run_summary():
    samples = np.zeros(5, dtype=SAMPLE_DTYPE)
    samples["t"] = np.arange(5) * 0.002
    samples["state"] = RigState.ARMED
    samples["f_des"] = [0.0, 100.0, 200.0, 100.0, 0.0]
    samples["f_meas"] = samples["f_des"] + 10.0
    samples["i_cmd"] = [0.0, 0.5, 1.25, 0.5, 0.0]
    samples["latency_us"] = [40.0, 50.0, 60.0, 70.0, 80.0]
    events = [{"kind": "fault", "t": 0.008, "reason": "overcurrent", "fault": "overcurrent"}]
    summary = summarize(samples, events)
    numbers = summary_numbers(summary)
    record = run(**numbers)
    assert record.et == pytest.approx(summary["et"]) and record.et > 0
    assert record.peak_current_a == 1.25
    assert record.faults_count == 1 and record.faults[0]["reason"] == "overcurrent"
    assert record.latency_p99_us == summary["latency_us"]["p99"]
    assert record.temp_max_degc is None  # the summary has no temperature


def test_the_schema_is_the_newest_migration(url):
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext
    from alembic.script import ScriptDirectory

    import mrrig.catalog.store as store

    script = ScriptDirectory(str(Path(store.__file__).with_name("migrations")))
    assert script.get_current_head() == SCHEMA_REVISION
    catalog = open_catalog(url)
    with catalog.engine.connect() as conn:
        assert conn.scalar(sa.text("SELECT version_num FROM alembic_version")) == SCHEMA_REVISION
        assert compare_metadata(MigrationContext.configure(conn), metadata) == []


def test_a_catalog_of_an_unknown_newer_schema_is_refused(tmp_path):
    path = tmp_path / "catalog.sqlite"
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE alembic_version (version_num VARCHAR(32) PRIMARY KEY)")
        db.execute("INSERT INTO alembic_version VALUES ('9999')")
    with pytest.raises(CatalogError, match="schema revision '9999' unknown to this mrrig"):
        find_runs(path)


def test_sqlite_catalog_is_in_wal_mode_with_a_busy_timeout(tmp_path):
    path = tmp_path / "catalog.sqlite"
    register_run(path, run())
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    with open_catalog(path).engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar() == 10_000


def test_unreachable_lab_database_spools_locally_and_sync_brings_each_run_once(pg_server, tmp_path):
    lab = _new_pg_database(pg_server)
    local = tmp_path / "catalog.sqlite"
    cut_off = f"postgresql://postgres@127.0.0.1:{find_free_port()}/lab?connect_timeout=2"
    register_run(local, run(0))  # the spool has a run that the lab has from a later write
    register_run(lab, run(0))
    with pytest.raises(CatalogUnreachable, match="unreachable"):
        register_run(cut_off, run(1))
    spooled = [register_run(cut_off, run(n), spool_url=local) for n in (1, 2, 3)]
    assert all(r.spooled and r.new for r in spooled)
    assert "catalog.sqlite" in spooled[0].url
    report = sync(local, lab)
    assert (report.copied, report.updated, report.unchanged) == (3, 0, 1)
    assert [r.run_id for r in find_runs(lab)] == [run(n).run_id for n in range(4)]
    again = sync(local, lab)
    assert (again.copied, again.updated, again.unchanged) == (0, 0, 4)
    register_run(local, run(2, verdict="re-reviewed"))
    assert sync(local, lab).updated == 1
    assert get_run(lab, run(2).run_id).verdict == "re-reviewed"
    assert len(find_runs(lab)) == 4


ROLES_SQL = Path(__file__).parents[1] / "mrrig" / "catalog" / "roles.sql"


def test_postgresql_roles_observers_read_rigs_insert_but_do_not_delete(pg_server, tmp_path):
    """mrrig/catalog/roles.sql, as the README says to apply it: an observer's login reads the
    catalog and cannot register; a rig's registers and registers again, and cannot delete."""
    lab = _new_pg_database(pg_server)
    register_run(lab, run(0))  # the owner makes the schema
    suffix = uuid.uuid4().hex[:8]  # roles are the server's, not the database's
    observer, rig = f"alice_{suffix}", f"rig1_{suffix}"
    owner = sa.create_engine(lab.replace("postgresql://", "postgresql+psycopg://"))
    with owner.begin() as conn:
        conn.exec_driver_sql(ROLES_SQL.read_text())
        conn.exec_driver_sql(f"CREATE ROLE {observer} LOGIN IN ROLE mrrig_observer")
        conn.exec_driver_sql(f"CREATE ROLE {rig} LOGIN IN ROLE mrrig_rig")
    owner.dispose()
    as_observer, as_rig = (lab.replace("postgres@", f"{who}@") for who in (observer, rig))

    assert [r.run_id for r in find_runs(as_observer)] == [run(0).run_id]
    with pytest.raises(CatalogError, match="permission denied for table runs"):
        register_run(as_observer, run(1))

    assert register_run(as_rig, run(1)).new
    assert not register_run(as_rig, run(1, verdict="re-reviewed")).new  # the upsert
    assert get_run(as_observer, run(1).run_id).verdict == "re-reviewed"
    with pytest.raises(CatalogError, match="permission denied for table runs"):
        with open_catalog(as_rig).connect(write=True) as conn:
            conn.execute(sa.delete(runs_table))
    with pytest.raises(CatalogError, match="permission denied for table runs"):
        with open_catalog(as_observer).connect(write=True) as conn:
            conn.execute(sa.delete(runs_table))
    assert len(find_runs(lab)) == 2
    listed = subprocess.run(
        [*MRRIG, "runs", "--json", "--catalog", as_observer], capture_output=True, text=True
    )
    assert listed.returncode == 0 and len(json.loads(listed.stdout)) == 2, listed.stderr


def test_sync_interrupted_by_kill_9_then_run_again_copies_each_run_exactly_once(url, tmp_path):
    local = tmp_path / "spool" / "catalog.sqlite"
    total = 1500
    register_runs(local, [run(n) for n in range(total)])
    proc = subprocess.Popen(
        [*MRRIG, "runs", "sync", "--from", str(local), "--to", url, "--batch", "1"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    remote = open_catalog(url)
    deadline = time.monotonic() + 60
    copied = 0
    while copied < 50 and time.monotonic() < deadline and proc.poll() is None:
        with remote.engine.connect() as conn:
            copied = conn.scalar(sa.text("SELECT count(*) FROM runs"))
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()
    with remote.engine.connect() as conn:
        before = conn.scalar(sa.text("SELECT count(*) FROM runs"))
    assert 50 <= before < total  # the kill came in the middle
    report = sync(local, url)
    assert (report.copied, report.updated, report.unchanged) == (total - before, 0, before)
    ids = [str(r.run_id) for r in find_runs(url)]
    assert len(ids) == len(set(ids)) == total
    assert set(ids) == {str(run(n).run_id) for n in range(total)}
    assert sync(local, url).copied == 0


WRITER = textwrap.dedent(
    """
    import sys, uuid
    from datetime import UTC, datetime, timedelta
    from pathlib import Path
    from mrrig.catalog import RunRecord, register_run
    catalog = Path(sys.argv[1])
    t0 = datetime(2026, 12, 1, tzinfo=UTC)
    for n in range(100000):
        rec = catalog.parent / f"rig1-{n:06d}.rrd"
        rec.write_bytes(b"rrd")  # the recording is there before its run is registered
        register_run(catalog, RunRecord(
            run_id=uuid.uuid5(uuid.NAMESPACE_URL, f"kill-{n}"), rig="rig1",
            started_utc=t0 + timedelta(seconds=n), et=0.01, recording_path=str(rec)))
        print(n, flush=True)
    """
)


def test_kill_9_of_the_writer_leaves_the_catalog_intact_missing_at_most_the_run_in_flight(
    tmp_path,
):
    catalog = tmp_path / "recordings" / "catalog.sqlite"
    catalog.parent.mkdir()
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(catalog)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    last = -1
    while last < 150:
        line = proc.stdout.readline()
        assert line, "the writer ended early"
        last = int(line)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    for line in proc.stdout:  # what it reported before the kill landed
        last = int(line)
    with sqlite3.connect(catalog) as db:
        assert db.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
    present = {str(r.run_id) for r in find_runs(catalog)}
    wanted = [str(uuid.uuid5(uuid.NAMESPACE_URL, f"kill-{n}")) for n in range(last + 2)]
    assert set(wanted[: last + 1]) <= present <= set(wanted)  # at most the run in flight
    files = {p.name for p in catalog.parent.glob("*.rrd")}
    unlisted = sorted(files - {f"rig1-{n:06d}.rrd" for n in range(len(present))})
    assert len(unlisted) <= 1
    out = subprocess.run(
        [*MRRIG, "runs", "--catalog", str(catalog), "--limit", "1"],
        capture_output=True,
        text=True,
        check=True,
    )
    if unlisted:
        assert f"1 recording in {catalog.parent} has no run in the catalog: {unlisted[0]}" in (
            out.stderr
        )
    else:
        assert "no run in the catalog" not in out.stderr
    register_run(catalog, run(0))  # and it takes new runs
    assert len(find_runs(catalog)) == len(present) + 1


def _cli(capsys, *args: str) -> tuple[int, str, str]:
    code = mrrig_main(["runs", *args])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_runs_lists_and_prints_json_with_the_registered_numbers(url, capsys):
    register_runs(url, [run(0, specimen="SN1"), run(1, specimen="SN2", plan="p", step="2")])
    code, out, _ = _cli(capsys, "--catalog", url)
    lines = out.splitlines()
    assert code == 0 and lines[0].split()[:3] == ["run", "started", "(UTC)"]
    assert lines[2].split()[:6] == [
        str(run(1).run_id)[:8],
        "2026-12-01",
        "09:00:00",
        "rig1",
        "SN2",
        "p/2",
    ]
    assert lines[-1] == "2 runs"
    code, out, _ = _cli(capsys, "--catalog", url, "--specimen", "SN2", "--json")
    assert json.loads(out) == [run(1, specimen="SN2", plan="p", step="2").to_json()]
    code, out, _ = _cli(capsys, "--catalog", url, "--where", "et > 0.015", "--json")
    assert [r["et"] for r in json.loads(out)] == [0.02]


def test_the_list_names_each_runs_model_by_its_sha256(tmp_path, capsys):
    """Issue 42's walkthrough: `mrrig runs --specimen` is to list each step with the model as
    deployed; the list showed the controller only (the sha256 was in --json and `show`)."""
    catalog = str(tmp_path / "catalog.sqlite")
    digest = hashlib.sha256(b"a model").hexdigest()
    inversion = run(1, controller="network_inversion", model_sha256=digest)
    register_runs(catalog, [run(0, controller="constant"), inversion])
    code, out, _ = _cli(capsys, "--catalog", catalog)
    head, first, second = (line.split() for line in out.splitlines()[:3])
    assert code == 0 and head[6:9] == ["controller", "model", "Et"]
    assert first[6:8] == ["constant", "-"] and second[6:8] == ["network_inversion", digest[:12]]


def test_runs_reads_the_catalog_from_the_environment(tmp_path, monkeypatch, capsys):
    path = tmp_path / "elsewhere.sqlite"
    register_run(path, run(0))
    monkeypatch.setenv("MRRIG_CATALOG", str(path))
    code, out, _ = _cli(capsys, "--json")
    assert code == 0 and len(json.loads(out)) == 1


def test_runs_show_says_whether_the_recording_is_unchanged(tmp_path, capsys):
    catalog = tmp_path / "catalog.sqlite"
    rrd = tmp_path / "rig1-20261201T080000Z.rrd"
    rrd.write_bytes(b"a recording" * 1000)
    digest = hashlib.sha256(rrd.read_bytes()).hexdigest()
    rec = run(
        recording_path=str(rrd), recording_size_bytes=rrd.stat().st_size, recording_sha256=digest
    )
    register_run(catalog, rec)
    code, out, _ = _cli(capsys, "show", str(rec.run_id)[:8], "--catalog", str(catalog))
    assert code == 0 and out.splitlines()[-1].split() == ["recording", "unchanged"]
    assert f"recording_sha256      {digest}" in out
    rrd.write_bytes(b"A recording" * 1000)  # same size, other bytes
    code, out, _ = _cli(capsys, "show", str(rec.run_id), "--catalog", str(catalog), "--json")
    assert code == 1 and json.loads(out)["recording_check"].startswith("changed: sha256")
    rrd.unlink()
    code, out, _ = _cli(capsys, "show", str(rec.run_id), "--catalog", str(catalog))
    assert code == 1 and "missing:" in out.splitlines()[-1]


def test_runs_compare_puts_two_runs_side_by_side(url, capsys):
    register_runs(url, [run(0), run(1, controller="heaviside")])
    a, b = str(run(0).run_id), str(run(1).run_id)
    code, out, _ = _cli(capsys, "compare", a[:6], b[:6], "--catalog", url, "--no-plot")
    rows = {line[2:].split()[0]: line for line in out.splitlines()[1:]}
    assert code == 0
    assert rows["controller"].startswith("* controller") and "heaviside" in rows["controller"]
    assert rows["rig"].startswith("  rig")
    assert rows["et"].split()[-3:] == ["0.01", "0.02", "+0.01"]


def _recorded_run(folder: Path, n: int, amplitude_n: float, **fields) -> RunRecord:
    """A 2 s run at 500 Hz (1 s idle, 1 s armed tracking a sine of `amplitude_n`) written by
    the sidecar's recorder, with its identity, and registered through the API."""
    from mrrig.api import register_run as api_register
    from mrrig.rigio.recording import Recorder

    t = np.arange(1000) / 500.0
    s = np.zeros(t.size, SAMPLE_DTYPE)
    s["t"], s["x"], s["xd"] = t, 0.01 * np.sin(2 * np.pi * t), 0.02 * np.pi * np.cos(2 * np.pi * t)
    s["f_des"] = amplitude_n * np.sin(2 * np.pi * 2.0 * t)
    s["f_meas"] = 0.9 * s["f_des"]
    s["i_cmd"], s["latency_us"] = amplitude_n / 600.0, 300.0
    s["state"] = np.where(t >= 1.0, RigState.ARMED, RigState.IDLE)
    run_id = uuid.uuid5(uuid.NAMESPACE_URL, f"mrrig-test-recorded-{n}")
    started = T0 + timedelta(hours=n)
    path = folder / f"run{n}.rrd"
    rec = Recorder(
        path, "rig1", identity={"run_id": str(run_id), "started_utc": started.isoformat()}
    )
    rec.add_samples(s)
    rec.add_summary(summarize(s, []))
    rec.close()
    return api_register(
        "rig1", started, run_id=run_id, catalog=folder / "catalog.sqlite", recording=path,
        ended_utc=started + timedelta(seconds=2), summary=summarize(s, []), **fields,
    )  # fmt: skip


def test_runs_compare_writes_one_figure_with_both_runs(tmp_path, capsys):
    from PIL import Image

    a = _recorded_run(tmp_path, 0, 300.0, controller="constant")
    b = _recorded_run(tmp_path, 1, 500.0, controller="heaviside")
    png = tmp_path / "ab.png"
    catalog = str(tmp_path / "catalog.sqlite")
    code, out, err = _cli(capsys, "compare", str(a.run_id)[:8], str(b.run_id)[:8],
                          "--catalog", catalog, "--plot", str(png))  # fmt: skip
    assert code == 0, err
    assert out.splitlines()[-1] == f"figure: {png}"
    image = Image.open(png)
    title = image.text["Title"]
    print(title)
    assert f"A {str(a.run_id)[:8]} rig1, Et " in title and f"B {str(b.run_id)[:8]} rig1" in title
    assert title.count(": 500 armed frames") == 2
    # both runs' lines are drawn: matplotlib's first two colours (C0 A, C1 B)
    pixels = np.asarray(image.convert("RGB")).reshape(-1, 3)
    for rgb in ((0x1F, 0x77, 0xB4), (0xFF, 0x7F, 0x0E)):
        assert (np.abs(pixels.astype(int) - rgb).sum(axis=1) < 30).sum() > 1000, rgb
    # a run without its recording: the numbers, then one line saying why no figure
    Path(b.recording_path).unlink()
    code, out, err = _cli(capsys, "compare", str(a.run_id), str(b.run_id), "--catalog", catalog)
    assert code == 2 and "controller" in out
    assert f"run B {str(b.run_id)[:8]}: no recording to plot (missing: " in err


def test_api_runs_is_a_dataframe_of_utc_times_whole_seconds_or_not(tmp_path):
    from mrrig.api import runs as api_runs

    catalog = tmp_path / "catalog.sqlite"
    register_runs(catalog, [run(0), run(1, started_utc=T0 + timedelta(hours=1, microseconds=5))])
    df = api_runs(catalog)
    assert list(df["started_utc"]) == [T0, T0 + timedelta(hours=1, microseconds=5)]
    assert str(df["started_utc"].dt.tz) == "UTC" and df["et"].tolist() == [0.01, 0.02]


def test_runs_sync_prints_its_counts(tmp_path, capsys):
    local, lab = tmp_path / "a.sqlite", tmp_path / "b.sqlite"
    register_runs(local, [run(0), run(1)])
    code, out, _ = _cli(capsys, "sync", "--from", str(local), "--to", str(lab))
    assert code == 0 and out.startswith("sync: 2 copied, 0 updated, 0 already there (")
    code, out, _ = _cli(capsys, "sync", "--from", str(local), "--to", str(lab))
    assert out.startswith("sync: 0 copied, 0 updated, 2 already there (")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--catalog", "{missing}"], "error: no catalog at "),
        (["--catalog", "{catalog}", "--where", "et < 1; drop"], "error: --where: ';' at char"),
        (["--catalog", "{catalog}", "--since", "last week"], "error: --since: 'last week'"),
        (["show", "0123abcd", "--catalog", "{catalog}"], "error: no run 0123abcd in the cata"),
        (["show", "x';--", "--catalog", "{catalog}"], 'error: run id "x\';--": expected a'),
        (["--catalog", "mysql://db/x"], "error: catalog mysql://db/x: only sqlite:/// and"),
        (
            ["--catalog", "postgresql://u:secret@127.0.0.1:{port}/x?connect_timeout=2"],
            "error: catalog postgresql+psycopg://u:***@127.0.0.1:",
        ),
    ],
)
def test_runs_errors_are_one_line_and_exit_2(tmp_path, args, message):
    catalog = tmp_path / "catalog.sqlite"
    register_run(catalog, run(0))
    values = {"missing": tmp_path / "none.sqlite", "catalog": catalog, "port": find_free_port()}
    proc = subprocess.run(
        [*MRRIG, "runs", *(a.format(**values) for a in args)], capture_output=True, text=True
    )
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(message), proc.stderr
    assert "secret" not in proc.stderr


def test_bench_catalog_prints_its_medians():
    proc = subprocess.run(
        [*MRRIG, "bench", "catalog", "--runs", "300", "--repeat", "2"],
        capture_output=True,
        text=True,
    )
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("filled ") and ": 300 runs in " in lines[0]
    assert lines[1].startswith("runs --since 7d: ") and lines[1].endswith(" of 300 runs")
    assert lines[2].startswith("API find_runs: median ")
    assert lines[3].startswith("CLI `mrrig runs --since 7d` (own process, table printed: ")
    # the target's verdict is the benchmark's to print, not this test's to time on a loaded
    # machine: the line is there and the exit code follows it
    verdict = {"target: CLI under 1 s: met": 0, "target: CLI under 1 s: MISSED": 1}
    assert lines[4] in verdict and proc.returncode == verdict[lines[4]], (lines[4], proc.stderr)


# issue 40, finding 10: no match, --where nested too deep, --since beyond the calendar


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--rig", "nosuch"], "no run in the catalog {catalog} matches --rig 'nosuch'"),
        (["--specimen", "X"], "no run in the catalog {catalog} matches --specimen 'X'"),
        (["--specimen", "X", "--json"], "no run in the catalog {catalog} matches --specimen 'X'"),
        ([], "no run in the catalog {empty} at all: the catalog is empty"),
    ],
)
def test_runs_with_no_matching_run_say_so_in_one_line_and_exit_1(tmp_path, args, message):
    catalog, empty = tmp_path / "catalog.sqlite", tmp_path / "empty" / "catalog.sqlite"
    register_run(catalog, run(0, specimen="SN1"))
    open_catalog(empty)  # a catalog without runs
    which = empty if not args else catalog
    proc = subprocess.run(
        [*MRRIG, "runs", "--catalog", str(which), *args], capture_output=True, text=True
    )
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert proc.stderr == message.format(catalog=catalog, empty=empty) + "\n"
    assert proc.stdout == ("[]\n" if "--json" in args else "")


@pytest.mark.parametrize(
    ("where", "message"),
    [
        ("(" * 400 + "et < 1" + ")" * 400, "error: --where: nested deeper than 32 levels"),
        ("not " * 400 + "et < 1", "error: --where: nested deeper than 32 levels"),
    ],
)
def test_runs_where_nested_beyond_its_limit_is_one_line_and_exit_2(tmp_path, where, message):
    catalog = tmp_path / "catalog.sqlite"
    register_run(catalog, run(0))
    proc = subprocess.run(
        [*MRRIG, "runs", "--catalog", str(catalog), "--where", where],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(message), proc.stderr
    # as deep as the limit still works
    deep = "(" * 32 + "et < 1" + ")" * 32
    assert [r.run_id for r in find_runs(catalog, where=deep)] == [run(0).run_id]


@pytest.mark.parametrize("since", ["99999999999d", "99999999d", "9999999999999w"])
def test_runs_since_beyond_the_calendar_is_one_line_and_exit_2(tmp_path, since):
    catalog = tmp_path / "catalog.sqlite"
    register_run(catalog, run(0))
    proc = subprocess.run(
        [*MRRIG, "runs", "--catalog", str(catalog), "--since", since],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert (
        proc.stderr == f"error: --since: {since!r} reaches back before the year 1; give a"
        " shorter span\n"
    )


# issue 42: `mrrig runs` finds a specimen's campaign, and characterization runs (constant
# currents: an Et that means nothing) stay out of the list unless asked for


def _campaign_runs() -> list[RunRecord]:
    return [
        run(0, specimen="SN-MR-042", plan="qual", step="1", campaign="qual A"),
        run(1, specimen="SN-MR-042", plan="qual", step="2", campaign="qual A"),
        run(2, specimen="SN-MR-042", plan="qual", step="1", campaign="qual B"),
        run(3, specimen="SN-MR-042", plan="characterize", step="run-001", campaign="m1"),
        run(4, specimen="SN-MR-042", plan="characterize", step="run-002", campaign="m1"),
        run(5, specimen="SN-OTHER"),  # no plan (a daemon's own run): never a characterization
    ]


def _listed(capsys, url, *args: str) -> list[int]:
    code, out, _ = _cli(capsys, "--catalog", url, "--json", *args)
    return [int(r["started_utc"][11:13]) - T0.hour for r in json.loads(out)] if code == 0 else []


def test_runs_filter_by_campaign_and_leave_characterization_out_unless_asked(url, capsys):
    register_runs(url, _campaign_runs())
    assert _listed(capsys, url) == [0, 1, 2, 5]
    assert _listed(capsys, url, "--specimen", "SN-MR-042") == [0, 1, 2]
    assert _listed(capsys, url, "--campaign", "qual A") == [0, 1]
    assert _listed(capsys, url, "--specimen", "SN-MR-042", "--all") == [0, 1, 2, 3, 4]
    assert _listed(capsys, url, "--characterization") == [3, 4]
    assert _listed(capsys, url, "--campaign", "m1", "--characterization") == [3, 4]
    assert _listed(capsys, url, "--plan", "characterize") == [3, 4]
    assert _listed(capsys, url, "--campaign", "m1") == []  # asked for, but not by --all
    code, out, _ = _cli(capsys, "--catalog", url)
    assert code == 0 and out.splitlines()[-1] == "4 runs"
    # the Python API leaves nothing out unless told
    assert len(find_runs(url)) == 6 and len(find_runs(url, characterization=False)) == 4
    assert [r.campaign for r in find_runs(url, campaign="qual B")] == ["qual B"]


def test_runs_with_only_characterization_runs_say_how_to_list_them(tmp_path):
    catalog = tmp_path / "catalog.sqlite"
    register_run(catalog, run(0, plan="characterize", step="run-001"))
    proc = subprocess.run(
        [*MRRIG, "runs", "--catalog", str(catalog)], capture_output=True, text=True
    )
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr == (
        f"no run in the catalog {catalog} but characterization runs (--all lists them too)\n"
    )
    proc = subprocess.run(
        [*MRRIG, "runs", "--catalog", str(catalog), "--all", "--characterization"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2 and "not allowed with argument" in proc.stderr


def test_a_catalog_of_the_first_schema_is_migrated_with_its_runs_kept(tmp_path):
    from alembic import command
    from alembic.config import Config

    import mrrig.catalog.store as store

    path = tmp_path / "catalog.sqlite"
    engine = sa.create_engine(f"sqlite:///{path}")
    with engine.begin() as conn:
        cfg = Config()
        cfg.set_main_option("script_location", str(Path(store.__file__).with_name("migrations")))
        cfg.attributes["connection"] = conn
        command.upgrade(cfg, "0001")
        row = run(0, specimen="SN1").to_row()
        del row["campaign"]
        conn.execute(
            sa.text(
                f"INSERT INTO runs ({', '.join(row)}, registered_utc)"
                f" VALUES ({', '.join(':' + k for k in row)}, :registered_utc)"
            ),
            {
                k: json.dumps(v) if isinstance(v, dict | list) else v
                for k, v in (row | {"registered_utc": T0.replace(tzinfo=None)}).items()
            },
        )
    engine.dispose()
    (old,) = find_runs(path)
    assert old == run(0, specimen="SN1") and old.campaign is None
    register_run(path, run(1, campaign="c"))
    assert [r.campaign for r in find_runs(path, campaign="c")] == ["c"]
