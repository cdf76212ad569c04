"""A run's recording in the formats a lab's tools read: Parquet, CSV and MDF4 (`mrrig export`),
and Parquet and MDF4 read back as a `Recording` (`mrrig review`, `mrrig evaluate`).

Every format holds the same columns, named with their units (`COLUMNS`: `t_s`, `x_m`,
`force_n`, `i_cmd_a`, ...), and an absolute UTC time: the run identity's `started_utc` (the
daemon's start, taken just before its loop clock starts: within milliseconds) plus the sample's
sensor time `t_s`. A recording without identity (made before runs had one) takes the UTC time
in its file name (`<rig>-YYYYmmddTHHMMSSZ.rrd`, the recorder's start, to 1 s), else the file's
modification time less the last sample's `t_s` (the recorder closes at the run's end); the
metadata's `utc_source` says which.

- Parquet: each field's metadata holds `unit`, `description` and the sample `field`; the
  schema's metadata `mrrig` holds the run's identity, summary, events and `utc_source` (JSON).
- MDF4: one channel group, master channel `t_s` (the sensor time, s), a channel per column with
  its unit and comment, the header's start time the UTC start; the same JSON as an embedded
  attachment `mrrig.json`.
- CSV: a `#` preamble (one line of the same JSON, then one line per column with its unit and
  description), then a header of the unit-named columns; `utc` as ISO 8601 to the microsecond.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mrrig import json_text
from mrrig.errors import MrrigError
from mrrig.loop.samples import SAMPLE_DTYPE, RigState

if TYPE_CHECKING:
    from mrrig.offline.review import Recording

log = logging.getLogger(__name__)

FORMATS = ("parquet", "csv", "mf4")
# the files `read_any` reads, by suffix
RECORDING_SUFFIXES = (".rrd", ".parquet", ".mf4")
META_KEY = "mrrig"
MDF_ATTACHMENT = "mrrig.json"
UTC_COLUMN = "utc"
_STATES = ", ".join(f"{s.value} {s.name}" for s in RigState)


@dataclass(frozen=True)
class Column:
    """One sample field as exported: its column name (with the unit), unit and meaning."""

    field: str
    name: str
    unit: str
    description: str


COLUMNS: tuple[Column, ...] = (
    Column("t", "t_s", "s", "sensor time since the daemon started (frame receive time)"),
    Column("counter", "counter", "", "E2E counter of the RigSensors frame answered"),
    Column("x", "x_m", "m", "measured displacement"),
    Column("x_est", "x_est_m", "m", "Kalman-filtered displacement"),
    Column("xd", "xd_m_s", "m/s", "estimated velocity"),
    Column("xdd", "xdd_m_s2", "m/s^2", "estimated acceleration"),
    Column("f_meas", "force_n", "N", "load-cell force"),
    Column("f_des", "f_des_n", "N", "desired force"),
    Column("f_model", "f_model_n", "N", "forward-model force at the commanded current"),
    Column("i_cmd", "i_cmd_a", "A", "commanded coil current (0 when SAFE)"),
    Column("i_meas", "i_meas_a", "A", "measured coil current (latest RigStatus)"),
    Column("latency_us", "latency_us", "us", "receive to send of this cycle"),
    Column("adapt_gain", "adapt_gain", "1", "on-line adaptation's gain on the model (NaN: none)"),
    Column("adapt_offset_n", "adapt_offset_n", "N", "on-line adaptation's force offset"),
    Column("temp_degc", "temp_degc", "degC", "damper temperature (latest RigStatus)"),
    Column("state", "state", "", f"the daemon's safety state ({_STATES})"),
    Column("outside", "outside", "", "inputs outside the model's envelope (NaN: none kept)"),
    Column("hil_k", "hil_k", "", "hybrid simulation: the model's frame index (NaN: none)"),
    Column("hil_x_c", "hil_x_c_m", "m", "hybrid simulation: the model's stroke x_c"),
    Column("hil_setpoint", "hil_setpoint_m", "m", "hybrid simulation: the setpoint sent"),
    Column("hil_delay_s", "hil_delay_s", "s", "hybrid simulation: the delay estimate"),
    Column("hil_acc", "hil_acc_m_s2", "m/s^2", "hybrid simulation: body (roof) acceleration"),
    Column("hil_load_n", "hil_load_n", "N", "hybrid simulation: dynamic tyre load"),
    Column("hil_z_body", "hil_z_body_m", "m", "hybrid simulation: the body's displacement"),
    Column("hil_v_body", "hil_v_body_m_s", "m/s", "hybrid simulation: the body's velocity"),
    Column("hil_z_wheel", "hil_z_wheel_m", "m", "hybrid simulation: the wheel's displacement"),
    Column("hil_v_wheel", "hil_v_wheel_m_s", "m/s", "hybrid simulation: the wheel's velocity"),
    Column("hil_drift_2", "hil_drift_2_m", "m", "hybrid simulation: storey 2's drift"),
    Column("hil_drift_3", "hil_drift_3_m", "m", "hybrid simulation: storey 3's drift"),
)
UTC_DESCRIPTION = "absolute time, UTC: the run's UTC start plus t_s"
_NAME_UTC = re.compile(r"-(\d{8}T\d{6}Z)$")


class ExportError(MrrigError, ValueError):
    """An export that cannot be written or a file that cannot be read back; one line naming
    the file."""


def utc_start(rec: Recording) -> tuple[dt.datetime | None, str]:
    """The UTC time at `t = 0` of the recording's samples, and where it comes from."""
    started = (rec.identity or {}).get("started_utc")
    if started:
        try:
            return dt.datetime.fromisoformat(started).astimezone(dt.UTC), "run identity started_utc"
        except ValueError:
            log.warning("%s: run identity's started_utc %r is not a time", rec.path, started)
    m = _NAME_UTC.search(rec.path.stem)
    if m:
        t0 = dt.datetime.strptime(m.group(1), "%Y%m%dT%H%M%SZ").replace(tzinfo=dt.UTC)
        return t0, "file name (the recorder's start, to 1 s; no run identity in the recording)"
    if rec.samples.size and rec.path.is_file():
        end = dt.datetime.fromtimestamp(rec.path.stat().st_mtime, dt.UTC)
        t_last = float(rec.samples["t"][-1])
        return end - dt.timedelta(seconds=t_last), (
            "file modification time less the last t_s (no run identity, no time in the name)"
        )
    return None, "none: no run identity, no time in the file name, no samples"


