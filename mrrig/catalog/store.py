"""The catalog's one access layer (SQLAlchemy Core) for SQLite and PostgreSQL.

A catalog is named by a URL: `sqlite:///recordings/catalog.sqlite` (a plain path means the
same), or `postgresql://user@host/db` (driven by psycopg 3). Opening one brings its schema to
the newest migration (Alembic, mrrig/catalog/migrations/), under a lock, so that two rigs
opening a fresh catalog at once migrate it once. SQLite runs in WAL mode with a busy timeout
and takes its write lock at the start of a write (BEGIN IMMEDIATE): a reader never blocks a
writer, and two writers wait for each other instead of failing.

Writes are idempotent by run id: registering a run again updates its row, `sync` copies a
run over once however often it runs or is interrupted.
"""

from __future__ import annotations

import logging
import threading
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy import event

from mrrig.catalog.query import parse_where
from mrrig.catalog.record import CHARACTERIZATION_PLAN, RunRecord
from mrrig.catalog.schema import SCHEMA_REVISION, runs
from mrrig.errors import MrrigError

log = logging.getLogger("mrrig.catalog")

DEFAULT_PATH = Path("recordings") / "catalog.sqlite"
SQLITE_BUSY_TIMEOUT_MS = 10_000
CONNECT_TIMEOUT_S = 5
# rows per statement and per transaction in `register_runs` and `sync`
BATCH_ROWS = 500
_MIGRATION_LOCK_ID = 0x6D72726967  # "mrrig": the PostgreSQL advisory lock of a migration


class CatalogError(MrrigError, RuntimeError):
    """The catalog cannot do what was asked (no such run, a database error, ...)."""


class CatalogUnreachable(CatalogError, ConnectionError):
    """The catalog's database cannot be reached (refused, timed out, connection lost)."""


@dataclass(frozen=True)
class Registration:
    """Where `register_run` wrote a run: `url` (the password hidden), `new` if the run was not
    there before, `spooled` if the catalog asked for was unreachable and the spool took it."""

    url: str
    new: bool
    spooled: bool


@dataclass(frozen=True)
class SyncReport:
    """What `sync` did: runs `copied` (new there), `updated` (registered again since), and
    `unchanged` (already there as they are here)."""

    copied: int
    updated: int
    unchanged: int


def catalog_url(text: str | Path) -> sa.URL:
    """The SQLAlchemy URL of `text`: a path is an SQLite file, `postgresql://` uses psycopg 3."""
    text = str(text)
    if "://" not in text:
        return sa.URL.create("sqlite+pysqlite", database=str(Path(text).absolute()))
    try:
        url = sa.make_url(text)
    except sa.exc.ArgumentError:
        raise CatalogError(f"catalog: not a database URL: {text!r}") from None
    if url.get_backend_name() == "postgresql":
        return url.set(drivername="postgresql+psycopg")
    if url.get_backend_name() == "sqlite":
        if not url.database or url.database == ":memory:":
            raise CatalogError(f"catalog {text}: an SQLite catalog is a file, give its path")
        return url.set(drivername="sqlite+pysqlite")
    raise CatalogError(
        f"catalog {url.render_as_string(hide_password=True)}: only sqlite:/// and"
        " postgresql:// catalogs are supported"
    )


