"""Rerun recording of a run: one .rrd per run, written by the telemetry sidecar process.

Layout of the recording (the contract `mrrig.offline.review` reads back):

- Every SAMPLE_DTYPE field is a `Scalars` series (float64, so f8 fields are kept bit for bit
  and the u1 fields exactly) at the entity in `FIELD_ENTITIES`, on two timelines:
  `sensor_time` (duration, the sample's `t`; nanosecond resolution) and `frame` (sequence,
  the sample's running index in this recording, so rows are unique even if two samples
  share a time). `t` itself is also stored as a scalar (`frame/t`) because the timeline
  rounds it to whole nanoseconds. A field of `LATER_FIELDS` (adaptation, temperature,
  coverage, the hybrid simulation's) is sent from its first flush with a value that is not
  NaN on: a run without adaptation or HIL writes none of those 8 series (each frame of a
  series costs about 24 bytes in the file whatever its value: 718 -> 513 bytes a frame). A
  reader takes the frames before a field's first as NaN (`mrrig.offline.rrd_scan`).
- `loops/force_velocity` and `loops/force_displacement`: one `LineStrips2D` strip per flush
  window, at the window's last sensor time, in normalised coordinates (value / full scale,
  so both axes span about +-1); `<loop>/axes` beside each strip draws the axes and labels
  their full scales (1-2-5 steps that only grow during a run).
- For the viewer only: `tracking_error/f_err` (f_meas - f_des, N), `frame_gap/gap_ms` (time
  since the previous sensor frame) and `summary_text` (the summary as the daemon prints it).
- `events`: `TextLog` (text, level) plus `AnyValues` `t_s` (exact time, s) and `fields`
  (JSON object of the extra fields: kind, reason, ...), on `sensor_time` and the `event`
  sequence timeline.
- `summary`: static `TextDocument` holding the JSON of `add_summary`'s dict (NaN allowed).
- `run`: static `TextDocument` holding the run's identity (JSON: run id, rig, host, specimen,
  operator, start UTC, controller and its parameters, model, config and DBC sha256, version).
- `recording_end`: static `TextDocument`, written by `close()`: JSON `frames` and `events`
  sent. A file that lacks it, or holds fewer frames, is truncated.

Samples are buffered and sent with `send_columns` every `flush_interval_s`: one `log` call
per sample would cost 30-60 us.

The file has no RRD footer (the manifest of its chunks): rerun would hold that manifest in the
writer's memory for the whole run, about 1 kB a chunk (issue 40: 2-3 MB a minute). The end
marker `recording_end` says that the file is whole; `rerun rrd optimize IN -o OUT` adds a
footer where a tool needs one.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import logging
import math
import os
import signal
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

# rerun warns of every file written without a footer (which it is, on purpose: see above);
# its other warnings stay, and a RUST_LOG of the user's own is theirs
os.environ.setdefault("RUST_LOG", "warn,re_log_encoding::rrd::file_sink=error")
import rerun as rr  # noqa: E402 - after its log filter
import rerun.blueprint as rrb  # noqa: E402

from mrrig import json_text
from mrrig.errors import MrrigError
from mrrig.loop.samples import SAMPLE_DTYPE

log = logging.getLogger(__name__)

APPLICATION_ID = "mrrig"
SENSOR_TIMELINE = "sensor_time"
FRAME_TIMELINE = "frame"
EVENT_TIMELINE = "event"
EVENTS_ENTITY = "events"
SUMMARY_ENTITY = "summary"
RUN_ENTITY = "run"  # the run's identity (JSON), static, from the start
# written by `close()`: the samples and events sent (JSON), static; the file has no footer, so
# this is how a reader knows that it holds the whole recording
RECORDING_END_ENTITY = "recording_end"
LOOP_FV_ENTITY = "loops/force_velocity"
LOOP_FX_ENTITY = "loops/force_displacement"
# derived series for the viewer only (review reads FIELD_ENTITIES)
ERROR_ENTITY = "tracking_error/f_err"
GAP_ENTITY = "frame_gap/gap_ms"
REPORT_ENTITY = "summary_text"
LOOP_AXES = "axes"  # child of each loop entity: its axes, labelled with their full scales
# per loop: (x field, its name and unit), the y field is f_meas
_LOOPS = {
    LOOP_FV_ENTITY: ("xd", "velocity", "m/s"),
    LOOP_FX_ENTITY: ("x", "displacement", "m"),
}

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
    "adapt_gain": "adaptation/gain",
    "adapt_offset_n": "adaptation/offset_n",
    "temp_degc": "temperature/temp_degc",
    "state": "state/state",
    "outside": "coverage/outside",
    "hil_k": "hil/k",
    "hil_x_c": "displacement/hil_x_c",
    "hil_setpoint": "displacement/hil_setpoint",
    "hil_delay_s": "hil/delay_s",
    "hil_acc": "hil/acc",
    "hil_load_n": "hil/load_n",
    # the model's states (the "Hybrid simulation" tab shows them beside the rig's)
    "hil_z_body": "model/displacement/body",
    "hil_z_wheel": "model/displacement/wheel",
    "hil_drift_2": "model/displacement/storey_2_drift",
    "hil_drift_3": "model/displacement/storey_3_drift",
    "hil_v_body": "model/velocity/body",
    "hil_v_wheel": "model/velocity/wheel",
}

# fields that recordings made before them lack: `mrrig review` reads those as NaN
LATER_FIELDS = ("adapt_gain", "adapt_offset_n", "temp_degc", "outside") + tuple(
    f for f in FIELD_ENTITIES if f.startswith("hil_")
)

# legend names: what each series is, not only its field name
_SERIES_NAMES: dict[str, str] = {
    "f_meas": "f_meas measured (load cell)",
    "f_des": "f_des desired",
    "f_model": "f_model network model",
    "i_cmd": "i_cmd commanded",
    "i_meas": "i_meas measured",
    "x": "x measured",
    "x_est": "x_est estimated (Kalman)",
    "xd": "xd estimated (Kalman)",
    "xdd": "xdd estimated (Kalman)",
    "adapt_gain": "gain on the model force",
    "adapt_offset_n": "offset of the model force (N)",
    "hil_x_c": "x_c the model's stroke",
    "hil_setpoint": "setpoint sent (compensated)",
    "hil_z_body": "body (model)",
    "hil_z_wheel": "wheel (model)",
    "hil_v_body": "body (model)",
    "hil_v_wheel": "wheel (model)",
    "hil_drift_2": "storey 2 drift (model)",
    "hil_drift_3": "storey 3 drift (model)",
    "hil_acc": "body (roof) acceleration (model)",
    "hil_load_n": "dynamic tyre load (model)",
}

_SERIES_COLORS: dict[str, tuple[int, int, int]] = {
    "f_meas": (31, 119, 180),
    "f_des": (214, 39, 40),
    "f_model": (44, 160, 44),
    "i_cmd": (214, 39, 40),
    "i_meas": (31, 119, 180),
    "x": (31, 119, 180),
    "x_est": (255, 127, 14),
    "adapt_gain": (31, 119, 180),
    "adapt_offset_n": (255, 127, 14),
    "hil_x_c": (214, 39, 40),
    "hil_setpoint": (44, 160, 44),
    "hil_z_body": (31, 119, 180),
    "hil_z_wheel": (255, 127, 14),
    "hil_v_body": (31, 119, 180),
    "hil_v_wheel": (255, 127, 14),
    "hil_drift_2": (255, 127, 14),
    "hil_drift_3": (44, 160, 44),
}

_SIGNALS = {signal.SIGINT, signal.SIGTERM}
# rerun writes the file in a thread of its own and only logs a failed write; a flush that
# waits for that thread raises once it has died (disk full, file size limit), or times out.
# Under the sidecar's heartbeat timeout (5 s), so a failing disk is not taken for a stuck
# sidecar; a healthy flush of 0.5 s of samples takes milliseconds
WRITE_TIMEOUT_S = 1.0


class RecordingError(MrrigError, OSError):
    """The recording file could not be written; what reached it is truncated."""


def recording_path(directory: str | Path, rig: str, now: dt.datetime | None = None) -> Path:
    """`<directory>/<rig>-<UTC time>.rrd`, e.g. `rig1-20250114T093012Z.rrd`."""
    now = dt.datetime.now(dt.UTC) if now is None else now.astimezone(dt.UTC)
    return Path(directory) / f"{rig}-{now:%Y%m%dT%H%M%SZ}.rrd"


def nice_scale(value: float) -> float:
    """The smallest 1, 2 or 5 x 10^k at or above `value` (> 0): a full scale people read."""
    if not math.isfinite(value) or value <= 0:
        return 1.0
    k = math.floor(math.log10(value))
    for mantissa in (1.0, 2.0, 5.0, 10.0):
        scale = mantissa * 10.0**k
        if scale >= value * (1 - 1e-12):
            return scale
    return 10.0 ** (k + 1)


def _series_view(origin: str, name: str, contents: list[str] | None = None) -> rrb.TimeSeriesView:
    """A time series view without a legend (one drawn over the plot hides the traces that pass
    under it): a view of several series names their colours in its title, and hovering a
    trace shows its name. `contents`: the entities shown, where not all under `origin`."""
    extra = {} if contents is None else {"contents": contents}
    return rrb.TimeSeriesView(
        origin=origin, name=name, plot_legend=rrb.PlotLegend(visible=False), **extra
    )


def _loop_view(origin: str, name: str) -> rrb.Spatial2DView:
    # both coordinates are normalised to +-1 of their full scale (LOOP_AXES_ENTITY labels
    # the scales), so a loop fills the square view instead of a vertical line of N over m/s
    recent = rrb.VisibleTimeRange(
        SENSOR_TIMELINE,
        start=rrb.TimeRangeBoundary.cursor_relative(seconds=-2.0),
        end=rrb.TimeRangeBoundary.cursor_relative(),
    )
    return rrb.Spatial2DView(
        origin=origin,
        name=name,
        time_ranges=recent,
        visual_bounds=rrb.VisualBounds2D(x_range=[-1.25, 1.25], y_range=[-1.25, 1.25]),
    )


# the "Hybrid simulation" tab's series, by field (fixed here: the recorder's entity table may
# be a recording's older one)
_HIL_VIEWS = {
    name: [FIELD_ENTITIES[f] for f in fields]
    for name, fields in (
        ("stroke", ("x", "hil_x_c", "hil_setpoint")),
        ("force", ("f_meas", "f_des")),
        ("x_c", ("hil_x_c",)),
        ("load", ("hil_load_n",)),
        ("acc", ("hil_acc",)),
    )
}


def _hil_tab() -> rrb.Horizontal:
    """A hybrid simulation's run (spec/hil.md): the rig's side (the model's stroke x_c, the
    setpoint sent and the measured stroke; the measured and the desired damper force) beside
    the numerical model's states (quarter car: body and wheel displacement and velocity,
    suspension travel = x_c, tyre load, body acceleration; building: storey drifts, storey 1's
    = x_c, roof acceleration). Empty in a run without one."""
    rig = rrb.Vertical(
        _series_view(
            "/",
            "Rig stroke (m): measured blue, model's x_c red, setpoint sent green",
            _HIL_VIEWS["stroke"],
        ),
        _series_view(
            "/",
            "Rig damper force (N): measured blue, the law's desired red",
            _HIL_VIEWS["force"],
        ),
        name="The rig",
    )
    model = rrb.Vertical(
        _series_view(
            "/",
            "Model displacement (m): body blue, wheel orange, travel or storey-1 drift "
            "(x_c) red; storey 2 orange, 3 green",
            [*_HIL_VIEWS["x_c"], "model/displacement/**"],
        ),
        _series_view("model/velocity", "Model velocity (m/s): body blue, wheel orange"),
        _series_view(
            "/",
            "Model dynamic tyre load (N)",
            _HIL_VIEWS["load"],
        ),
        _series_view(
            "/",
            "Model body (building: roof) acceleration (m/s^2)",
            _HIL_VIEWS["acc"],
        ),
        name="The numerical model",
    )
    return rrb.Horizontal(rig, model, name="Hybrid simulation")


def default_blueprint() -> rrb.Blueprint:
    """One tab per task: tracking (forces, their error, the loops), current, motion, the
    on-line adaptation and the damper's temperature, timing, a hybrid simulation's rig and
    model side by side, events with the run's summary."""
    return rrb.Blueprint(
        rrb.Tabs(
            rrb.Horizontal(
                rrb.Vertical(
                    _series_view("forces", "Force (N): desired red, measured blue, model green"),
                    _series_view(ERROR_ENTITY, "Tracking error f_meas - f_des (N)"),
                    row_shares=[3, 2],
                ),
                rrb.Vertical(
                    _loop_view(LOOP_FV_ENTITY, "Force-velocity loop (normalised)"),
                    _loop_view(LOOP_FX_ENTITY, "Force-displacement loop (normalised)"),
                ),
                column_shares=[2, 1],
                name="Tracking",
            ),
            rrb.Vertical(
                _series_view("current", "Damper current (A): commanded red, measured blue"),
                _series_view("state", "State (0 IDLE, 1 ARMED, 2 FAULT)"),
                row_shares=[3, 1],
                name="Current",
            ),
            rrb.Vertical(
                _series_view(
                    "displacement", "Displacement (m): measured blue, Kalman estimate orange"
                ),
                _series_view("velocity", "Velocity, estimated (m/s)"),
                _series_view("acceleration", "Acceleration, estimated (m/s^2)"),
                name="Motion",
            ),
            rrb.Vertical(
                _series_view("adaptation", "On-line adaptation: gain blue, offset (N) orange"),
                _series_view("temperature", "Damper temperature (degC)"),
                name="Adaptation",
            ),
            rrb.Vertical(
                _series_view("latency", "Cycle latency, receive -> send (us)"),
                _series_view(GAP_ENTITY, "Gap between sensor frames (ms)"),
                _series_view("state", "State (0 IDLE, 1 ARMED, 2 FAULT)"),
                row_shares=[2, 2, 1],
                name="Timing",
            ),
            _hil_tab(),
            rrb.Horizontal(
                rrb.TextLogView(origin=EVENTS_ENTITY, name="Events (faults, state changes)"),
                rrb.TextDocumentView(origin=REPORT_ENTITY, name="Run summary"),
                column_shares=[1, 1],
                name="Events and summary",
            ),
            active_tab=0,
        ),
        # the views get the window: the blueprint and selection panels start collapsed, the
        # time panel as its bar (the sensor_time timeline, where the loops' 2 s window moves)
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=SENSOR_TIMELINE),
    )


