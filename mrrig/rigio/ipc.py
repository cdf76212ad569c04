"""Framed messages over two OS pipes between the control loop and the telemetry sidecar.

The loop must never block on telemetry: its write end is non-blocking and every message is at
most PIPE_BUF bytes, so POSIX makes each write all-or-nothing. A message that does not fit in
the pipe is dropped and counted, never written in part. Frame: struct '<BH' (type, payload
length) followed by the payload.

Loop -> sidecar: SAMPLES (raw SAMPLE_DTYPE records), EVENT, STATUS, REPLY (JSON with the
request's "id", written by the daemon's control thread on its own `ReplyWriter`), SUMMARY
(JSON objects), STOP (empty), FRAMES (raw `canlog.FRAME_DTYPE` records, for the bus log).
Sidecar -> loop: READY (JSON {"error": null or one line}, once, when its Zenoh session and
recording are open or have failed), REQUEST (struct '<I' id, then the request's JSON text as
the client sent it, checked by the sidecar), FORCE_REF (struct '<dd': force in N, sidecar
receive time from time.monotonic()), HEARTBEAT (empty, every HEARTBEAT_PERIOD_S), NOTICE (JSON
object: {"kind": "recording_failed" or "duplicate_rig", "reason": ...}).
"""

from __future__ import annotations

import enum
import fcntl
import json
import logging
import os
import select
import struct
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from mrrig import json_text
from mrrig.loop.kernel_stalls import shortened
from mrrig.loop.samples import SAMPLE_DTYPE

log = logging.getLogger(__name__)

# POSIX makes pipe writes of up to PIPE_BUF bytes atomic (Linux 4096, macOS 512)
PIPE_BUF = min(4096, select.PIPE_BUF)
HEADER = struct.Struct("<BH")
MAX_PAYLOAD = PIPE_BUF - HEADER.size
SAMPLES_PER_MESSAGE = MAX_PAYLOAD // SAMPLE_DTYPE.itemsize
_SAMPLES_STEP = SAMPLES_PER_MESSAGE * SAMPLE_DTYPE.itemsize
FORCE_REF = struct.Struct("<dd")
REQUEST_ID = struct.Struct("<I")
MAX_REQUEST_PAYLOAD = MAX_PAYLOAD - REQUEST_ID.size
HEARTBEAT_PERIOD_S = 0.2
_F_SETPIPE_SZ = 1031  # Linux fcntl; a bigger pipe rides out longer sidecar stalls
_READ_CHUNK = 1 << 16


class Msg(enum.IntEnum):
    """Message types; values are the first byte of a frame."""

    SAMPLES = 1
    EVENT = 2
    STATUS = 3
    REPLY = 4
    SUMMARY = 5
    STOP = 6
    FRAMES = 7
    REQUEST = 16
    FORCE_REF = 17
    READY = 18
    HEARTBEAT = 19
    NOTICE = 20


@dataclass(frozen=True)
class ChannelFds:
    """The four pipe ends. The loop keeps loop_rx/loop_tx, the sidecar gets the other two."""

    loop_rx: int  # loop reads REQUEST / FORCE_REF
    loop_tx: int  # loop writes SAMPLES / EVENT / ...
    sidecar_rx: int
    sidecar_tx: int

    def loop_fds(self) -> tuple[int, int]:
        """(rx, tx) for `LoopEnd`."""
        return (self.loop_rx, self.loop_tx)

    def sidecar_fds(self) -> tuple[int, int]:
        """The fds to hand to the sidecar process (`subprocess.Popen(pass_fds=...)`)."""
        return (self.sidecar_rx, self.sidecar_tx)