def utc_ns(t: np.ndarray, t0: dt.datetime) -> np.ndarray:
    """Nanoseconds since the Unix epoch, UTC (int64), of sensor times `t` (s) after `t0`."""
    base = int(t0.timestamp()) * 1_000_000_000 + t0.microsecond * 1000
    return base + np.round(t * 1e9).astype(np.int64)


def _meta(rec: Recording, utc_source: str, t0: dt.datetime | None) -> str:
    """The run's identity, summary and events, strict JSON (an undefined number is null)."""
    return json_text.dumps(
        {
            "source": rec.path.name,
            "identity": rec.identity,
            "summary": rec.summary,
            "events": rec.events,
            "utc_start": t0.isoformat() if t0 else None,
            "utc_source": utc_source,
            "columns": {c.name: {"unit": c.unit, "field": c.field} for c in COLUMNS},
        }
    )


def default_out(recording: Path, fmt: str) -> Path:
    """The export beside the recording: `run.rrd` -> `run.parquet`, `run.csv`, `run.mf4`."""
    return recording.with_suffix(f".{fmt}")


def export(rec: Recording, fmt: str, out: Path, force: bool = False) -> Path:
    """Write `rec` as `fmt` (one of `FORMATS`) to `out`; returns `out`. A file there already
    is replaced only with `force`; a link, a catalog or a recording never (`OutputError`,
    `mrrig.export.target`)."""
    from mrrig.export.target import OutputError, write_new

    if fmt not in FORMATS:
        raise ExportError(f"{out}: unknown export format {fmt!r} (one of {', '.join(FORMATS)})")
    t0, source = utc_start(rec)
    if t0 is None:
        log.warning("%s: no UTC start: the utc column is empty (%s)", rec.path, source)
    writer = {"parquet": _write_parquet, "csv": _write_csv, "mf4": _write_mf4}[fmt]
    try:
        write_new(out, force, lambda tmp: writer(rec, tmp, t0, _meta(rec, source, t0)))
    except OutputError:
        raise
    except OSError as e:
        raise ExportError(f"{out}: cannot write: {e.strerror or e}") from e
    return out


def _write_parquet(rec: Recording, out: Path, t0: dt.datetime | None, meta: str) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    s = rec.samples
    fields = [
        pa.field(
            UTC_COLUMN,
            pa.timestamp("ns", tz="UTC"),
            metadata={"unit": "UTC", "description": UTC_DESCRIPTION},
        )
    ]
    utc_type = pa.timestamp("ns", tz="UTC")
    if t0 is None:
        arrays = [pa.nulls(s.size, utc_type)]
    else:
        arrays = [pa.array(utc_ns(s["t"], t0), type=pa.int64()).cast(utc_type)]
    for c in COLUMNS:
        arrays.append(pa.array(s[c.field]))
        fields.append(
            pa.field(
                c.name,
                arrays[-1].type,
                metadata={"unit": c.unit, "description": c.description, "field": c.field},
            )
        )
    schema = pa.schema(fields, metadata={META_KEY: meta})
    pq.write_table(pa.Table.from_arrays(arrays, schema=schema), out)


