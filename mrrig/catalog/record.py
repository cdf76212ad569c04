"""`RunRecord`: one run's identity and numbers, as the catalog keeps them (spec/system.md, "Runs,
plans and the catalog"). Plain values only; the database's row is `to_row()`/`from_row()`.

Units: times are timezone-aware UTC datetimes, Et is dimensionless (eqs 41-43), latencies in
microseconds, current in amperes, temperature in degrees Celsius, sizes in bytes.
"""

from __future__ import annotations

import dataclasses
import getpass
import math
import re
import socket
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib import metadata
from typing import Any

from mrrig.errors import MrrigError
from mrrig.safe_text import one_line

# the plan name of characterization runs (`mrrig characterize`: constant currents, whose Et
# means nothing): `mrrig runs` leaves them out unless asked
CHARACTERIZATION_PLAN = "characterize"


class RecordError(MrrigError, ValueError):
    """A run record that the catalog cannot keep (a naive time, a bad sha256, ...)."""


_SHA256 = re.compile(r"[0-9a-fA-F]{64}")
# who and what, as given or claimed (a host, a user, a plan's step name): kept as one printable,
# bounded line (`safe_text.one_line`), for `mrrig runs` prints them on a terminal
_TEXT_FIELDS = (
    "rig",
    "host",
    "specimen",
    "operator",
    "plan",
    "step",
    "controller",
    "verdict",
    "campaign",
)

# the summary numbers a query may compare (`mrrig runs --where "et < 0.01"`): column -> unit
NUMERIC_COLUMNS: dict[str, str] = {
    "et": "",
    "faults_count": "",
    "latency_p50_us": "us",
    "latency_p99_us": "us",
    "peak_current_a": "A",
    "temp_max_degc": "degC",
    "duration_s": "s",
    "recording_size_bytes": "B",
}


def _local_user() -> str:
    try:
        return getpass.getuser()
    except (OSError, KeyError):  # no user name in the environment nor in the password file
        return ""


