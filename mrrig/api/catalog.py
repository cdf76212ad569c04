"""The run catalog from Python (and for `mrrig runs`, which is built on these): find runs,
check a run's recording, register a run, sync a spool, compare two runs in one figure.

A catalog is an SQLite file or a `postgresql://` URL; None means `default_catalog()`:
$MRRIG_CATALOG, else `recordings/catalog.sqlite`. Times are aware UTC datetimes; numbers in
the units of `mrrig.catalog.RunRecord` (Et dimensionless, latency us, current A, degC).
"""

from __future__ import annotations

import hashlib
import os
import uuid
from collections.abc import Mapping
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import pandas as pd

    from mrrig.catalog import RunRecord, SyncReport

ENV_CATALOG = "MRRIG_CATALOG"
_HASH_CHUNK = 1 << 20


def default_catalog() -> str:
    """The catalog `mrrig runs` reads by default: $MRRIG_CATALOG, else
    `recordings/catalog.sqlite`."""
    from mrrig.catalog import DEFAULT_PATH

    return os.environ.get(ENV_CATALOG) or str(DEFAULT_PATH)


def run_records(
    catalog: str | Path | None = None,
    *,
    rig: str | None = None,
    specimen: str | None = None,
    plan: str | None = None,
    controller: str | None = None,
    campaign: str | None = None,
    characterization: bool | None = None,
    since: str | datetime | None = None,
    until: datetime | None = None,
    where: str | None = None,
    limit: int | None = None,
) -> list[RunRecord]:
    """The catalog's runs matching every filter, oldest first (with `limit`: the newest
    `limit`), as `RunRecord`s. `campaign`: the runs it groups (a plan's steps, a
    characterization matrix); `characterization`: True for the characterization runs only
    (`mrrig characterize`'s constant currents), False for all but those, None for both.
    `since`: a datetime, or a span as `mrrig runs --since` (`"7d"`, `"12h"`) or an ISO date;
    `where`: `"et < 0.01 and faults_count == 0"` (the catalog's numeric columns)."""
    from mrrig.catalog import find_runs, parse_since

    return find_runs(
        catalog or default_catalog(),
        rig=rig,
        specimen=specimen,
        plan=plan,
        controller=controller,
        campaign=campaign,
        characterization=characterization,
        since=parse_since(since) if isinstance(since, str) else since,
        until=until,
        where=where,
        limit=limit,
    )


def runs(
    catalog: str | Path | None = None,
    *,
    rig: str | None = None,
    specimen: str | None = None,
    plan: str | None = None,
    controller: str | None = None,
    campaign: str | None = None,
    characterization: bool | None = None,
    since: str | datetime | None = None,
    until: datetime | None = None,
    where: str | None = None,
    limit: int | None = None,
) -> pd.DataFrame:
    """`run_records` as a pandas DataFrame, one row per run: run id, rig, specimen, plan,
    step, `started_utc`/`ended_utc` (UTC timestamps), controller, `et`, `faults_count`,
    `latency_p50_us`/`latency_p99_us` (us), `peak_current_a` (A), `temp_max_degc` (degC),
    verdict, recording path and sha256, ... (the fields of `mrrig runs --json`)."""
    import pandas as pd

    found = run_records(
        catalog,
        rig=rig,
        specimen=specimen,
        plan=plan,
        controller=controller,
        campaign=campaign,
        characterization=characterization,
        since=since,
        until=until,
        where=where,
        limit=limit,
    )
    frame = pd.DataFrame([r.to_json() for r in found])
    for name in ("started_utc", "ended_utc"):
        if name in frame:
            frame[name] = pd.to_datetime(frame[name], utc=True, format="ISO8601")
    return frame


def get_run(run_id: str | uuid.UUID, catalog: str | Path | None = None) -> RunRecord:
    """The run `run_id`, or the one run whose id starts with it (4+ hex digits); CatalogError
    where none or several match."""
    from mrrig.catalog import get_run as get

    return get(catalog or default_catalog(), run_id)


