"""One pass over a run's .rrd file, chunk by chunk, in bounded memory.

`scan_recording` reads the file with Rerun's streaming chunk reader (`rerun.chunk.RrdReader`:
no server, no store of the whole file, a file without footer as well) and hands the samples
to a callback in batches, in frame order, as they complete: each SAMPLE_DTYPE field is an
entity of its own (`mrrig.rigio.recording`), so a frame is complete once every field's
chunk holding it has come. What it keeps is a window of frames (`WINDOW_FRAMES`, about two
minutes at 500 Hz), the events and the static documents (summary, identity, end marker).

Frames that lack a field the recording has (a writer killed between the fields of one flush)
are dropped and counted; a field of `LATER_FIELDS` that the whole recording lacks (one made
before it existed) is NaN.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from mrrig.loop.samples import SAMPLE_DTYPE
from mrrig.rigio.recording import (
    EVENT_TIMELINE,
    EVENTS_ENTITY,
    FIELD_ENTITIES,
    FRAME_TIMELINE,
    LATER_FIELDS,
    RECORDING_END_ENTITY,
    RUN_ENTITY,
    SUMMARY_ENTITY,
)

log = logging.getLogger(__name__)

WINDOW_FRAMES = 1 << 16  # frames held back for fields still to come (131 s at 500 Hz)
_SCALARS = "Scalars:scalars"
_TEXT = "TextDocument:text"
_STATIC = {SUMMARY_ENTITY: "summary", RUN_ENTITY: "identity", RECORDING_END_ENTITY: "end"}


@dataclasses.dataclass
class Scan:
    """What a pass over a recording found besides its samples."""

    entities: set[str]  # every entity path seen ("/forces/f_meas", ...)
    events: list[dict[str, Any]]  # t, level, text, plus the extra fields, in event order
    summary: dict[str, Any] | None  # the last static summary, or None
    identity: dict[str, Any] | None  # the run's identity, or None
    end: dict[str, Any] | None  # the recorder's end marker (frames, events), or None
    frames: int  # samples handed to the callback
    dropped: int  # frames dropped for a missing field


class _Assembler:
    """Per-field values by frame number into SAMPLE_DTYPE rows; complete rows out in frame
    order once `window` newer frames have come (or at `finish`)."""

    def __init__(self, emit: Callable[[np.ndarray], None], window: int) -> None:
        self._emit = emit
        self._window = window
        self._fields = list(FIELD_ENTITIES)
        self._seen = np.zeros(len(self._fields), dtype=bool)
        self._base = 0  # the first frame not handed out yet
        self._top = 0  # one past the highest frame received
        self._buf = np.empty(3 * window, dtype=SAMPLE_DTYPE)
        self._have = np.zeros((3 * window, len(self._fields)), dtype=bool)
        self.frames = self.dropped = self.late = 0

    def add(self, field: str, frames: np.ndarray, values: np.ndarray) -> None:
        k = self._fields.index(field)
        self._seen[k] = True
        late = frames < self._base
        if late.any():  # its frame was handed out without it: nothing to do but count
            self.late += int(late.sum())
            frames, values = frames[~late], values[~late]
        if not frames.size:
            return
        need = int(frames.max()) + 1 - self._base
        if need > self._buf.size:  # a chunk longer than the window (a compacted file)
            grow = max(need, 2 * self._buf.size)
            self._buf = np.resize(self._buf, grow)
            self._have = np.concatenate(
                [self._have, np.zeros((grow - self._have.shape[0], self._have.shape[1]), bool)]
            )
        rows = frames - self._base
        self._buf[field][rows] = values
        self._have[rows, k] = True
        self._top = max(self._top, int(frames.max()) + 1)
        if self._top - self._base > 2 * self._window:
            self._flush(self._top - self._window)

    def finish(self) -> list[str]:
        """Hand out the rest; returns the fields the recording never had."""
        self._flush(self._top)
        return [f for f, seen in zip(self._fields, self._seen, strict=True) if not seen]

    def _flush(self, upto: int) -> None:
        n = upto - self._base
        if n <= 0:
            return
        have = self._have[:n]
        # a field the recording has so far must be there; one it never had is NaN
        complete = have[:, self._seen].all(axis=1)
        out = self._buf[:n][complete].copy()
        for field, seen in zip(self._fields, self._seen, strict=True):
            if not seen:
                out[field] = np.nan
        self.dropped += int(n - complete.sum())
        rest = self._top - upto
        self._buf[:rest] = self._buf[n : n + rest]
        self._have[:rest] = self._have[n : n + rest]
        self._have[rest:] = False
        self._base = upto
        if out.size:
            self.frames += out.size
            self._emit(out)


def _values(table: pa.RecordBatch, name: str) -> list[Any]:
    """A list column's first item per row (None for an empty or null row)."""
    return [v[0] if v else None for v in table.column(name).to_pylist()]