class Recorder:
    """Writes one run to an .rrd file (and optionally streams it to a running viewer).

    `live_url` (e.g. rerun+http://127.0.0.1:9876/proxy) also streams to a running viewer or
    `rerun --serve-grpc` proxy. With nothing listening there, the constructor and `close()`
    block for rerun's connect timeout (seconds); the file is complete either way.

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
        identity: dict[str, Any] | None = None,
    ) -> None:
        """`identity`: the run's (`mrrig.rigio.run_identity`), a static JSON document at
        `run`, so that a recording copied elsewhere still says what it is."""
        self.path = Path(path)
        self.rig = rig
        self.flush_interval_s = flush_interval_s
        self._lock = threading.Lock()
        self._pending: list[np.ndarray] = []
        self._first_pending_t_s: float | None = None
        self._frames = 0
        self._events = 0
        self._started: set[str] = set()  # LATER_FIELDS sent so far (from their first value)
        self._closed = False
        self._dropped_after_close = 0
        self.failed = ""  # why writing the file failed: what it holds is truncated
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._rec = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
        # no footer: rerun keeps the footer's manifest (about 1 kB for each chunk, 50 chunks a
        # second here) in memory until the file is closed, so a recording with one grows its
        # writer by 2-3 MB a minute (issue 40). The file is whole without it; the run's end
        # is its summary, and readers stream it (`mrrig.offline.review`)
        sinks: list[Any] = [rr.FileSink(self.path, write_footer=False)]
        if live_url is not None:
            sinks.append(rr.GrpcSink(live_url))
        self._rec.set_sinks(*sinks, default_blueprint=default_blueprint())
        self._rec.log("rig", rr.TextDocument(rig), static=True)
        if identity is not None:
            self._rec.log(RUN_ENTITY, rr.TextDocument(json_text.dumps(identity)), static=True)
        for field, entity in FIELD_ENTITIES.items():
            color = _SERIES_COLORS.get(field)
            self._rec.log(
                entity,
                rr.SeriesLines(
                    names=_SERIES_NAMES.get(field, field), colors=[color] if color else None
                ),
                static=True,
            )
        self._rec.log(ERROR_ENTITY, rr.SeriesLines(names="f_meas - f_des"), static=True)
        self._rec.log(GAP_ENTITY, rr.SeriesLines(names="sensor frame gap"), static=True)
        # full scales of the loops' normalised axes: they only grow, to 1-2-5 steps
        self._scales = {"x": 0.0, "xd": 0.0, "f_meas": 0.0}
        self._last_t: float | None = None
        # the file as opened (the sink creates it at once): what `check_file` compares with
        st = os.stat(self.path)
        self._file_id = (st.st_dev, st.st_ino)
        self._checked = (st.st_size, self._frames)  # size and samples sent at the last check
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

    def check_file(self) -> int:
        """The file's size now. Raises RecordingError where the file this recording writes
        is gone (removed, or its directory), another file, shorter than at the last check, or
        not grown while samples were sent: the writer keeps writing to what it opened and
        says nothing, and the run's record would be lost silently."""
        with self._guard():
            size, frames = self._checked
            if self._closed:
                return size
            try:
                st = os.stat(self.path)
            except OSError as exc:
                raise RecordingError(
                    f"{self.path}: the file is gone while recording ({exc.strerror}: removed,"
                    " or its directory); what is written from here on is lost"
                ) from None
            if (st.st_dev, st.st_ino) != self._file_id:
                raise RecordingError(
                    f"{self.path}: replaced by another file while recording; the run's"
                    " record is lost"
                )
            if st.st_size < size or (st.st_size == size and self._frames > frames):
                raise RecordingError(
                    f"{self.path}: {st.st_size} bytes after {size} at the last check, with"
                    f" {self._frames - frames} samples sent since: cut or not written"
                )
            self._checked = (st.st_size, self._frames)
            return st.st_size

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
            self._rec.log(REPORT_ENTITY, summary_document(d, self.rig), static=True)

    def flush(self) -> None:
        """Send everything buffered now."""
        with self._guard():
            if not self._closed:
                self._flush_locked()

    def close(self) -> None:
        """Flush, write the end marker and disconnect. Idempotent; later calls drop data."""
        with self._guard():
            if self._closed:
                return
            try:
                self._flush_locked()
                end = json_text.dumps({"frames": self._frames, "events": self._events})
                self._rec.log(RECORDING_END_ENTITY, rr.TextDocument(end), static=True)
            finally:
                self._rec.disconnect()
                self._closed = True
            if self.failed:
                log.error("recording closed truncated (%s): %s", self.failed, self.path)
            else:
                log.info(
                    "recording closed: %s (%d frames, %d events)",
                    self.path,
                    self._frames,
                    self._events,
                )

    def abandon(self) -> None:
        """After a failed write: stop taking data without flushing or writing the end marker (a
        stream whose file writer failed may hang in either). The file stays truncated."""
        with self._guard():
            self._closed = True
            self._pending = []
        log.error("recording abandoned truncated (%s): %s", self.failed, self.path)

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
            values = batch[field].astype(np.float64)
            if field in LATER_FIELDS and field not in self._started:
                if np.isnan(values).all():
                    continue  # none yet: readers take the frames before its first as NaN
                self._started.add(field)
            self._rec.send_columns(
                entity, indexes=indexes, columns=rr.Scalars.columns(scalars=values)
            )
        self._frames += n
        t = batch["t"]
        self._send_derived(indexes, batch)
        self._last_t = float(t[-1])
        self._rec.reset_time()
        self._rec.set_time(SENSOR_TIMELINE, duration=float(t[-1]))
        for field in self._scales:
            peak = float(np.nanmax(np.abs(batch[field]), initial=0.0))
            if peak > self._scales[field]:
                self._scales[field] = nice_scale(peak)
        f_scale = self._scales["f_meas"] or 1.0
        for entity, (field, name, unit) in _LOOPS.items():
            scale = self._scales[field] or 1.0
            # the 2D view's y axis points down: -force, so that pulling is up as on paper
            self._rec.log(
                entity,
                rr.LineStrips2D(
                    [np.column_stack((batch[field] / scale, -batch["f_meas"] / f_scale))]
                ),
            )
            self._rec.log(f"{entity}/{LOOP_AXES}", *loop_axes(name, unit, scale, f_scale))
        self._rec.reset_time()
        try:
            self._rec.flush(timeout_sec=WRITE_TIMEOUT_S)
        except RuntimeError as exc:
            self.failed = str(exc)
            raise RecordingError(f"{self.path}: writing failed: {exc}") from None

    def _send_derived(self, indexes: list[Any], batch: np.ndarray) -> None:
        """The tracking error and the gap between sensor frames, for the viewer's tabs."""
        t = batch["t"]
        prev = t[0] if self._last_t is None else self._last_t
        gaps_ms = np.diff(t, prepend=prev) * 1e3
        error = batch["f_meas"] - batch["f_des"]
        self._rec.send_columns(
            ERROR_ENTITY, indexes=indexes, columns=rr.Scalars.columns(scalars=error)
        )
        self._rec.send_columns(
            GAP_ENTITY, indexes=indexes, columns=rr.Scalars.columns(scalars=gaps_ms)
        )