def check_recording(run: RunRecord) -> str:
    """Whether the run's recording is still what was registered: `unchanged`, `missing: ...`,
    `changed: ...` (size, else sha256), `unchecked: ...` (no sha256 registered: a recording
    still being written when the run was) or `no recording registered`."""
    if not run.recording_path:
        return "no recording registered"
    path = Path(run.recording_path)
    if not path.is_file():
        return f"missing: {path} is not there"
    size = path.stat().st_size
    if run.recording_size_bytes is not None and size != run.recording_size_bytes:
        return f"changed: {size} bytes, {run.recording_size_bytes} registered"
    if run.recording_sha256 is None:
        return "unchecked: no sha256 registered"
    digest = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(_HASH_CHUNK):
            digest.update(chunk)
    if digest.hexdigest() != run.recording_sha256:
        return f"changed: sha256 {digest.hexdigest()}, {run.recording_sha256} registered"
    return "unchanged"


def unregistered_recordings(
    catalog: str | Path | None = None, folder: str | Path | None = None
) -> tuple[Path | None, list[str]]:
    """The `.rrd` files in `folder` (default: an SQLite catalog's own folder; none for a
    server's) that no run of the catalog names, sorted: a run whose registration was lost
    (its writer killed, the catalog unreachable without a spool). Returns (folder, names)."""
    from mrrig.catalog.store import catalog_url, recording_names

    catalog = catalog or default_catalog()
    if folder is None:
        url = catalog_url(catalog)
        if url.get_backend_name() != "sqlite":
            return None, []
        folder = Path(url.database or "").parent
    folder = Path(folder)
    on_disk = {p.name for p in folder.glob("*.rrd")}
    if not on_disk:
        return folder, []
    return folder, sorted(on_disk - recording_names(catalog))


def sync_runs(src: str | Path, dst: str | Path, batch_rows: int = 500) -> SyncReport:
    """Copy the runs of `src` (a rig's spool) that `dst` (the lab's catalog) lacks or has
    from an older registration, `batch_rows` to a transaction: each run once, by run id."""
    from mrrig.catalog import sync

    return sync(src, dst, batch_rows=batch_rows)


def register_run(
    rig: str,
    started_utc: datetime,
    *,
    catalog: str | Path | None = None,
    spool: str | Path | None = None,
    summary: Mapping[str, Any] | None = None,
    recording: str | Path | None = None,
    model: str | Path | None = None,
    config: str | Path | None = None,
    **fields: Any,
) -> RunRecord:
    """Register one run in the catalog and return its record (a new run id unless `run_id`
    is given; registering the same id again replaces its row).

    `started_utc` (and `ended_utc` in `fields`): aware datetimes. `catalog`: an SQLite file
    or a `postgresql://` URL (default: `default_catalog()`); `spool`: where the run goes when
    that one cannot be reached (`mrrig runs sync` brings it over later). `summary`: a run
    summary (`mrrig.loop.summary`: Et, faults, latency in us, current in A, temperature in
    degC) for the numbers; `recording` (a finished one: `recording_path` names one still
    being written), `model`, `config`: files whose path and sha256 are kept. `fields`: any
    other `RunRecord` field (`plan`, `step`, `verdict`, `controller`, `controller_params`,
    `specimen`, `tags`, `operator`, `et`, ...), over the summary's.
    CatalogError where the catalog (and the spool) cannot take it."""
    from mrrig.catalog import RunRecord, summary_numbers
    from mrrig.catalog import register_run as register
    from mrrig.rigio.run_identity import file_sha256, operator_of

    values: dict[str, Any] = summary_numbers(summary) if summary is not None else {}
    values |= {"run_id": fields.pop("run_id", None) or uuid.uuid4(), "operator": operator_of(None)}
    if model is not None:
        values |= {"model_path": str(model), "model_sha256": file_sha256(model)}
    if config is not None:
        values["config_sha256"] = file_sha256(config)
    if recording is not None:
        path = Path(recording).resolve()
        values |= {
            "recording_path": str(path),
            "recording_size_bytes": path.stat().st_size,
            "recording_sha256": file_sha256(path),
        }
    record = RunRecord(rig=rig, started_utc=started_utc, **(values | fields))
    register(catalog or default_catalog(), record, spool_url=spool)
    return record