def _write_csv(rec: Recording, out: Path, t0: dt.datetime | None, meta: str) -> None:
    import pandas as pd

    frame = pd.DataFrame({c.name: rec.samples[c.field] for c in COLUMNS})
    utc = pd.to_datetime(utc_ns(rec.samples["t"], t0), utc=True) if t0 else pd.NaT
    frame.insert(0, UTC_COLUMN, utc)
    with out.open("w", newline="") as f:
        f.write(f"# mrrig export of {rec.path.name}; metadata (JSON) on the next line\n")
        f.write(f"# {META_KEY}: {meta}\n")
        f.write(f"# {UTC_COLUMN} [UTC]: {UTC_DESCRIPTION}\n")
        for c in COLUMNS:
            f.write(f"# {c.name} [{c.unit or '-'}]: {c.description}\n")
        frame.to_csv(f, index=False, date_format="%Y-%m-%dT%H:%M:%S.%fZ")


def _write_mf4(rec: Recording, out: Path, t0: dt.datetime | None, meta: str) -> None:
    from asammdf import MDF, Signal

    s = rec.samples
    t = np.ascontiguousarray(s["t"])
    mdf = MDF(version="4.10")
    if t0 is not None:
        mdf.header.start_time = t0
    utc_s = utc_ns(s["t"], t0) / 1e9 if t0 else np.full(s.size, np.nan)
    signals = [
        Signal(utc_s, t, name="utc_unix_s", unit="s", comment=f"{UTC_DESCRIPTION}, Unix time")
    ]
    signals += [
        Signal(np.ascontiguousarray(s[c.field]), t, name=c.name, unit=c.unit, comment=c.description)
        for c in COLUMNS
        if c.field != "t"
    ]
    mdf.append(signals, comment=f"mrrig samples of {rec.path.name}; master channel t_s (s)")
    mdf.groups[0].channels[0].name = "t_s"
    mdf.groups[0].channels[0].comment = COLUMNS[0].description
    mdf.attach(meta.encode(), file_name=MDF_ATTACHMENT, mime="application/json", embedded=True)
    mdf.save(out, overwrite=True)
    mdf.close()


def read_any(path: str | Path) -> Recording:
    """A run from its `.rrd`, or from a Parquet or MDF4 export of it (by suffix)."""
    # rerun is slow to import: only .rrd files pay for it
    from mrrig.offline.review import read_recording

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".parquet":
        return read_parquet(path)
    if suffix == ".mf4":
        return read_mf4(path)
    return read_recording(path)


def _recording(path: Path, meta: dict[str, Any], samples: np.ndarray) -> Recording:
    from mrrig.offline.review import Recording

    return Recording(
        path=path,
        samples=samples,
        events=meta.get("events") or [],
        summary=meta.get("summary"),
        identity=meta.get("identity"),
    )


def _load_meta(path: Path, text: bytes | str | None) -> dict[str, Any]:
    if text is None:
        raise ExportError(f"{path}: not an mrrig export (no '{META_KEY}' metadata)")
    try:
        meta = json.loads(text)
    except ValueError as e:
        raise ExportError(f"{path}: its '{META_KEY}' metadata is not JSON: {e}") from e
    if not isinstance(meta, dict):
        raise ExportError(f"{path}: its '{META_KEY}' metadata is not a JSON object")
    return meta


def read_parquet(path: Path) -> Recording:
    """A run from its Parquet export (columns found by their `field` metadata)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if not path.is_file():
        raise ExportError(f"{path}: no such file")
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError) as e:
        raise ExportError(f"{path}: not a readable Parquet file: {e}") from e
    meta = _load_meta(path, (table.schema.metadata or {}).get(META_KEY.encode()))
    samples = np.empty(table.num_rows, dtype=SAMPLE_DTYPE)
    for c in COLUMNS:
        if c.name not in table.column_names:
            raise ExportError(f"{path}: no column {c.name!r} ({c.description}, {c.unit})")
        col = table.column(c.name).to_numpy()
        samples[c.field] = col.astype(SAMPLE_DTYPE[c.field])
    return _recording(path, meta, samples)


def read_mf4(path: Path) -> Recording:
    """A run from its MDF4 export (channels by their unit-named names)."""
    from asammdf import MDF

    if not path.is_file():
        raise ExportError(f"{path}: no such file")
    try:
        mdf = MDF(path)
    except Exception as e:  # noqa: BLE001 - asammdf raises many kinds on a foreign file
        raise ExportError(f"{path}: not a readable MDF file: {e}") from e
    try:
        text = None
        for k, att in enumerate(mdf.attachments):
            if Path(str(att.file_name)).name == MDF_ATTACHMENT:
                text = mdf.extract_attachment(k)[0]
        meta = _load_meta(path, text)
        names = set(mdf.channels_db)
        first = COLUMNS[1]
        if first.name not in names:
            raise ExportError(f"{path}: no channel {first.name!r} ({first.description})")
        t = mdf.get(first.name).timestamps
        samples = np.empty(t.size, dtype=SAMPLE_DTYPE)
        samples["t"] = t
        for c in COLUMNS[1:]:
            if c.name not in names:
                raise ExportError(f"{path}: no channel {c.name!r} ({c.description}, {c.unit})")
            samples[c.field] = mdf.get(c.name).samples.astype(SAMPLE_DTYPE[c.field])
    finally:
        mdf.close()
    return _recording(path, meta, samples)
