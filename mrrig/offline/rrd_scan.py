"""One pass over a run's .rrd file, chunk by chunk, in bounded memory.

`scan_recording` reads the file with Rerun's streaming chunk reader (`rerun.chunk.RrdReader`:
no server, no store of the whole file, a file without footer as well) and hands the samples
to a callback in batches, in frame order, as they complete: each SAMPLE_DTYPE field is an
entity of its own (`mrrig.rigio.recording`), so a frame is complete once every field's
chunk holding it has come. What it keeps is about a window of frames (`WINDOW_FRAMES`, two
minutes at 500 Hz, or a flush more), the events and the static documents (summary,
identity, end marker).

Frames that lack a field the recording has (a writer killed between the fields of one flush)
are dropped and counted; a field of `LATER_FIELDS` that the whole recording lacks (one made
before it existed, or a run that never had a value of it) is NaN, and so is such a field in
the frames before its first (the recorder sends it from its first value on).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import struct
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

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
_FILE_HEADER, _MESSAGE_HEADER = 12, 16  # bytes: "RRF2", version, options; kind, length
_STATIC = {SUMMARY_ENTITY: "summary", RUN_ENTITY: "identity", RECORDING_END_ENTITY: "end"}


@dataclasses.dataclass
class Scan:
    """What a pass over a recording found besides its samples."""

    entities: set[str]  # every entity path seen ("/forces/f_meas", ...)
    cut: str  # why the file ends early (a writer killed mid-write), or ""
    events: list[dict[str, Any]]  # t, level, text, plus the extra fields, in event order
    summary: dict[str, Any] | None  # the last static summary, or None
    identity: dict[str, Any] | None  # the run's identity, or None
    end: dict[str, Any] | None  # the recorder's end marker (frames, events), or None
    frames: int  # samples handed to the callback
    dropped: int  # frames dropped for a missing field


class _Assembler:
    """Per-field values by frame number into SAMPLE_DTYPE rows; rows out in frame order once
    every field seen so far has come past them and `window` frames are held (or at `finish`).
    """

    def __init__(self, emit: Callable[[np.ndarray], None], window: int) -> None:
        self._emit = emit
        self._window = window
        self._fields = list(FIELD_ENTITIES)
        # a frame needs every field but those a recording made before them may lack entirely
        self._required = np.array([f not in LATER_FIELDS for f in self._fields])
        self._seen = np.zeros(len(self._fields), dtype=bool)
        self._field_top = np.zeros(len(self._fields), dtype=np.int64)  # per field: max + 1
        # per later field: its first frame (the frames before it are NaN: not sent till then)
        self._later = ~self._required
        self._first = np.full(len(self._fields), np.iinfo(np.int64).max, dtype=np.int64)
        self._base = 0  # the first frame not handed out yet
        self._top = 0  # one past the highest frame received
        self._buf = np.empty(4 * window, dtype=SAMPLE_DTYPE)
        self._have = np.zeros((4 * window, len(self._fields)), dtype=bool)
        self.frames = self.dropped = self.late = 0

    def add(self, field: str, frames: np.ndarray, values: np.ndarray) -> None:
        k = self._fields.index(field)
        self._seen[k] = True
        if frames.size:
            self._first[k] = min(self._first[k], int(frames.min()))
        late = frames < self._base
        if late.any():  # its frame was handed out without it: nothing to do but count
            self.late += int(late.sum())
            frames, values = frames[~late], values[~late]
        if not frames.size:
            return
        top = int(frames.max()) + 1
        need = top - self._base
        if need > self._buf.size:  # a chunk longer than the buffer (a compacted file)
            grow = max(need, 2 * self._buf.size)
            self._buf = np.resize(self._buf, grow)
            extra = np.zeros((grow - self._have.shape[0], self._have.shape[1]), dtype=bool)
            self._have = np.concatenate([self._have, extra])
        rows = frames - self._base
        self._buf[field][rows] = values
        self._have[rows, k] = True
        self._top = max(self._top, top)
        self._field_top[k] = max(self._field_top[k], top)
        # every field needed has come this far (a later one not seen so far is not needed)
        ready = int(self._field_top[self._required | self._seen].min())
        if ready - self._base > self._window:
            self._flush(ready)
        elif self._top - self._base > 4 * self._window:  # a field that stopped coming
            self._flush(self._top - self._window)

    def finish(self) -> list[str]:
        """Hand out the rest; returns the fields the recording never had."""
        self._flush(self._top)
        return [f for f, seen in zip(self._fields, self._seen, strict=True) if not seen]

    def _flush(self, upto: int) -> None:
        n = upto - self._base
        if n <= 0:
            return
        # every field but a later one the recording has not had so far (it is NaN)
        needed = self._required | self._seen
        frame = self._base + np.arange(n)
        for k in np.flatnonzero(self._later & self._seen):
            before = frame < self._first[k]  # a later field's frames before its first: NaN
            if before.any():
                self._buf[self._fields[k]][:n][before] = np.nan
                self._have[:n, k] |= before
        complete = self._have[:n][:, needed].all(axis=1)
        out = self._buf[:n][complete].copy()
        for field, need in zip(self._fields, needed, strict=True):
            if not need:
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


def open_rrd(path: str | Path) -> Any:
    """`rerun.chunk.RrdReader` of `path`, without its warning that the file has no footer (a
    recording has none: `mrrig.rigio.recording`) and will be scanned whole."""
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="RRD file has no footer")
        return RrdReader(str(path))


def whole_length(path: str | Path) -> int:
    """The bytes of `path` up to the end of its last whole message: the file's size unless a
    writer killed mid-write cut its last message short (rerun's reader refuses such a file).
    RRD framing: a 12-byte file header, then messages of a 16-byte header (kind, payload
    length: little-endian u64) and the payload."""
    size = Path(path).stat().st_size
    with open(path, "rb") as f:
        offset = _FILE_HEADER
        while offset + _MESSAGE_HEADER <= size:
            f.seek(offset + 8)
            (length,) = struct.unpack("<Q", f.read(8))
            end = offset + _MESSAGE_HEADER + length
            if end > size:
                break
            offset = end
    return offset


def scan_recording(
    path: str | Path,
    on_samples: Callable[[np.ndarray], None],
    window: int = WINDOW_FRAMES,
) -> Scan:
    """Read `path` once; `on_samples` gets the SAMPLE_DTYPE samples in frame order, in
    batches. A file whose last message is cut short is read up to it (from a copy of its
    whole messages: rerun's reader refuses the file); `Scan.cut` says so. Raises what the
    reader raises on a file it cannot decode, and ValueError where the recording lacks a
    field that every recording has."""
    path = Path(path)
    whole, size = whole_length(path), path.stat().st_size
    if whole == size:
        return _scan(path, on_samples, window, "")
    cut = f"its last message is cut short at byte {whole} of {size} (a writer killed mid-write)"
    log.warning("%s: %s: reading the whole messages before it", path, cut)
    with tempfile.TemporaryDirectory(prefix="mrrig-rrd-") as tmp:
        prefix = Path(tmp) / path.name
        with path.open("rb") as src, prefix.open("wb") as dst:
            _copy(src, dst, whole)
        return _scan(prefix, on_samples, window, cut)


def _copy(src: BinaryIO, dst: BinaryIO, n: int) -> None:
    while n > 0:
        block = src.read(min(n, 1 << 20))
        if not block:
            return
        dst.write(block)
        n -= len(block)


def _scan(path: Path, on_samples: Callable[[np.ndarray], None], window: int, cut: str) -> Scan:
    by_entity = {f"/{e}": f for f, e in FIELD_ENTITIES.items()}
    static = {f"/{e}": name for e, name in _STATIC.items()}
    events_path = f"/{EVENTS_ENTITY}"
    found: dict[str, Any] = {}
    events: list[tuple[int, dict[str, Any]]] = []
    entities: set[str] = set()
    asm = _Assembler(on_samples, window)
    stream = open_rrd(path).stream()
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
        cut=cut,
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