def register_recording(
    recording: str | Path, catalog: str | Path | None = None
) -> tuple[RunRecord, bool]:
    """Register the run that a daemon's recording carries (its identity, and its summary: a
    recording without one is a run that crashed or was killed, registered `crashed`), ended
    when the file was last written. Idempotent: a run the catalog has is left as it is.
    Returns (the record, whether it was added). CatalogError where the recording has no
    run identity (a recording from before runs had one, or not a daemon's)."""
    import datetime as dt

    from mrrig.catalog import CatalogError
    from mrrig.catalog import register_run as register
    from mrrig.catalog.finished import run_record
    from mrrig.catalog.store import has_run
    from mrrig.offline.review import read_recording

    path = Path(recording)
    rec = read_recording(path)
    if not rec.identity:
        raise CatalogError(f"{path}: carries no run identity (written before runs had one?)")
    catalog = catalog or default_catalog()
    ended = dt.datetime.fromtimestamp(path.stat().st_mtime, dt.UTC)
    record = run_record(rec.identity, rec.summary, path, ended_utc=ended)
    if has_run(catalog, record.run_id):
        return record, False
    register(catalog, record)
    return record, True


def replay_journals(
    catalog: str | Path | None = None, folder: str | Path | None = None
) -> tuple[int, int]:
    """Register the runs journalled in `folder` (default: an SQLite catalog's own folder)
    because their catalog could not take them (locked, corrupt, unreachable), each into the
    catalog its journal names. Returns (registered, still journalled)."""
    from mrrig.catalog.journal import replay
    from mrrig.catalog.store import catalog_url

    if folder is None:
        url = catalog_url(catalog or default_catalog())
        if url.get_backend_name() != "sqlite":
            return 0, 0
        folder = Path(url.database or "").parent
    report = replay(folder)
    return report.registered, report.kept


def compare_figure(
    a: RunRecord | str, b: RunRecord | str, out_png: str | Path, catalog: str | Path | None = None
) -> Path:
    """One figure (PNG) with both runs, through `mrrig review`'s plotting: each run's desired
    and measured force, tracking error and current from its first armed frame, and its armed
    force-velocity loop. A run is a `RunRecord` or a run id (4+ digits). A step's run is cut
    from its daemon's recording by the step's UTC start and end. CatalogError where a run's
    recording is not there."""
    from mrrig.api.live import Recording
    from mrrig.catalog import CatalogError
    from mrrig.offline.review_report import plot_compare

    drawn = []
    for name, run in (("A", a), ("B", b)):
        run = run if not isinstance(run, str) else get_run(run, catalog)
        if not run.recording_path or not Path(run.recording_path).is_file():
            raise CatalogError(
                f"run {name} {str(run.run_id)[:8]}: no recording to plot ({check_recording(run)})"
            )
        rec = Recording(run.recording_path)
        s = rec.samples
        if rec.identity and rec.identity.get("run_id") != str(run.run_id) and rec.utc_start:
            t0 = (run.started_utc - rec.utc_start).total_seconds()
            t1 = (run.ended_utc - rec.utc_start).total_seconds() if run.ended_utc else None
            s = s[(s["t"] >= t0) & ((s["t"] <= t1) if t1 is not None else True)]
        part = "/".join(x for x in (run.plan, run.step) if x)
        et = "n/a" if run.et is None else f"{run.et:.4f}"
        label = f"{name} {str(run.run_id)[:8]} {run.rig}{' ' + part if part else ''}, Et {et}"
        lo, hi = (s["t"][0], s["t"][-1]) if s.size else (0.0, -1.0)
        events = [e for e in rec.events if e.get("t") is not None and lo <= e["t"] <= hi]
        drawn.append((label, s, events))
    return plot_compare(drawn, out_png)
