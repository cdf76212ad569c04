"""Reading a run's .rrd back: samples, events and summary; checking it; a PNG for people
without a viewer.

The layout read here is the one `mrrig.rigio.recording` writes (see its module docstring).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import rerun as rr

from mrrig.errors import MrrigError
from mrrig.loop.samples import SAMPLE_DTYPE
from mrrig.rigio.recording import (
    EVENT_TIMELINE,
    EVENTS_ENTITY,
    FIELD_ENTITIES,
    FRAME_TIMELINE,
    LATER_FIELDS,
    RUN_ENTITY,
    SUMMARY_ENTITY,
)

log = logging.getLogger(__name__)

_DATASET = "run"
RRD_MAGIC = b"RRF2"  # the FourCC an .rrd file starts with (rerun-sdk 0.41, as pinned)


class ReviewError(MrrigError, ValueError):
    """A recording that cannot be read or checked; the message is one line naming the file."""


@dataclasses.dataclass
class Recording:
    """A run read back from its .rrd file."""

    path: Path
    samples: np.ndarray  # SAMPLE_DTYPE, sorted by t
    events: list[dict[str, Any]]  # t, level, text, plus the extra fields (kind, reason, ...)
    summary: dict[str, Any] | None  # what `Recorder.add_summary` stored, or None
    # the run's identity (run id, rig, specimen, model and config sha256, ...), where recorded
    identity: dict[str, Any] | None = None


def _read_field(dataset: Any, entity: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Frame numbers and values of one scalar entity (one query per entity: much faster than
    one query joining all of them)."""
    name = f"/{entity}:Scalars:scalars"
    table = (
        dataset.filter_contents([f"/{entity}"])
        .reader(index=FRAME_TIMELINE)
        .select(FRAME_TIMELINE, name)
        .to_arrow_table()
    )
    frames = table.column(FRAME_TIMELINE).to_numpy()
    lists = table.column(name).combine_chunks()
    lengths = lists.value_lengths().fill_null(0).to_numpy(zero_copy_only=False)
    if not (lengths == 1).all():
        log.warning("%s: %s has %d rows without one value", path, entity, (lengths != 1).sum())
        keep = lengths == 1
        frames, lists = frames[keep], lists.filter(pa.array(keep))
    return frames, lists.flatten().to_numpy(zero_copy_only=False)


def _rebuild_samples(dataset: Any, path: Path) -> np.ndarray:
    """Samples from the per-field entities, aligned on the frame timeline. Frames missing a
    field (a writer killed mid-flush) are dropped."""
    columns = {}
    absent = []
    for field, entity in FIELD_ENTITIES.items():
        try:
            columns[field] = _read_field(dataset, entity, path)
        except Exception:  # noqa: BLE001 - the query's own error for an entity never logged
            if field not in LATER_FIELDS:
                raise
            absent.append(field)  # a recording made before the field existed
    n = max((int(f.max()) + 1 for f, _ in columns.values() if f.size), default=0)
    complete = np.ones(n, dtype=bool)
    for frames, _ in columns.values():
        present = np.zeros(n, dtype=bool)
        present[frames] = True
        complete &= present
    if not complete.all():
        log.warning("%s: %d frames with missing fields dropped", path, int((~complete).sum()))
    samples = np.empty(int(complete.sum()), dtype=SAMPLE_DTYPE)
    for field, (frames, values) in columns.items():
        full = np.empty(n)
        full[frames] = values
        samples[field] = full[complete].astype(SAMPLE_DTYPE[field])
    for field in absent:
        samples[field] = np.nan
    return samples[np.argsort(samples["t"], kind="stable")]


def _rebuild_events(table: pa.Table) -> list[dict[str, Any]]:
    events = []
    for row in table.select(
        [
            f"/{EVENTS_ENTITY}:t_s",
            f"/{EVENTS_ENTITY}:TextLog:level",
            f"/{EVENTS_ENTITY}:TextLog:text",
            f"/{EVENTS_ENTITY}:fields",
        ]
    ).to_pylist():
        t_s, level, text, fields = (v[0] if v else None for v in row.values())
        events.append({"t": t_s, "level": level, "text": text, **json.loads(fields or "{}")})
    return events


