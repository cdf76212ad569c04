"""A finished daemon run's record: the identity the daemon made at start-up
(`mrrig.rigio.run_identity`), the summary it sent at its end and its recording. Made by the
sidecar when the loop has ended, and by `mrrig runs register REC` from what a recording
carries.

The verdict comes from the summary's exit code (`mrrig.loop.exit_codes.Exit`). A run is `ok`
only where its summary says it ended normally: a daemon that raised (the summary's `crashed`)
or ended without a summary (killed, or crashed before it could send one) is `crashed`.
"""

from __future__ import annotations

import datetime as dt
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from mrrig.catalog.record import RecordError, RunRecord, summary_numbers

log = logging.getLogger("mrrig.catalog")

# a daemon run's verdict in the catalog, from its exit code (mrrig.loop.exit_codes.Exit)
RUN_VERDICTS = {0: "ok", 1: "fault", 3: "bus_lost", 4: "telemetry_lost"}
CRASHED = "crashed"
# the identity's keys that are not the record's (where the sidecar registers it)
_ROUTING = ("catalog", "catalog_spool")


def verdict_of(summary: Mapping[str, Any] | None) -> str:
    """The catalog's verdict of a run that ended with `summary` (None: it sent none)."""
    if summary is None or summary.get("crashed"):
        return CRASHED
    return RUN_VERDICTS.get(summary.get("exit_code"), "error")


def run_record(
    ident: Mapping[str, Any],
    summary: Mapping[str, Any] | None,
    recording: Path | None,
    ended_utc: dt.datetime | None = None,
) -> RunRecord:
    """The record of the run `ident`, ended with `summary` (None where the daemon sent none:
    no numbers, verdict `crashed`) at `ended_utc` (default now), with the recording's path,
    size and sha256 where it is a file. RecordError where `ident` is not a run's identity."""
    from mrrig.rigio.run_identity import file_sha256

    fields = {k: v for k, v in ident.items() if k not in _ROUTING}
    exists = recording is not None and recording.is_file()
    numbers = summary_numbers(summary) if summary is not None else {}
    if summary is not None and summary.get("crashed"):
        numbers["faults"] = [*numbers["faults"], {"fault": CRASHED, "reason": summary["crashed"]}]
        numbers["faults_count"] += 1
    try:
        fields["started_utc"] = dt.datetime.fromisoformat(fields["started_utc"])
        return RunRecord(
            **fields,
            ended_utc=ended_utc or dt.datetime.now(dt.UTC),
            verdict=verdict_of(summary),
            recording_path=str(recording.resolve()) if exists else None,
            recording_size_bytes=recording.stat().st_size if exists else None,
            recording_sha256=file_sha256(recording) if exists else None,
            **numbers,
        )
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, RecordError):
            raise
        raise RecordError(f"run {ident.get('run_id')}: not a run's identity: {exc}") from None
