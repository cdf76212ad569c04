"""Bus logs in the CAN world's formats: every frame the daemon's loop received or sent,
written with python-can's own writers (`.blf`, `.asc`, `.log` candump, `.trc`, `.csv`, `.mf4`
where asammdf is installed), readable by cantools, candump's tools or Vector's.

The loop never writes a file: it keeps each frame as a tuple (`FrameTap`, a list append) and
hands them to the sidecar in packed batches over its non-blocking pipe (`ipc.Msg.FRAMES`);
the sidecar writes them (`BusLogWriter`). A batch the pipe cannot take is dropped and counted
(`can_log_dropped` in the summary), never waited for.

`check_bus_log` compares a bus log with the run's recording (`mrrig review --can-log`).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import logging
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mrrig.errors import MrrigError
from mrrig.pycan import can, with_mf4

if TYPE_CHECKING:
    from mrrig.rigio.canbus.profile import RigProfile

log = logging.getLogger(__name__)

FRAME_DTYPE = np.dtype(
    [
        ("t", "<f8"),  # bus timestamp (rx) or wall-clock time after send() returned (tx), s
        ("id", "<u4"),
        ("dlc", "u1"),
        ("flags", "u1"),  # FLAG_RX, FLAG_EXTENDED
        ("data", "V8"),
    ]
)
FLAG_RX, FLAG_EXTENDED = 1, 2
FRAMES_PER_BATCH = 128  # about 0.12 s of the loop's traffic (0.5 kHz in, 0.5 kHz out)
SUFFIXES = (".blf", ".asc", ".log", ".trc", ".csv", ".mf4")
WRITER_PACKAGES = {".mf4": "asammdf"}  # python-can's writers that need an optional package


class BusLogError(MrrigError, ValueError):
    """A bus log that cannot be written or read; one line naming the file."""


def check_suffix(path: str | Path) -> Path:
    """A bus log path with a suffix python-can writes (the format follows the suffix)."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise BusLogError(
            f"{path}: unknown bus log format {path.suffix!r} (one of {', '.join(SUFFIXES)})"
        )
    return path


def check_writable(path: str | Path) -> Path:
    """`check_suffix`, and the optional package its writer needs is installed here: checked
    where the config is loaded, before anything starts (found missing in the telemetry
    process, it came as a traceback and a start-up that failed half-way)."""
    path = check_suffix(path)
    package = WRITER_PACKAGES.get(path.suffix.lower())
    if package is not None and importlib.util.find_spec(package) is None:
        raise BusLogError(
            f"{path}: a {path.suffix} bus log needs the Python package {package}, not installed"
            f" here (pip install {package}, or another suffix: {', '.join(SUFFIXES[:-1])})"
        )
    return path


class FrameTap:
    """The loop's side: one list append per frame; `take()` packs a batch when one is full.

    A received frame is kept as its `can.Message` (python-can makes a new one per `recv`), so
    the frame's path to its command costs an append (0.1 us); a sent frame, after `send()`
    returned, as a tuple (the packer may reuse its message objects)."""

    def __init__(self, batch: int = FRAMES_PER_BATCH) -> None:
        self._rows: list[can.Message | tuple[float, int, int, int, bytes]] = []
        self._batch = batch

    def rx(self, msg: can.Message) -> None:
        self._rows.append(msg)

    def tx(self, msg: can.Message) -> None:
        flags = FLAG_EXTENDED if msg.is_extended_id else 0
        self._rows.append((time.time(), msg.arbitration_id, msg.dlc, flags, bytes(msg.data)))

    def take(self, force: bool = False) -> np.ndarray | None:
        """The frames kept so far as a FRAME_DTYPE array, once a batch is full (or `force`)."""
        if not self._rows or (len(self._rows) < self._batch and not force):
            return None
        rows, self._rows = self._rows, []
        return np.array([r if isinstance(r, tuple) else _rx_row(r) for r in rows], FRAME_DTYPE)


def _rx_row(msg: can.Message) -> tuple[float, int, int, int, bytes]:
    flags = FLAG_RX | (FLAG_EXTENDED if msg.is_extended_id else 0)
    return (msg.timestamp, msg.arbitration_id, msg.dlc, flags, bytes(msg.data))


def to_messages(frames: np.ndarray, channel: str | None = None) -> list[can.Message]:
    """FRAME_DTYPE rows as python-can messages (what the writers take)."""
    return [
        can.Message(
            timestamp=float(f["t"]),
            arbitration_id=int(f["id"]),
            is_extended_id=bool(f["flags"] & FLAG_EXTENDED),
            is_rx=bool(f["flags"] & FLAG_RX),
            dlc=int(f["dlc"]),
            data=bytes(f["data"])[: int(f["dlc"])],
            channel=channel,
        )
        for f in frames
    ]


class BusLogWriter:
    """The sidecar's side: python-can's writer for the file's suffix."""

    def __init__(self, path: str | Path, channel: str | None = None) -> None:
        self.path = check_suffix(path)
        self.channel = channel
        self.frames = 0
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if self.path.suffix.lower() == ".mf4":
                with_mf4()
            self._writer = can.Logger(str(self.path))
        except ImportError as exc:  # .mf4 without asammdf
            raise BusLogError(f"{self.path}: cannot write this format here: {exc}") from exc
        except OSError as exc:
            raise BusLogError(f"{self.path}: cannot write: {exc.strerror or exc}") from exc

    def write(self, frames: np.ndarray) -> None:
        for msg in to_messages(frames, self.channel):
            self._writer.on_message_received(msg)
        self.frames += frames.size

    def close(self) -> None:
        self._writer.stop()
        log.info("bus log closed: %s (%d frames)", self.path, self.frames)


