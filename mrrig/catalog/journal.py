"""Runs are never lost: a finished run is written to a journal beside its recording
(`REC.rrd.journal`, one JSON line: the catalog it goes to and its record) before it is
registered, and the journal is removed once the catalog has it. A catalog that is locked,
corrupt or unreachable (and its spool too) leaves the journal there; `replay` registers it
later: the next registration by a daemon's sidecar (journals in its recording's folder) and
every `mrrig runs` (journals in an SQLite catalog's folder, or `--recordings`).

A run without a recording is journalled beside its SQLite catalog (or spool) instead, as
`run-<run id>.journal`. The journal is written to a temporary name and renamed, so a replay
never reads half of one.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mrrig.catalog.record import RecordError, RunRecord
from mrrig.catalog.store import CatalogError, Registration, catalog_url, register_run

log = logging.getLogger("mrrig.catalog")

SUFFIX = ".journal"


@dataclass(frozen=True)
class ReplayReport:
    """What `replay` did: journals `registered` (and removed), `kept` (their catalog still
    cannot take them), `unreadable` (not a journal: left there, named in the log)."""

    registered: int
    kept: int
    unreadable: int


def journal_path(record: RunRecord, catalog: str, spool: str | None) -> Path | None:
    """Where the run's journal goes: beside its recording, else beside the SQLite file that
    would take it (the catalog, else the spool); None where there is no such folder."""
    if record.recording_path:
        return Path(record.recording_path + SUFFIX)
    for url in (catalog, spool):
        if url is None:
            continue
        try:
            parsed = catalog_url(url)
        except CatalogError:
            continue
        if parsed.get_backend_name() == "sqlite" and parsed.database:
            return Path(parsed.database).parent / f"run-{record.run_id}{SUFFIX}"
    return None


def write_journal(path: Path, record: RunRecord, catalog: str, spool: str | None) -> None:
    """The run's journal at `path`, on disk (fsync) before this returns; OSError if not."""
    line = json.dumps({"catalog": catalog, "spool": spool, "run": record.to_json()})
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(line + "\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def register_journalled(record: RunRecord, catalog: str, spool: str | None = None) -> Registration:
    """Journal the run, register it (`register_run`, spooled where `catalog` is unreachable),
    and remove the journal once it is in. CatalogError (the journal kept, its path in the
    message) where neither catalog takes it."""
    path = journal_path(record, catalog, spool)
    if path is not None:
        try:
            write_journal(path, record, catalog, spool)
        except OSError as exc:
            log.error("run %s: no journal at %s: %s", record.run_id, path, exc)
            path = None
    try:
        where = register_run(catalog, record, spool_url=spool)
    except CatalogError as exc:
        kept = f"; journalled in {path}, registered when the catalog is back" if path else ""
        raise CatalogError(f"{exc}{kept}") from exc
    if path is not None:
        path.unlink(missing_ok=True)
    return where


def replay(folder: str | Path, catalog: str | None = None) -> ReplayReport:
    """Register every journalled run in `folder` into the catalog its journal names (or
    `catalog`, where given), removing each journal its catalog took. Never raises for a
    catalog that still cannot take a run: that journal stays, with a warning."""
    registered = kept = unreadable = 0
    folder = Path(folder)
    if not folder.is_dir():
        return ReplayReport(0, 0, 0)
    for path in sorted(folder.glob(f"*{SUFFIX}")):
        try:
            entry = read_journal(path)
        except FileNotFoundError:
            continue  # another replay took it
        except (OSError, ValueError) as exc:
            log.warning("%s: not a run journal, left there: %s", path, exc)
            unreadable += 1
            continue
        record, target, spool = entry
        try:
            register_run(catalog or target, record, spool_url=None if catalog else spool)
        except CatalogError as exc:
            log.warning("run %s still not registered (%s kept): %s", record.run_id, path, exc)
            kept += 1
            continue
        path.unlink(missing_ok=True)
        log.info("run %s registered in %s from its journal", record.run_id, catalog or target)
        registered += 1
    return ReplayReport(registered, kept, unreadable)


def read_journal(path: Path) -> tuple[RunRecord, str, str | None]:
    """The run, its catalog and spool of the journal at `path`; ValueError naming the file
    where it is not one."""
    text = path.read_text(encoding="utf-8")
    try:
        entry: Any = json.loads(text)
        if not isinstance(entry, dict) or not isinstance(entry.get("catalog"), str):
            raise ValueError("no catalog named")
        return RunRecord.from_json(entry["run"]), entry["catalog"], entry.get("spool")
    except (KeyError, TypeError, ValueError, RecordError) as exc:
        raise ValueError(f"{path}: {exc}") from None