class Catalog:
    """One open catalog: an engine at the newest schema. `open_catalog` shares one per URL."""

    def __init__(self, url: sa.URL) -> None:
        self.url = url
        self.name = url.render_as_string(hide_password=True)
        self.dialect = url.get_backend_name()
        if self.dialect == "sqlite":
            self.engine = sa.create_engine(url)
            event.listen(self.engine, "connect", _sqlite_connect)
            event.listen(self.engine, "begin", _sqlite_begin)
        else:
            args = {} if "connect_timeout" in url.query else {"connect_timeout": CONNECT_TIMEOUT_S}
            self.engine = sa.create_engine(url, connect_args=args, pool_pre_ping=True)
        self.migrated = False

    @contextmanager
    def connect(self, write: bool = False) -> Iterator[sa.Connection]:
        """A connection in a transaction, committed at the end; database errors become
        CatalogError (CatalogUnreachable where the connection failed or was lost)."""
        try:
            with self.engine.connect() as conn:
                conn.execution_options(catalog_write=write)
                with conn.begin():
                    yield conn
        except sa.exc.DBAPIError as exc:
            reason = _first_line(exc.orig if exc.orig is not None else exc)
            if isinstance(exc, sa.exc.OperationalError | sa.exc.InterfaceError) and (
                self.dialect != "sqlite" or exc.connection_invalidated
            ):
                raise CatalogUnreachable(f"catalog {self.name}: unreachable: {reason}") from exc
            raise CatalogError(f"catalog {self.name}: {reason}") from exc

    def migrate(self) -> None:
        """Bring the schema to SCHEMA_REVISION (once per process; a quick read when it is)."""
        if self.migrated:
            return
        with self.connect() as conn:
            current = _revision(conn)
        if current != SCHEMA_REVISION:
            with self.connect(write=True) as conn:
                if self.dialect == "postgresql":
                    conn.execute(sa.select(sa.func.pg_advisory_xact_lock(_MIGRATION_LOCK_ID)))
                _upgrade(conn, self.name)
        self.migrated = True


_catalogs: dict[str, Catalog] = {}
_catalogs_lock = threading.Lock()


def open_catalog(url: str | Path | sa.URL, create: bool = True) -> Catalog:
    """The catalog at `url`, migrated; an SQLite file that is not there is made (and its
    folder) when `create`, else CatalogError."""
    url = url if isinstance(url, sa.URL) else catalog_url(url)
    key = url.render_as_string(hide_password=False)
    with _catalogs_lock:
        catalog = _catalogs.get(key)
        if catalog is None:
            if url.get_backend_name() == "sqlite":
                path = Path(url.database or "")
                if not path.exists():
                    if not create:
                        raise CatalogError(f"no catalog at {path}: no run registered there yet")
                    path.parent.mkdir(parents=True, exist_ok=True)
            catalog = _catalogs[key] = Catalog(url)
    catalog.migrate()
    return catalog


def register_run(
    url: str | Path, record: RunRecord, spool_url: str | Path | None = None
) -> Registration:
    """Register one run in the catalog at `url` (its row replaced if the run id is there).

    Where that catalog is unreachable (a lab's PostgreSQL from a rig cut off) and `spool_url`
    is given (the rig's local SQLite catalog), the run goes there instead, with a warning;
    `sync(spool_url, url)` brings it over later. CatalogUnreachable otherwise."""
    try:
        new = register_runs(url, [record])
        return Registration(open_catalog(url).name, new == 1, False)
    except CatalogUnreachable as exc:
        if spool_url is None:
            raise
        log.warning("%s; run %s spooled to %s", exc, record.run_id, spool_url)
        new = register_runs(spool_url, [record])
        return Registration(open_catalog(spool_url).name, new == 1, True)


def register_runs(url: str | Path, records: Iterable[RunRecord]) -> int:
    """Register many runs (rows replaced by run id), BATCH_ROWS to a transaction; the number
    of runs that were not there before."""
    catalog = open_catalog(url)
    now = datetime.now(UTC).replace(tzinfo=None)
    new = 0
    for batch in _batches((r.to_row() | {"registered_utc": now} for r in records), BATCH_ROWS):
        with catalog.connect(write=True) as conn:
            ids = [row["run_id"] for row in batch]
            there = set(conn.scalars(sa.select(runs.c.run_id).where(runs.c.run_id.in_(ids))))
            conn.execute(_upsert(catalog.dialect), batch)
            _close_steps(conn, batch)
            new += len(set(ids) - there)
    return new


def _close_steps(conn: sa.Connection, rows: list[dict[str, Any]]) -> None:
    """A run registered with its recording's sha256 (the daemon's, once the file is closed)
    gives it to the runs registered while that recording was still being written (a plan's
    steps): from then on `check_recording` checks them too."""
    for row in rows:
        if row.get("recording_path") and row.get("recording_sha256"):
            conn.execute(
                sa.update(runs)
                .where(
                    runs.c.recording_path == row["recording_path"],
                    runs.c.recording_sha256.is_(None),
                )
                .values(
                    recording_sha256=row["recording_sha256"],
                    recording_size_bytes=row["recording_size_bytes"],
                )
            )