def read_recording(path: str | Path) -> Recording:
    """Read a recording written by `Recorder`.

    A file without footer (writer killed before `close()`) still gives what reached the
    disk; `rerun rrd optimize IN -o OUT` rewrites it with a footer. Serves the file with a
    local Rerun server on 127.0.0.1 (random port) for the query and shuts it down before
    returning.
    """
    path = Path(path)
    if not path.is_file():
        raise ReviewError(f"{path}: no such file")
    with path.open("rb") as f:
        head = f.read(len(RRD_MAGIC))
    if head != RRD_MAGIC:
        # before the reader, which would log its own warning besides this error
        raise ReviewError(f"{path}: not an .rrd file (it starts {head!r}, not {RRD_MAGIC!r})")
    try:
        server = rr.server.Server(host="127.0.0.1", datasets={_DATASET: [path]})
    except Exception as e:
        raise ReviewError(f"{path}: cannot serve the recording: {e}") from e
    try:
        dataset = server.client().get_dataset(_DATASET)
        schema = dataset.schema()
        indexes = {c.name for c in schema.index_columns()}
        entities = set(schema.entity_paths())
        if not entities:
            raise ReviewError(
                f"{path}: not a readable RRD (not an .rrd file, truncated, or without footer;"
                " see `rerun rrd verify`)"
            )
        ours = {f"/{e}" for e in FIELD_ENTITIES.values()} | {f"/{SUMMARY_ENTITY}", "/rig"}
        if not entities & ours:
            shown = ", ".join(sorted(entities)[:5]) + (", ..." if len(entities) > 5 else "")
            raise ReviewError(
                f"{path}: not an mrrig recording: a Rerun file of another application (its"
                f" entities {shown}; an mrrig recording has /rig and the rig's series)"
            )
        if FRAME_TIMELINE in indexes:
            samples = _rebuild_samples(dataset, path)
        else:
            samples = np.empty(0, dtype=SAMPLE_DTYPE)
        events: list[dict[str, Any]] = []
        if EVENT_TIMELINE in indexes:
            events_table = (
                dataset.filter_contents([f"/{EVENTS_ENTITY}"])
                .reader(index=EVENT_TIMELINE)
                .to_arrow_table()
            )
            events = _rebuild_events(events_table)
        summary = _static_json(dataset, entities, SUMMARY_ENTITY)
        identity = _static_json(dataset, entities, RUN_ENTITY)
    except ReviewError:
        raise
    except Exception as e:
        raise ReviewError(
            f"{path}: cannot read the recording (truncated? `rerun rrd verify` checks it): {e}"
        ) from e
    finally:
        server.shutdown()
    return Recording(path=path, samples=samples, events=events, summary=summary, identity=identity)


def _static_json(dataset: Any, entities: set[str], entity: str) -> dict[str, Any] | None:
    """The JSON of a static TextDocument (the summary, the run's identity), or None."""
    if f"/{entity}" not in entities:
        return None
    static = dataset.filter_contents([f"/{entity}"]).reader(index=None).to_arrow_table()
    return json.loads(static.column(f"/{entity}:TextDocument:text")[0][0].as_py())


_VERIFIED_RE = re.compile(r"(\d+) files? verified without error")


def verify_rrd(path: str | Path) -> None:
    """Check a file with `rerun rrd verify`; raise ReviewError unless it reports it fine.

    The CLI exits 0 on a non-RRD file ("0 files verified"), so its output is what counts.
    """
    path = Path(path)
    if not path.is_file():
        raise ReviewError(f"{path}: no such file")
    rerun_cli = Path(sys.executable).parent / "rerun"
    try:
        proc = subprocess.run(
            [str(rerun_cli), "rrd", "verify", str(path)],
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as e:
        raise ReviewError(f"{path}: cannot run {rerun_cli}: {e}") from e
    output = proc.stdout + proc.stderr
    m = _VERIFIED_RE.search(output)
    if proc.returncode != 0 or m is None or int(m.group(1)) != 1:
        lines = [ln.strip() for ln in output.splitlines() if ln.strip()]
        # the line naming the file says what is wrong; the last one only counts errors
        reason = next((ln for ln in lines if path.name in ln), lines[-1] if lines else "")
        raise ReviewError(f"{path}: rerun rrd verify failed: {reason}")


def plot_recording(rec: Recording, out_png: str | Path) -> Path:
    """The review figure (`mrrig.offline.review_report.plot`) of the whole run as a PNG."""
    from mrrig.loop.summary import summarize
    from mrrig.offline.review_report import plot

    counters = {k: v for k, v in (rec.summary or {}).items() if not isinstance(v, dict | list)}
    plot(rec, summarize(rec.samples, rec.events, counters), out_png)
    return Path(out_png)
