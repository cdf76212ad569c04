"""Rerun recording of a run: one .rrd per run, written by the telemetry sidecar process.

Layout of the recording (the contract `mrrig.review` reads back):

- Every SAMPLE_DTYPE field is a `Scalars` series (float64, so f8 fields are kept bit for bit
  and the u1 fields exactly) at the entity in `FIELD_ENTITIES`, on two timelines:
  `sensor_time` (duration, the sample's `t`; nanosecond resolution) and `frame` (sequence,
  the sample's running index in this recording, so rows are unique even if two samples
  share a time). `t` itself is also stored as a scalar (`frame/t`) because the timeline
  rounds it to whole nanoseconds.
- `loops/force_velocity` and `loops/force_displacement`: one `LineStrips2D` strip per flush
  window, at the window's last sensor time.
- `events`: `TextLog` (text, level) plus `AnyValues` `t_s` (exact time, s) and `fields`
  (JSON object of the extra fields: kind, reason, ...), on `sensor_time` and the `event`
  sequence timeline.
- `summary`: static `TextDocument` holding the JSON of `add_summary`'s dict (NaN allowed).

Samples are buffered and sent with `send_columns` every `flush_interval_s`: one `log` call
per sample would cost 30-60 us.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import logging
import signal
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from mrrig import json_text
from mrrig.samples import SAMPLE_DTYPE

log = logging.getLogger(__name__)

APPLICATION_ID = "mrrig"
SENSOR_TIMELINE = "sensor_time"
FRAME_TIMELINE = "frame"
EVENT_TIMELINE = "event"
EVENTS_ENTITY = "events"
SUMMARY_ENTITY = "summary"
LOOP_FV_ENTITY = "loops/force_velocity"
LOOP_FX_ENTITY = "loops/force_displacement"

FIELD_ENTITIES: dict[str, str] = {
    "t": "frame/t",
    "counter": "frame/counter",
    "x": "displacement/x",
    "x_est": "displacement/x_est",
    "xd": "velocity/xd",
    "xdd": "acceleration/xdd",
    "f_meas": "forces/f_meas",
    "f_des": "forces/f_des",
    "f_model": "forces/f_model",
    "i_cmd": "current/i_cmd",
    "i_meas": "current/i_meas",
    "latency_us": "latency/latency_us",
    "state": "state/state",
}

_SERIES_COLORS: dict[str, tuple[int, int, int]] = {
    "f_meas": (31, 119, 180),
    "f_des": (214, 39, 40),
    "f_model": (44, 160, 44),
    "i_cmd": (214, 39, 40),
    "i_meas": (31, 119, 180),
    "x": (31, 119, 180),
    "x_est": (255, 127, 14),
}

_SIGNALS = {signal.SIGINT, signal.SIGTERM}


def recording_path(directory: str | Path, rig: str, now: dt.datetime | None = None) -> Path:
    """`<directory>/<rig>-<UTC time>.rrd`, e.g. `rig1-20250114T093012Z.rrd`."""
    now = dt.datetime.now(dt.UTC) if now is None else now.astimezone(dt.UTC)
    return Path(directory) / f"{rig}-{now:%Y%m%dT%H%M%SZ}.rrd"


def default_blueprint() -> rrb.Blueprint:
    """Time series on the left, loops and the event log on the right."""
    recent = rrb.VisibleTimeRange(
        SENSOR_TIMELINE,
        start=rrb.TimeRangeBoundary.cursor_relative(seconds=-2.0),
        end=rrb.TimeRangeBoundary.cursor_relative(),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.TimeSeriesView(origin="forces", name="Force (N)"),
                rrb.TimeSeriesView(origin="current", name="Current (A)"),
                rrb.TimeSeriesView(origin="displacement", name="Displacement (m)"),
                rrb.TimeSeriesView(origin="velocity", name="Velocity (m/s)"),
                rrb.TimeSeriesView(origin="acceleration", name="Acceleration (m/s^2)"),
                rrb.TimeSeriesView(origin="latency", name="Cycle latency (us)"),
                rrb.TimeSeriesView(origin="state", name="State (0 IDLE, 1 ARMED, 2 FAULT)"),
            ),
            rrb.Vertical(
                rrb.Spatial2DView(
                    origin=LOOP_FV_ENTITY, name="F-v loop (m/s, N)", time_ranges=recent
                ),
                rrb.Spatial2DView(
                    origin=LOOP_FX_ENTITY, name="F-x loop (m, N)", time_ranges=recent
                ),
                rrb.TextLogView(origin=EVENTS_ENTITY, name="Events"),
            ),
            column_shares=[2, 1],
        ),
        collapse_panels=False,
    )


class Recorder:
    """Writes one run to an .rrd file (and optionally streams it to a running viewer).

    `live_url` (e.g. rerun+http://127.0.0.1:9876/proxy) also streams to a running viewer or
    `rerun --serve-grpc` proxy. Measured here: with nothing listening there, the constructor
    blocks about 6 s and `close()` about 5 s (rerun's connect timeout); the file is complete
    either way.

    Meant for one thread plus signal handlers: a SIGTERM/SIGINT handler may call `close()`.
    Each public method holds a lock with SIGINT/SIGTERM blocked in the calling thread, so a
    handler can neither interrupt a half-sent flush nor deadlock on the lock.
    """

    def __init__(
        self,
        path: str | Path,
        rig: str,
        flush_interval_s: float = 0.5,
        live_url: str | None = None,
    ) -> None:
        self.path = Path(path)
        self.rig = rig
        self.flush_interval_s = flush_interval_s
        self._lock = threading.Lock()
        self._pending: list[np.ndarray] = []
        self._first_pending_t_s: float | None = None
        self._frames = 0
        self._events = 0
        self._closed = False
        self._dropped_after_close = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._rec = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
        sinks: list[Any] = [rr.FileSink(self.path)]
        if live_url is not None:
            sinks.append(rr.GrpcSink(live_url))
        self._rec.set_sinks(*sinks, default_blueprint=default_blueprint())
        self._rec.log("rig", rr.TextDocument(rig), static=True)
        for field, entity in FIELD_ENTITIES.items():
            color = _SERIES_COLORS.get(field)
            self._rec.log(
                entity,
                rr.SeriesLines(names=field, colors=[color] if color else None),
                static=True,
            )
        log.info("recording to %s%s", self.path, f" and {live_url}" if live_url else "")

    @contextlib.contextmanager
    def _guard(self) -> Iterator[None]:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
        try:
            with self._lock:
                yield
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)

    @property
    def frames(self) -> int:
        """Samples sent to the recording so far (not counting the buffer)."""
        return self._frames

    def add_samples(self, arr: np.ndarray) -> None:
        """Buffer a batch of SAMPLE_DTYPE records; sends once `flush_interval_s` of sensor
        time has been buffered."""
        if arr.dtype != SAMPLE_DTYPE:
            raise TypeError(f"samples must have SAMPLE_DTYPE, got {arr.dtype}")
        if arr.size == 0:
            return
        with self._guard():
            if self._closed:
                self._drop(arr.size)
                return
            self._pending.append(arr.copy())
            if self._first_pending_t_s is None:
                self._first_pending_t_s = float(arr["t"][0])
            if float(arr["t"][-1]) - self._first_pending_t_s >= self.flush_interval_s:
                self._flush_locked()

    def add_event(self, t_s: float, level: str, text: str, **fields: Any) -> None:
        """A fault or state change as a text log entry at sensor time `t_s`.

        Extra fields (kind, reason, ...) are kept as JSON beside the text.
        """
        with self._guard():
            if self._closed:
                self._drop(1)
                return
            self._rec.reset_time()
            self._rec.set_time(SENSOR_TIMELINE, duration=t_s)
            self._rec.set_time(EVENT_TIMELINE, sequence=self._events)
            self._rec.log(
                EVENTS_ENTITY,
                rr.TextLog(text, level=level),
                rr.AnyValues(t_s=float(t_s), fields=json_text.dumps(fields)),
            )
            self._rec.reset_time()
            self._events += 1

    def add_summary(self, d: dict[str, Any]) -> None:
        """Store the run's final summary/counters (static JSON `TextDocument` at `summary`)."""
        with self._guard():
            if self._closed:
                self._drop(1)
                return
            self._rec.log(SUMMARY_ENTITY, rr.TextDocument(json_text.dumps(d)), static=True)

    def flush(self) -> None:
        """Send everything buffered now."""
        with self._guard():
            if not self._closed:
                self._flush_locked()

    def close(self) -> None:
        """Flush and write the footer (disconnect). Idempotent; later calls drop data."""
        with self._guard():
            if self._closed:
                return
            self._flush_locked()
            self._rec.disconnect()
            self._closed = True
            log.info(
                "recording closed: %s (%d frames, %d events)", self.path, self._frames, self._events
            )

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _drop(self, n: int) -> None:
        if self._dropped_after_close == 0:
            log.warning("recorder %s is closed: dropping data", self.path)
        self._dropped_after_close += n

    def _flush_locked(self) -> None:
        if not self._pending:
            return
        batch = np.concatenate(self._pending)
        self._pending = []
        self._first_pending_t_s = None
        n = batch.size
        indexes = [
            rr.TimeColumn(SENSOR_TIMELINE, duration=batch["t"]),
            rr.TimeColumn(FRAME_TIMELINE, sequence=np.arange(self._frames, self._frames + n)),
        ]
        for field, entity in FIELD_ENTITIES.items():
            self._rec.send_columns(
                entity,
                indexes=indexes,
                columns=rr.Scalars.columns(scalars=batch[field].astype(np.float64)),
            )
        self._frames += n
        self._rec.reset_time()
        self._rec.set_time(SENSOR_TIMELINE, duration=float(batch["t"][-1]))
        self._rec.log(
            LOOP_FV_ENTITY, rr.LineStrips2D([np.column_stack((batch["xd"], batch["f_meas"]))])
        )
        self._rec.log(
            LOOP_FX_ENTITY, rr.LineStrips2D([np.column_stack((batch["x"], batch["f_meas"]))])
        )
        self._rec.reset_time()