def make_channel(pipe_bytes: int | None = 1 << 20) -> ChannelFds:
    """Create both pipes; try to enlarge them to `pipe_bytes` (None keeps the OS default).

    The fds are not inheritable: pass the sidecar's pair with `pass_fds` (see
    `mrrig.rigio.sidecar_process.start_sidecar`).
    """
    to_sidecar_r, to_sidecar_w = os.pipe()
    to_loop_r, to_loop_w = os.pipe()
    if pipe_bytes is not None:
        for fd in (to_sidecar_w, to_loop_w):
            try:
                fcntl.fcntl(fd, _F_SETPIPE_SZ, pipe_bytes)
            except OSError as exc:
                log.warning(
                    "could not set pipe size to %d bytes (%s); using the default", pipe_bytes, exc
                )
    return ChannelFds(
        loop_rx=to_loop_r, loop_tx=to_sidecar_w, sidecar_rx=to_sidecar_r, sidecar_tx=to_loop_w
    )


def parse_frames(buf: bytearray) -> list[tuple[int, bytes]]:
    """Remove every complete frame from the front of `buf`; a partial frame stays there."""
    out: list[tuple[int, bytes]] = []
    pos = 0
    n = len(buf)
    while n - pos >= HEADER.size:
        mtype, length = HEADER.unpack_from(buf, pos)
        end = pos + HEADER.size + length
        if end > n:
            break
        out.append((mtype, bytes(buf[pos + HEADER.size : end])))
        pos = end
    if pos:
        del buf[:pos]
    return out


def decode_samples(payload: bytes) -> np.ndarray:
    """SAMPLES payload -> read-only SAMPLE_DTYPE array."""
    return np.frombuffer(payload, dtype=SAMPLE_DTYPE)


def decode_frames(payload: bytes) -> np.ndarray:
    """FRAMES payload -> read-only `canlog.FRAME_DTYPE` array."""
    from mrrig.rigio.canlog import FRAME_DTYPE

    return np.frombuffer(payload, dtype=FRAME_DTYPE)


def decode_json(payload: bytes) -> dict[str, Any]:
    """EVENT / STATUS / REPLY / SUMMARY / REQUEST payload -> dict."""
    return json.loads(payload)


def _encode_json(obj: dict[str, Any]) -> bytes:
    return json_text.dumps(obj, separators=(",", ":")).encode()


class _Writer:
    """Non-blocking, all-or-nothing framed writes; drops and counts what does not fit."""

    def __init__(self, fd: int) -> None:
        os.set_blocking(fd, False)
        self.fd = fd
        self.dropped = 0  # messages not written (pipe full, reader gone, too large)
        self.peer_gone = False

    def write(self, mtype: int, payload: bytes) -> bool:
        n = len(payload)
        if n > MAX_PAYLOAD:
            self.dropped += 1
            log.warning(
                "dropped a %s message of %d bytes (limit %d)", Msg(mtype).name, n, MAX_PAYLOAD
            )
            return False
        try:
            # one writev of <= PIPE_BUF bytes: atomic, so never a partial frame in the pipe
            os.writev(self.fd, (HEADER.pack(mtype, n), payload))
        except BlockingIOError:
            self.dropped += 1
            return False
        except BrokenPipeError:
            self.dropped += 1
            self.peer_gone = True
            return False
        return True

    def close(self) -> None:
        os.close(self.fd)