def _scalars(batch: pa.RecordBatch) -> tuple[np.ndarray, np.ndarray]:
    """Frame numbers and values of a scalar series' chunk (rows without one value dropped)."""
    frames = batch.column(FRAME_TIMELINE).to_numpy(zero_copy_only=False)
    lists = batch.column(_SCALARS)
    lengths = lists.value_lengths().fill_null(0).to_numpy(zero_copy_only=False)
    if not (lengths == 1).all():
        keep = lengths == 1
        frames, lists = frames[keep], lists.filter(pa.array(keep))
    return frames.astype(np.int64), lists.flatten().to_numpy(zero_copy_only=False)


def scan_recording(
    path: str | Path,
    on_samples: Callable[[np.ndarray], None],
    window: int = WINDOW_FRAMES,
) -> Scan:
    """Read `path` once; `on_samples` gets the SAMPLE_DTYPE samples in frame order, in
    batches. Raises what the reader raises on a file it cannot decode, and ValueError where
    the recording lacks a field that every recording has."""
    from rerun.chunk import RrdReader

    by_entity = {f"/{e}": f for f, e in FIELD_ENTITIES.items()}
    static = {f"/{e}": name for e, name in _STATIC.items()}
    events_path = f"/{EVENTS_ENTITY}"
    found: dict[str, Any] = {}
    events: list[tuple[int, dict[str, Any]]] = []
    entities: set[str] = set()
    asm = _Assembler(on_samples, window)
    with warnings.catch_warnings():
        # "no footer/manifest: ... a whole-file scan": the scan is what this reads it for
        warnings.simplefilter("ignore")
        stream = RrdReader(path).stream()
    for chunk in stream:
        entity = chunk.entity_path
        entities.add(entity)
        if entity in by_entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            if FRAME_TIMELINE in batch.schema.names and _SCALARS in batch.schema.names:
                asm.add(by_entity[entity], *_scalars(batch))
        elif entity in static and chunk.is_static:
            texts = [t for t in _values(chunk.to_record_batch(), _TEXT) if t is not None]
            if texts:  # static: the last one written is the one that holds
                found[static[entity]] = json.loads(texts[-1])
        elif entity == events_path and not chunk.is_static:
            events += _events(chunk.to_record_batch())
    absent = asm.finish()
    required = [f for f in absent if f not in LATER_FIELDS]
    if required and asm.frames + asm.dropped:
        raise ValueError(f"the recording has frames but no {FIELD_ENTITIES[required[0]]} series")
    if asm.dropped:
        log.warning("%s: %d frames with missing fields dropped", path, asm.dropped)
    if asm.late:
        log.warning("%s: %d values came after their frame was read: dropped", path, asm.late)
    events.sort(key=lambda e: e[0])
    return Scan(
        entities=entities,
        events=[e for _, e in events],
        summary=found.get("summary"),
        identity=found.get("identity"),
        end=found.get("end"),
        frames=asm.frames,
        dropped=asm.dropped,
    )


def _events(batch: pa.RecordBatch) -> list[tuple[int, dict[str, Any]]]:
    names = batch.schema.names
    n = batch.num_rows

    def column(name: str) -> list[Any]:
        return _values(batch, name) if name in names else [None] * n

    order = batch.column(EVENT_TIMELINE).to_pylist() if EVENT_TIMELINE in names else list(range(n))
    rows = zip(
        order,
        column("t_s"),
        column("TextLog:level"),
        column("TextLog:text"),
        column("fields"),
        strict=True,
    )
    return [
        (i if i is not None else -1, {"t": t, "level": lv, "text": tx, **json.loads(f or "{}")})
        for i, t, lv, tx, f in rows
    ]