def find_runs(
    url: str | Path,
    *,
    rig: str | None = None,
    specimen: str | None = None,
    plan: str | None = None,
    controller: str | None = None,
    campaign: str | None = None,
    characterization: bool | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
    where: str | None = None,
    limit: int | None = None,
) -> list[RunRecord]:
    """The runs that match every filter given, oldest first (with `limit`: the newest
    `limit` of them). `characterization`: True for the characterization runs only
    (CHARACTERIZATION_PLAN), False for all but those, None for both. `since`/`until` bound
    the run's wall-clock start (aware datetimes); `where` is the expression language of
    `mrrig.catalog.query` (`"et < 0.01"`)."""
    stmt = sa.select(runs)
    for column, value in (
        ("rig", rig),
        ("specimen", specimen),
        ("plan", plan),
        ("controller", controller),
        ("campaign", campaign),
    ):
        if value is not None:
            stmt = stmt.where(runs.c[column] == value)
    if characterization is not None:
        is_one = sa.func.coalesce(runs.c.plan, "") == CHARACTERIZATION_PLAN
        stmt = stmt.where(is_one if characterization else sa.not_(is_one))
    if since is not None:
        stmt = stmt.where(runs.c.started_utc >= _naive_utc(since, "since"))
    if until is not None:
        stmt = stmt.where(runs.c.started_utc < _naive_utc(until, "until"))
    if where:
        stmt = stmt.where(parse_where(where))
    stmt = stmt.order_by(runs.c.started_utc.desc(), runs.c.run_id.desc())
    if limit is not None:
        stmt = stmt.limit(limit)
    with open_catalog(url, create=False).connect() as conn:
        rows = conn.execute(stmt).mappings().all()
    return [RunRecord.from_row(row) for row in reversed(rows)]


def get_run(url: str | Path, run_id: str | uuid.UUID) -> RunRecord:
    """The run `run_id`, or the one run whose id starts with it (at least 4 characters, as
    `mrrig runs` prints 8); CatalogError where none or several match."""
    text = str(run_id).strip().lower()
    if len(text) < 4 or any(c not in "0123456789abcdef-" for c in text):
        raise CatalogError(f"run id {str(run_id)!r}: expected a UUID or its first 4+ hex digits")
    catalog = open_catalog(url, create=False)
    with catalog.connect() as conn:
        rows = (
            conn.execute(sa.select(runs).where(runs.c.run_id.startswith(text)).limit(2))
            .mappings()
            .all()
        )
    if not rows:
        raise CatalogError(f"no run {text} in the catalog {catalog.name}")
    if len(rows) > 1:
        raise CatalogError(f"run id {text}: several runs start with it; give more digits")
    return RunRecord.from_row(rows[0])


def has_run(url: str | Path, run_id: str | uuid.UUID) -> bool:
    """Whether the catalog at `url` (made where it is not there) has the run `run_id`."""
    with open_catalog(url).connect() as conn:
        found = conn.scalar(sa.select(runs.c.run_id).where(runs.c.run_id == str(run_id)))
    return found is not None


def recording_names(url: str | Path) -> set[str]:
    """The file names (no folder) of the recordings registered in the catalog at `url`: what
    `mrrig runs` compares a recordings folder with, wherever the rig's paths were rooted."""
    with open_catalog(url, create=False).connect() as conn:
        paths = conn.scalars(
            sa.select(runs.c.recording_path).where(runs.c.recording_path.is_not(None))
        )
        return {Path(p).name for p in paths}