class LoopEnd:
    """The loop's side: never blocks, never raises on a full pipe or a dead sidecar.

    `dropped` counts messages lost (pipe full, sidecar gone, oversize JSON),
    `dropped_samples` the samples in the dropped SAMPLES messages, `closed` turns True once
    the sidecar is gone (EOF or broken pipe).
    """

    def __init__(self, rx_fd: int, tx_fd: int) -> None:
        os.set_blocking(rx_fd, False)
        self._rx = rx_fd
        # poll(0) on a poll object is the cheapest "anything there?" (no exception, no lists)
        self._poller = select.poll()
        self._poller.register(rx_fd, select.POLLIN)
        self._rx_buf = bytearray()
        self._w = _Writer(tx_fd)
        self.dropped_samples = 0
        self._eof = False

    @property
    def dropped(self) -> int:
        return self._w.dropped

    @property
    def closed(self) -> bool:
        return self._eof or self._w.peer_gone

    def send_samples(self, arr: np.ndarray) -> bool:
        """Send a SAMPLE_DTYPE array, split into messages of at most PIPE_BUF bytes.

        Returns False if any part was dropped.
        """
        if arr.dtype is not SAMPLE_DTYPE and arr.dtype != SAMPLE_DTYPE:
            raise TypeError(f"expected SAMPLE_DTYPE records, got {arr.dtype}")
        raw = arr.tobytes()  # cheaper than memoryview casts of a structured array
        if len(raw) <= MAX_PAYLOAD:
            if self._w.write(Msg.SAMPLES, raw):
                return True
            self.dropped_samples += arr.size
            return False
        ok = True
        for start in range(0, len(raw), _SAMPLES_STEP):
            part = raw[start : start + _SAMPLES_STEP]
            if not self._w.write(Msg.SAMPLES, part):
                self.dropped_samples += len(part) // SAMPLE_DTYPE.itemsize
                ok = False
        return ok

    def send_event(self, event: dict[str, Any]) -> bool:
        """An event: {"t": sensor time s, "level": "info"|"warning"|"error", "text": ..., ...}."""
        return self._w.write(Msg.EVENT, _encode_json(event))

    def send_status(self, status: dict[str, Any]) -> bool:
        return self._w.write(Msg.STATUS, _encode_json(status))

    def send_summary(self, summary: dict[str, Any]) -> bool:
        """The run's summary for the recording. A run with many faults lists more than one
        message holds: the first ones that fit are listed and the rest counted
        (`faults_not_listed`); each fault is an event of the recording in any case. So are
        the loop's stalls (`kernel_stalls`): fewer of them are listed first, the largest kept."""
        raw = _encode_json(summary)
        stalls = summary.get("kernel_stalls") or {}
        keep = len(stalls.get("windows") or [])
        while len(raw) > MAX_PAYLOAD and keep:
            keep //= 2
            summary = dict(summary, kernel_stalls=shortened(stalls, keep))
            raw = _encode_json(summary)
        faults = summary.get("faults") or []
        keep = len(faults)
        while len(raw) > MAX_PAYLOAD and keep:
            keep //= 2
            short = dict(summary, faults=faults[:keep], faults_not_listed=len(faults) - keep)
            raw = _encode_json(short)
        return self._w.write(Msg.SUMMARY, raw)

    def send_frames(self, frames: np.ndarray) -> int:
        """CAN frames for the bus log (`canlog.FRAME_DTYPE`), in messages of at most PIPE_BUF
        bytes; returns the frames dropped (pipe full, sidecar gone)."""
        raw = frames.tobytes()
        step = MAX_PAYLOAD // frames.dtype.itemsize * frames.dtype.itemsize
        dropped = 0
        for start in range(0, len(raw), step):
            part = raw[start : start + step]
            if not self._w.write(Msg.FRAMES, part):
                dropped += len(part) // frames.dtype.itemsize
        return dropped

    def send_stop(self) -> bool:
        return self._w.write(Msg.STOP, b"")

    def reply_writer(self) -> ReplyWriter:
        """A second writer on the pipe to the sidecar, for the control thread."""
        return ReplyWriter(self._w.fd)

    def poll(self) -> list[tuple[Msg, Any]]:
        """Non-blocking: the messages that have arrived, decoded.

        (Msg.REQUEST, (id, raw JSON bytes)), (Msg.FORCE_REF, (force_n, t_rx_monotonic_s)),
        (Msg.HEARTBEAT, None), (Msg.NOTICE, dict). The request's JSON is decoded by the
        control thread, not here.
        """
        if not self._poller.poll(0):
            return []
        try:
            data = os.read(self._rx, _READ_CHUNK)
        except BlockingIOError:
            return []
        if not data:
            self._eof = True
            return []
        self._rx_buf += data
        out: list[tuple[Msg, Any]] = []
        for mtype, payload in parse_frames(self._rx_buf):
            if mtype == Msg.FORCE_REF:
                out.append((Msg.FORCE_REF, FORCE_REF.unpack(payload)))
            elif mtype == Msg.REQUEST:
                (request_id,) = REQUEST_ID.unpack_from(payload)
                out.append((Msg.REQUEST, (request_id, payload[REQUEST_ID.size :])))
            elif mtype == Msg.HEARTBEAT:
                out.append((Msg.HEARTBEAT, None))
            elif mtype == Msg.NOTICE:
                out.append((Msg.NOTICE, decode_json(payload)))
            elif mtype == Msg.READY:
                out.append((Msg.READY, decode_json(payload)))
            else:
                log.warning("ignored unexpected message type %d from the sidecar", mtype)
        return out

    def wait_ready(self, timeout_s: float) -> str | None:
        """At start-up, before the loop runs: wait for the sidecar's READY. Returns None when it
        is up, else one line saying why not (its own error, its exit, or no answer in time)."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            self._poller.poll(left * 1e3)
            for mtype, payload in self.poll():
                if mtype == Msg.READY:
                    return payload.get("error")
            if self._eof:
                return "it exited before it was ready"
        return f"it was not ready within {timeout_s:g} s"

    def close(self) -> None:
        os.close(self._rx)
        self._w.close()


class ReplyWriter:
    """The control thread's writer on the loop's pipe to the sidecar (a dup of its fd): each
    reply is one atomic write, so it never splits a message of the loop's."""

    def __init__(self, tx_fd: int) -> None:
        self._w = _Writer(os.dup(tx_fd))

    def send_reply(self, reply: dict[str, Any]) -> bool:
        """The answer to a REQUEST; must carry the request's "id"."""
        return self._w.write(Msg.REPLY, _encode_json(reply))

    def reply_to(self, request_id: int):
        """A callable delivering a reply to request `request_id`."""
        return lambda reply: self.send_reply({**reply, "id": request_id})

    def close(self) -> None:
        self._w.close()