@dataclasses.dataclass
class BusLogCheck:
    """A bus log against the recording of the same run."""

    path: Path
    frames: int
    per_message: dict[str, int]  # message name (or hex id) -> frames
    rx_sensor_frames: int
    tx_commands: int
    counters_in_order: bool  # the recording's sensor counters appear in the log, in order
    mismatches: list[str]

    @property
    def ok(self) -> bool:
        return not self.mismatches

    def text(self) -> str:
        parts = ", ".join(f"{k} {v}" for k, v in sorted(self.per_message.items()))
        lines = [f"bus log {self.path}: {self.frames} frames ({parts})"]
        if self.mismatches:
            lines += [f"  MISMATCH {m}" for m in self.mismatches]
        else:
            lines.append(
                f"  matches the recording: {self.rx_sensor_frames} sensor frames received,"
                f" {self.tx_commands} commands sent, the recorded sensor frames in order"
            )
        return "\n".join(lines)


def read_bus_log(path: str | Path) -> list[can.Message]:
    path = check_suffix(path)
    if not path.is_file():
        raise BusLogError(f"{path}: no such file")
    if path.suffix.lower() == ".mf4":
        with_mf4()
    try:
        return list(can.LogReader(str(path)))
    except Exception as exc:  # noqa: BLE001 - python-can's readers raise anything on bad files
        raise BusLogError(f"{path}: cannot read it as a bus log: {exc}") from exc


def check_bus_log(
    path: str | Path,
    samples: np.ndarray,
    summary: dict[str, Any] | None,
    profile: RigProfile | None = None,
):
    """Decode a bus log with the rig profile's DBC (`profile`, the run's `[can]`; None: the
    contract's) and compare it with a recording: its frame counts with the daemon's counters
    (frames received, commands sent), the sensor frames' E2E counters (where the layout has
    them) and measurements (the profile's displacement and force, in SI) with the recorded
    `counter`, `x` and `f_meas` series (in order, to the signals' resolution: two clean runs of
    one length have the same counts and counters)."""
    from mrrig.rigio.canbus.profile import load_profile

    if profile is None:
        profile = load_profile(None, {}, None, "the CAN contract")
    db = profile.codec.db
    x_role, f_role = profile.mapped["displacement"], profile.mapped["force"]
    layout = profile.sensor_layout
    resolution = {
        role.role: float(db.get_message_by_name(role.message).get_signal_by_name(role.signal).scale)
        * role.factor
        for role in (x_role, f_role)
    }
    key = _SensorKey(layout.counter_signal, resolution["displacement"], resolution["force"])
    messages = read_bus_log(path)
    per: dict[str, int] = {}
    sensor_keys: list[tuple[int, int, int]] = []
    rx_sensor = tx_cmd = 0
    bad_decode = 0
    for msg in messages:
        try:
            spec = db.get_message_by_frame_id(msg.arbitration_id)
        except KeyError:
            per[hex(msg.arbitration_id)] = per.get(hex(msg.arbitration_id), 0) + 1
            continue
        per[spec.name] = per.get(spec.name, 0) + 1
        try:
            values = spec.decode(msg.data, decode_choices=False)
        except Exception:  # noqa: BLE001 - a frame the DBC cannot decode is counted
            bad_decode += 1
            continue
        if spec.name == profile.sensor_message and msg.is_rx:
            rx_sensor += 1
            sensor_keys.append(
                key.of(
                    values.get(layout.counter_signal, 0),
                    values[x_role.signal] * x_role.factor,
                    values[f_role.signal] * f_role.factor,
                )
            )
        elif spec.name == profile.command_message and not msg.is_rx:
            tx_cmd += 1
    mismatches = []
    if bad_decode:
        mismatches.append(f"{bad_decode} frames the DBC cannot decode")
    s = summary or {}
    expected_sensors = s.get("sensor_frames_valid", 0) + s.get("sensor_frames_invalid", 0)
    if summary is not None and rx_sensor != expected_sensors:
        mismatches.append(f"sensor frames received: log {rx_sensor}, daemon {expected_sensors}")
    if summary is not None and tx_cmd != s.get("commands_sent"):
        mismatches.append(f"commands sent: log {tx_cmd}, daemon {s.get('commands_sent')}")
    recorded = [
        key.of(c, x, f)
        for c, x, f in zip(samples["counter"], samples["x"], samples["f_meas"], strict=True)
    ]
    in_order = _subsequence(recorded, sensor_keys)
    if not in_order:
        mismatches.append("the recorded sensor frames (counter, x, force) are not the log's")
    return BusLogCheck(Path(path), len(messages), per, rx_sensor, tx_cmd, in_order, mismatches)


@dataclasses.dataclass(frozen=True)
class _SensorKey:
    """A sensor frame as raw DBC steps: its E2E counter (0 where the layout has none), its
    displacement and force in steps of their signals' resolution (SI)."""

    counter_signal: str
    x_step: float
    f_step: float

    def of(self, counter: float, x_m: float, f_n: float) -> tuple[int, int, int]:
        c = int(counter) if self.counter_signal and math.isfinite(counter) else 0
        return c, round(float(x_m) / self.x_step), round(float(f_n) / self.f_step)


def _subsequence(needle: list, hay: list) -> bool:
    """Whether `needle` appears in `hay` in order (not necessarily adjacent)."""
    it = iter(hay)
    return all(any(x == y for y in it) for x in needle)