def _mrrig_version() -> str:
    try:
        return metadata.version("mrrig")
    except metadata.PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class RunRecord:
    """One run: who ran what, where, when, with which software, and how it went.

    `run_id` is the run's UUID. `host`, `operator` (the local user, unless the caller knows
    better: a certificate's CN) and `mrrig_version` default to this process's.
    `started_utc`/`ended_utc` are wall-clock times (aware, any zone: kept as UTC).
    `controller_params` is the controller's parameters as JSON values. sha256 fields are 64
    hex digits. `et` is the normalized tracking error (eqs 41-43, dimensionless),
    `latency_p50_us`/`latency_p99_us` the daemon's receive-to-send latency (us),
    `peak_current_a` the largest commanded current (A), `temp_max_degc` the damper's highest
    temperature (degC); None where the run has no such number (NaN in a summary). `campaign`
    names the test campaign the run is part of (a plan's steps, a characterization matrix).
    """

    run_id: uuid.UUID
    rig: str
    started_utc: datetime
    host: str = field(default_factory=socket.gethostname)
    specimen: str | None = None
    operator: str = field(default_factory=_local_user)
    plan: str | None = None
    step: str | None = None
    ended_utc: datetime | None = None
    controller: str = ""
    controller_params: dict[str, Any] = field(default_factory=dict)
    model_path: str | None = None
    model_sha256: str | None = None
    config_sha256: str | None = None
    dbc_sha256: str | None = None
    mrrig_version: str = field(default_factory=_mrrig_version)
    et: float | None = None
    faults_count: int = 0
    faults: list[dict[str, Any]] = field(default_factory=list)
    latency_p50_us: float | None = None
    latency_p99_us: float | None = None
    peak_current_a: float | None = None
    temp_max_degc: float | None = None
    verdict: str | None = None
    recording_path: str | None = None
    recording_size_bytes: int | None = None
    recording_sha256: str | None = None
    tags: list[str] = field(default_factory=list)
    campaign: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.run_id, uuid.UUID):
            object.__setattr__(self, "run_id", _uuid(self.run_id))
        if not self.rig:
            raise RecordError(f"run {self.run_id}: rig: empty")
        for name in _TEXT_FIELDS:
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, one_line(value))
        object.__setattr__(self, "tags", [one_line(tag) for tag in self.tags])
        for name in ("started_utc", "ended_utc"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _utc(value, name, self.run_id))
        for name in ("model_sha256", "config_sha256", "dbc_sha256", "recording_sha256"):
            value = getattr(self, name)
            if value is not None and not _is_sha256(value):
                raise RecordError(
                    f"run {self.run_id}: {name}: expected 64 hex digits, got {value!r}"
                )
            if value is not None:
                object.__setattr__(self, name, value.lower())
        for name in NUMERIC_COLUMNS:
            if name in ("duration_s", "faults_count", "recording_size_bytes"):
                continue
            value = getattr(self, name)
            # NaN is "undefined" in the summary (Et of a constant target): no number here
            if value is not None and not math.isfinite(float(value)):
                object.__setattr__(self, name, None)

    @property
    def duration_s(self) -> float | None:
        """Wall-clock duration (s), where the run has ended."""
        if self.ended_utc is None:
            return None
        return (self.ended_utc - self.started_utc).total_seconds()

    def to_row(self) -> dict[str, Any]:
        """The catalog's row: the fields, the run id as text, times as naive UTC."""
        row = dataclasses.asdict(self)
        row["run_id"] = str(self.run_id)
        row["started_utc"] = self.started_utc.replace(tzinfo=None)
        row["ended_utc"] = self.ended_utc.replace(tzinfo=None) if self.ended_utc else None
        row["duration_s"] = self.duration_s
        return row

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> RunRecord:
        """The record of a catalog row (`to_row`'s inverse; extra columns are left out). The
        row was checked when it was written and is not checked again: `mrrig runs` reads
        thousands of them."""
        values = {name: row[name] for name in _FIELDS}
        values["run_id"] = uuid.UUID(values["run_id"])
        for name in ("started_utc", "ended_utc"):
            if values[name] is not None:
                values[name] = values[name].replace(tzinfo=UTC)
        for name, empty in (("controller_params", dict), ("faults", list), ("tags", list)):
            if values[name] is None:
                values[name] = empty()
        record = object.__new__(cls)
        record.__dict__.update(values)  # a frozen dataclass: no __setattr__ after __init__
        return record

    def to_json(self) -> dict[str, Any]:
        """JSON values: times as ISO 8601 with +00:00, the run id as text."""
        out = dataclasses.asdict(self)
        out["run_id"] = str(self.run_id)
        out["started_utc"] = self.started_utc.isoformat()
        out["ended_utc"] = self.ended_utc.isoformat() if self.ended_utc else None
        out["duration_s"] = self.duration_s
        return out

    @classmethod
    def from_json(cls, values: Mapping[str, Any]) -> RunRecord:
        """The record of `to_json`'s values (checked as a new record is; `duration_s` and
        unknown keys are left out). RecordError where they are not a run's."""
        fields = {name: values[name] for name in _FIELDS if name in values}
        for name in ("started_utc", "ended_utc"):
            if isinstance(fields.get(name), str):
                try:
                    fields[name] = datetime.fromisoformat(fields[name])
                except ValueError:
                    raise RecordError(f"{name}: not an ISO time: {fields[name]!r}") from None
        try:
            return cls(**fields)
        except TypeError as exc:  # a required field missing
            raise RecordError(f"not a run record: {exc}") from None


_FIELDS = frozenset(f.name for f in dataclasses.fields(RunRecord))


def summary_numbers(summary: Mapping[str, Any]) -> dict[str, Any]:
    """The record's numbers from a run summary (`mrrig.loop.summary`): Et, the faults, the
    latency percentiles (us), the peak commanded current (A) and, where the summary has it,
    the highest temperature (degC). Pass them on: `RunRecord(..., **summary_numbers(s))`."""
    faults = list(summary.get("faults") or [])
    latency = summary.get("latency_us") or {}
    temp = summary.get("temp_degc")
    return {
        "et": summary.get("et"),
        "faults_count": len(faults),
        "faults": faults,
        "latency_p50_us": latency.get("p50"),
        "latency_p99_us": latency.get("p99"),
        "peak_current_a": (summary.get("i_cmd_a") or {}).get("max"),
        "temp_max_degc": temp.get("max") if isinstance(temp, Mapping) else None,
    }


def _uuid(value: Any) -> uuid.UUID:
    try:
        return uuid.UUID(str(value))
    except ValueError:
        raise RecordError(f"run_id: not a UUID: {value!r}") from None


def _utc(value: datetime, name: str, run_id: uuid.UUID) -> datetime:
    if not isinstance(value, datetime):
        raise RecordError(f"run {run_id}: {name}: expected a datetime, got {value!r}")
    if value.tzinfo is None or value.utcoffset() is None:
        raise RecordError(f"run {run_id}: {name}: a naive time; give its zone (UTC)")
    return value.astimezone(UTC)


def _is_sha256(value: Any) -> bool:
    return isinstance(value, str) and _SHA256.fullmatch(value) is not None