class SidecarEnd:
    """The sidecar's side: reads block (or select on `fileno()`), writes never block."""

    def __init__(self, rx_fd: int, tx_fd: int) -> None:
        os.set_blocking(rx_fd, True)
        self._rx = rx_fd
        self._rx_buf = bytearray()
        self._w = _Writer(tx_fd)
        self.eof = False

    @property
    def dropped(self) -> int:
        return self._w.dropped

    def fileno(self) -> int:
        return self._rx

    def read_ready(self) -> list[tuple[int, bytes]]:
        """One read (blocks if nothing is there); the complete frames, raw. Sets `eof`."""
        data = os.read(self._rx, _READ_CHUNK)
        if not data:
            self.eof = True
            return []
        self._rx_buf += data
        return parse_frames(self._rx_buf)

    def read(self, timeout_s: float | None) -> list[tuple[int, bytes]]:
        """Wait up to `timeout_s` for data; the complete frames that came, raw."""
        readable, _, _ = select.select([self._rx], [], [], timeout_s)
        return self.read_ready() if readable else []

    def send_request(self, request_id: int, raw: bytes) -> bool:
        """A request's JSON text (at most MAX_REQUEST_PAYLOAD bytes) under its id."""
        return self._w.write(Msg.REQUEST, REQUEST_ID.pack(request_id) + raw)

    def send_heartbeat(self) -> bool:
        return self._w.write(Msg.HEARTBEAT, b"")

    def send_notice(self, notice: dict[str, Any]) -> bool:
        return self._w.write(Msg.NOTICE, _encode_json(notice))

    def send_ready(self, error: str | None = None) -> bool:
        """Tell the loop the sidecar is up (`error` None) or could not start (one line)."""
        return self._w.write(Msg.READY, _encode_json({"error": error}))

    def send_force_ref(self, force_n: float, t_rx_s: float) -> bool:
        return self._w.write(Msg.FORCE_REF, FORCE_REF.pack(force_n, t_rx_s))

    def close(self) -> None:
        os.close(self._rx)
        self._w.close()