def sync(local_url: str | Path, remote_url: str | Path, batch_rows: int = BATCH_ROWS) -> SyncReport:
    """Copy the runs of `local_url` (a rig's spool) that `remote_url` (the lab's catalog) does
    not have, or has from an older registration; `batch_rows` runs to a transaction, so an
    interrupted sync keeps what it copied and the next one copies the rest, each run once."""
    local = open_catalog(local_url, create=False)
    remote = open_catalog(remote_url)
    with local.connect() as conn:
        mine = dict(conn.execute(sa.select(runs.c.run_id, runs.c.registered_utc)).all())
    theirs: dict[str, datetime] = {}
    for ids in _batches(mine, BATCH_ROWS):
        with remote.connect() as conn:
            stmt = sa.select(runs.c.run_id, runs.c.registered_utc).where(runs.c.run_id.in_(ids))
            theirs.update(conn.execute(stmt).all())
    missing = sorted(set(mine) - set(theirs))
    older = sorted(k for k in theirs if theirs[k] < mine[k])
    for ids in _batches([*missing, *older], batch_rows):
        with local.connect() as conn:
            rows = [
                dict(r)
                for r in conn.execute(sa.select(runs).where(runs.c.run_id.in_(ids))).mappings()
            ]
        with remote.connect(write=True) as conn:
            conn.execute(_upsert(remote.dialect, only_newer=True), rows)
    report = SyncReport(len(missing), len(older), len(mine) - len(missing) - len(older))
    log.info("sync %s -> %s: %s", local.name, remote.name, report)
    return report


def _upsert(dialect: str, only_newer: bool = False) -> Any:
    """INSERT ... ON CONFLICT (run_id) DO UPDATE, in the dialect's words; `only_newer`: only
    over an older registration."""
    if dialect == "sqlite":
        from sqlalchemy.dialects.sqlite import insert
    else:
        from sqlalchemy.dialects.postgresql import insert
    stmt = insert(runs)
    columns = {c.name: stmt.excluded[c.name] for c in runs.c if c.name != "run_id"}
    where = runs.c.registered_utc < stmt.excluded.registered_utc if only_newer else None
    return stmt.on_conflict_do_update(index_elements=[runs.c.run_id], set_=columns, where=where)


def _revision(conn: sa.Connection) -> str | None:
    if not sa.inspect(conn).has_table("alembic_version"):
        return None
    return conn.scalar(sa.text("SELECT version_num FROM alembic_version"))


def _upgrade(conn: sa.Connection, name: str) -> None:
    # its own INFO lines (from its import on) would say what the one line at the end says
    logging.getLogger("alembic").setLevel(logging.WARNING)
    from alembic import command
    from alembic.config import Config
    from alembic.util.exc import CommandError

    cfg = Config()
    cfg.set_main_option("script_location", str(Path(__file__).with_name("migrations")))
    cfg.attributes["connection"] = conn
    before = _revision(conn)
    try:
        command.upgrade(cfg, "head")
    except CommandError as exc:
        raise CatalogError(
            f"catalog {name}: schema revision {before!r} unknown to this mrrig (newest"
            f" {SCHEMA_REVISION}): {exc}"
        ) from exc
    if before != SCHEMA_REVISION:
        log.info("catalog %s: schema %s -> %s", name, before or "empty", SCHEMA_REVISION)


def _sqlite_connect(dbapi_connection: Any, _record: Any) -> None:
    # transactions are begun by _sqlite_begin, not by the driver (which would begin them
    # DEFERRED and late, after a SELECT): DDL inside them, and the write lock at the start
    dbapi_connection.isolation_level = None
    cursor = dbapi_connection.cursor()
    cursor.execute(f"PRAGMA busy_timeout = {SQLITE_BUSY_TIMEOUT_MS}")
    cursor.execute("PRAGMA journal_mode = WAL")
    # a committed run survives a power loss too, not only a killed process
    cursor.execute("PRAGMA synchronous = FULL")
    cursor.close()


def _sqlite_begin(conn: sa.Connection) -> None:
    write = conn.get_execution_options().get("catalog_write", False)
    conn.exec_driver_sql("BEGIN IMMEDIATE" if write else "BEGIN")


def _naive_utc(when: datetime, name: str) -> datetime:
    if when.tzinfo is None:
        raise CatalogError(f"{name}: a naive time; give its zone (UTC)")
    return when.astimezone(UTC).replace(tzinfo=None)


def _batches(items: Iterable[Any], size: int) -> Iterator[list[Any]]:
    batch: list[Any] = []
    for item in items:
        batch.append(item)
        if len(batch) >= size:
            yield batch
            batch = []
    if batch:
        yield batch


def _first_line(exc: BaseException) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__
