"""The run catalog: every run's identity and numbers in one table, in SQLite (a rig's
`recordings/catalog.sqlite`) or PostgreSQL (a lab's shared catalog), found again by rig,
specimen, campaign, plan, controller, time and numbers (`mrrig runs`).

    from mrrig.catalog import RunRecord, register_run, find_runs, get_run, sync

    register_run("recordings/catalog.sqlite", record)
    for run in find_runs("postgresql://lab-db/mrrig", specimen="SN1234", where="et < 0.05"):
        print(run.run_id, run.started_utc, run.et)
"""

from mrrig.catalog.query import QueryError, parse_since, parse_where
from mrrig.catalog.record import (
    CHARACTERIZATION_PLAN,
    NUMERIC_COLUMNS,
    RecordError,
    RunRecord,
    summary_numbers,
)
from mrrig.catalog.store import (
    DEFAULT_PATH,
    CatalogError,
    CatalogUnreachable,
    Registration,
    SyncReport,
    find_runs,
    get_run,
    register_run,
    register_runs,
    sync,
)

__all__ = [
    "CHARACTERIZATION_PLAN",
    "DEFAULT_PATH",
    "NUMERIC_COLUMNS",
    "CatalogError",
    "CatalogUnreachable",
    "QueryError",
    "RecordError",
    "Registration",
    "RunRecord",
    "SyncReport",
    "find_runs",
    "get_run",
    "parse_since",
    "parse_where",
    "register_run",
    "register_runs",
    "summary_numbers",
    "sync",
]