def loop_axes(name: str, unit: str, scale: float, f_scale: float) -> tuple[Any, Any]:
    """A loop view's axes: two grey lines through 0 and their ends labelled with the full
    scale and its unit (the drawn coordinates are value / full scale, force negated: the
    view's y axis points down)."""
    grey = [(150, 150, 150)]
    lines = rr.LineStrips2D([[(-1.0, 0.0), (1.0, 0.0)], [(0.0, -1.0), (0.0, 1.0)]], colors=grey)
    ticks = rr.Points2D(
        [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)],
        labels=[
            f"{name} +{scale:g} {unit}",
            f"-{scale:g} {unit}",
            f"-{f_scale:g} N",
            f"force +{f_scale:g} N",
        ],
        colors=grey,
        radii=0.01,
    )
    return lines, ticks


def summary_document(d: dict[str, Any], rig: str) -> rr.TextDocument:
    """The run's summary as the daemon prints it, for the viewer's summary view."""
    from mrrig.loop.summary import format_summary

    try:
        text = format_summary(d)
    except (KeyError, TypeError, ValueError):  # a partial summary: its JSON is still shown
        text = json_text.dumps(d, indent=2)
    body = f"# Run summary: rig {rig}\n\n```\n{text}\n```\n"
    return rr.TextDocument(body, media_type=rr.MediaType.MARKDOWN)
