"""The telemetry sidecar: every Zenoh (and Rerun) action of the daemon, in its own process.

The control loop talks to it over the pipes of `mrrig.rigio.ipc` and never runs a Zenoh callback.
The sidecar publishes `mrrig/<rig>/telemetry` (columnar JSON batches at `telemetry_hz`),
`mrrig/<rig>/status` (on change and every second) and `mrrig/<rig>/events`, holds the
liveliness token `mrrig/<rig>/alive/<session id>`, forwards `mrrig/<rig>/control` queries to
the loop as REQUESTs and `mrrig/<rig>/force_ref` puts as FORCE_REFs, answers
`mrrig/<rig>/status` queries with the latest status (what `mrrig rigs` reads), and writes the
recording. Every control request, answered or refused, becomes an audit event
(`mrrig.rigio.audit`).

One rig per name: it does not start where a token of its rig's name is alive, and a token of
its name that appears while it runs (a second daemon that missed it) is a `duplicate_rig`
fault for the loop, and every request but `status` and `disarm` is refused while it lasts.
A token counts only once it is attributed: the session whose id it carries answers the rig's
status (`mrrig/<rig>/status`, asked of every session every second while it is not); a token
alone, which any session allowed to declare it could, is logged and does not fault the rig.
The recording's file is checked every second: gone, replaced, shrunk or not grown is a
`recording_failed` (a removed directory otherwise loses the run silently), and the status
shows its path and size.

Zenoh callbacks only queue their item and wake the main thread through a pipe; all the work
is done by the main thread, which also closes the session (close waits for callbacks).

The process around it: `mrrig.rigio.sidecar_process`; the rig's key expressions and
liveliness tokens: `mrrig.rigio.zenoh_keys`.
"""

from __future__ import annotations

import logging
import math
import os
import queue
import select
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import zenoh

from mrrig import json_text
from mrrig.rigio import audit
from mrrig.rigio.control import RequestError, check_mark, parse_request
from mrrig.rigio.ipc import (
    HEARTBEAT_PERIOD_S,
    MAX_REQUEST_PAYLOAD,
    Msg,
    SidecarEnd,
    decode_frames,
    decode_json,
    decode_samples,
)
from mrrig.rigio.rig_topics import (
    JSON,
    alive_token,
    duplicate_text,
    keys,
    parse_force_ref,
    replier,
    telemetry_json,
    token_session,
)

log = logging.getLogger(__name__)

CONTROL_TIMEOUT_S = 1.0
STATUS_REPEAT_S = 1.0
NO_ANSWER = {"ok": False, "error": "daemon did not answer"}
# requests waiting for the daemon, at most; more get "busy" at once (a disarm always goes on)
MAX_IN_FLIGHT = 8
INBOX_BATCH = 50  # Zenoh queries and force references handled between looks at the loop
# a `status` control request is answered here from the loop's latest status (it sends one
# every 0.1 s) while that is younger than this; older (a stalled loop), it goes to the loop
STATUS_FRESH_S = 0.5
# a start-up's look for a live daemon of the same name: the answer of every reachable session
# comes within milliseconds (its peers are connected once the session is open)
DUPLICATE_CHECK_S = 1.0
# how often a token of the rig's name that no daemon has answered for is asked after again
ATTRIBUTE_PERIOD_S = 1.0
# the commands still taken while a second daemon of the rig's name is alive: the rest would
# be obeyed by both
_WHILE_DUPLICATE = ("status", "disarm")
RECORDING_CHECK_S = 1.0  # how often the recording's file is checked (inode, size)
# what a status publication is compared on: not the time or the counters, which always move
_STATUS_KEY = (
    "state",
    "armed",
    "controller",
    "reference",
    "fault",
    "fault_reason",
    "firmware_blocking",
    "recording",
)
_SHUTDOWN_READS = 64  # bounded final drain: a loop that keeps writing cannot hold us


class BusLog(Protocol):
    """What the sidecar needs of `mrrig.rigio.canlog.BusLogWriter`."""

    def write(self, frames: np.ndarray) -> None: ...
    def close(self) -> None: ...


class SampleSink(Protocol):
    """What the sidecar needs of `mrrig.rigio.recording.Recorder`."""

    def add_samples(self, arr: np.ndarray) -> None: ...
    def add_event(self, t_s: float, level: str, text: str, **fields: Any) -> None: ...

    failed: str  # why writing the file failed, "" while it has not
    path: Path

    def check_file(self) -> int: ...
    def add_summary(self, d: dict[str, Any]) -> None: ...
    def close(self) -> None: ...
    def abandon(self) -> None: ...


def _is_disarm(query: zenoh.Query) -> bool:
    """Whether a queued control query is a well-formed disarm."""
    try:
        raw = query.payload.to_bytes() if query.payload else b""
        return len(raw) <= MAX_REQUEST_PAYLOAD and parse_request(raw)["cmd"] == "disarm"
    except (RequestError, AttributeError):
        return False


@dataclass
class _Pending:
    query: zenoh.Query
    deadline_s: float
    request: dict[str, Any]
    requester: dict[str, Any]


class Sidecar:
    """The sidecar's state and main loop (main thread); uses the session, does not close it."""

    def __init__(
        self,
        rig: str,
        session: zenoh.Session | None,
        end: SidecarEnd,
        recorder: SampleSink | None,
        telemetry_hz: float,
        warnings: list[str] | None = None,
        bus_log: BusLog | None = None,
        identity: dict[str, Any] | None = None,
    ) -> None:
        """`warnings` (an insecure Zenoh config's) go into every status and the recording;
        `bus_log` writes the loop's FRAMES; `identity` (`mrrig.rigio.run_identity`): the run,
        registered in its catalog and published on `runs` with the summary at the end."""
        self._bus_log = bus_log
        self._identity = identity
        self._summary: dict[str, Any] | None = None
        self._record_path = getattr(recorder, "path", None)
        self.rig = rig
        self._keys = keys(rig)
        self._session = session
        self._end = end
        self._recorder = recorder
        self._period_s = 1.0 / telemetry_hz
        self._inbox: queue.SimpleQueue[tuple[str, Any, float]] = queue.SimpleQueue()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._stop = False
        self._batches: list[np.ndarray] = []
        self._last_t_s = 0.0
        self._last_status: bytes | None = None  # as the loop sent it
        self._last_status_key: tuple | None = None
        self._status_rx_s = -math.inf  # when the loop's latest status came
        self._heartbeat_s = -math.inf
        self._status_out = b""  # as published: with the warnings
        self._warnings = list(warnings or [])
        self._status_sent_s = 0.0
        self._pending: dict[int, _Pending] = {}
        self._next_id = 1
        self._entities: list[Any] = []
        self._pubs: dict[str, zenoh.Publisher] = {}  # empty without a session
        self._own_token = ""
        self._duplicates: set[str] = set()  # other daemons' tokens of this rig's name
        self._unattributed: set[str] = set()  # tokens of its name no daemon answered for yet
        self._attributed_s = -math.inf  # when the rig's status was last asked of all
        self._asking: Any = None  # the replies to that question (read here, no callback)
        self._recording_checked_s = time.monotonic()
        self._recording_bytes = 0

    # -- called from Zenoh threads or signal handlers: queue and wake only ------------------
    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"\0")
        except BlockingIOError:
            pass  # already awake: the pipe holds unread wake bytes

    def _on_query(self, query: zenoh.Query) -> None:
        self._inbox.put(("query", query, time.monotonic()))
        self._wake()

    def _on_status_query(self, query: zenoh.Query) -> None:
        self._inbox.put(("status_query", query, time.monotonic()))
        self._wake()

    def _on_alive(self, sample: zenoh.Sample) -> None:
        put = sample.kind == zenoh.SampleKind.PUT
        self._inbox.put(("alive", (str(sample.key_expr), put), time.monotonic()))
        self._wake()

    def _on_force_ref(self, sample: zenoh.Sample) -> None:
        self._inbox.put(("force_ref", sample.payload.to_bytes(), time.monotonic()))
        self._wake()

    def request_stop(self, *_: Any) -> None:
        """Signal-handler safe: ask the main loop to finish."""
        self._stop = True
        self._wake()

    # -- main thread --------------------------------------------------------------------------
    def run(self) -> None:
        """Declare everything, serve until STOP / EOF / request_stop, then undeclare."""
        s = self._session
        if s is not None:
            self._pubs = {
                name: s.declare_publisher(self._keys[name], encoding=JSON)
                for name in ("telemetry", "status", "events")
            }
            self._entities = [
                *self._pubs.values(),
                s.declare_queryable(self._keys["control"], self._on_query),
                s.declare_queryable(self._keys["status"], self._on_status_query),
                s.declare_subscriber(self._keys["force_ref"], self._on_force_ref),
            ]
            # a daemon of this name that start-up missed (not yet reachable) shows up here
            self._entities.append(
                s.liveliness().declare_subscriber(self._keys["alive"], self._on_alive, history=True)
            )
            # last, so a token seen by others means the sidecar is ready
            self._own_token = alive_token(self.rig, str(s.zid()))
            self._entities.append(s.liveliness().declare_token(self._own_token))
            log.info("sidecar for rig %r serving on mrrig/%s/*", self.rig, self.rig)
        else:
            log.info("sidecar for rig %r: recording only, no Zenoh", self.rig)
        for warning in self._warnings:
            log.warning("%s", warning)
            self._event({"t": 0.0, "level": "warning", "text": warning, "kind": "insecure"})
        try:
            self._serve()
        finally:
            self._shutdown()

    def _serve(self) -> None:
        next_telemetry_s = time.monotonic() + self._period_s
        while not self._stop:
            now = time.monotonic()
            self._heartbeat(now)
            self._attribute(now)
            wake_at = min(
                (
                    next_telemetry_s,
                    self._heartbeat_s + HEARTBEAT_PERIOD_S,
                    *(p.deadline_s for p in self._pending.values()),
                )
            )
            if self._last_status is not None:
                wake_at = min(wake_at, self._status_sent_s + STATUS_REPEAT_S)
            if self._inbox.qsize():  # a burst left some: the loop's messages first, then on
                wake_at = now
            readable, _, _ = select.select(
                [self._end, self._wake_r], [], [], max(0.0, wake_at - now)
            )
            if self._wake_r in readable:
                self._drain_wake()
            if self._inbox.qsize():
                self._handle_inbox()
            if self._end in readable:
                self._handle_loop_messages(self._end.read_ready())
                if self._end.eof:
                    log.info("loop pipe closed: stopping")
                    self._stop = True
            now = time.monotonic()
            if now >= next_telemetry_s:
                self._publish_telemetry()
                next_telemetry_s = max(next_telemetry_s + self._period_s, now)
            if self._last_status is not None and now >= self._status_sent_s + STATUS_REPEAT_S:
                self._publish_status(self._status_out, now)
            if now - self._recording_checked_s >= RECORDING_CHECK_S:
                self._check_recording(now)
            self._expire_queries(now)

    def _heartbeat(self, now: float) -> None:
        """The sign of life the daemon watches: sent while this loop makes progress."""
        if now - self._heartbeat_s >= HEARTBEAT_PERIOD_S:
            self._end.send_heartbeat()
            self._heartbeat_s = now

    def _drain_wake(self) -> None:
        try:
            while os.read(self._wake_r, 4096):
                pass
        except BlockingIOError:
            pass

    def _handle_inbox(self) -> None:
        """At most INBOX_BATCH items: a burst of requests does not hold up the loop's
        messages, the heartbeat or the telemetry. A query that waited longer than the
        daemon's answer timeout is answered busy, unread, except a disarm: it only makes
        the rig safer, so it is always passed on (a client that sees `busy` to a disarm would
        believe the rig still armed)."""
        for _ in range(INBOX_BATCH):
            try:
                kind, item, t_rx_s = self._inbox.get_nowait()
            except queue.Empty:
                return
            now = time.monotonic()
            self._heartbeat(now)
            if kind == "query" and now - t_rx_s > CONTROL_TIMEOUT_S and not _is_disarm(item):
                self._reply(item, {"ok": False, "error": "busy: the control plane is overloaded"})
                continue
            try:
                if kind == "query":
                    self._handle_query(item)
                elif kind == "alive":
                    self._handle_alive(*item)
                elif kind == "status_query":
                    if self._status_out:
                        self._reply(item, self._status_out, self._keys["status"])
                    else:
                        item.drop()  # no status yet: no answer, as if the rig were not there
                else:
                    self._handle_force_ref(item, t_rx_s)
            except Exception:  # one request or sample never ends the control plane
                log.exception("handling a %s failed", kind)
                if kind == "query":
                    self._reply(item, {"ok": False, "error": "internal error in the sidecar"})

    def _handle_query(self, query: zenoh.Query) -> None:
        raw = query.payload.to_bytes() if query.payload else b""
        requester = audit.requester(query, self._session)
        try:
            request = parse_request(raw)
        except RequestError as exc:
            # the audit keeps a bounded excerpt of what was refused
            self._answer(query, raw[:200], requester, {"ok": False, "error": str(exc)})
            return
        if self._duplicates and request["cmd"] not in _WHILE_DUPLICATE:
            refused = {"ok": False, "error": duplicate_text(self.rig, list(self._duplicates))}
            self._answer(query, request, requester, refused)
            return
        if request["cmd"] == "mark":
            self._answer(query, request, requester, self._mark(request))
            return
        now = time.monotonic()
        if request["cmd"] == "status" and now - self._status_rx_s <= STATUS_FRESH_S:
            status = decode_json(self._last_status)
            status["age_s"] = round(now - self._status_rx_s, 4)
            self._answer(query, request, requester, {"ok": True, "status": status})
            return
        if len(self._pending) >= MAX_IN_FLIGHT and request["cmd"] != "disarm":
            busy = {"ok": False, "error": f"busy: {MAX_IN_FLIGHT} requests in flight"}
            self._answer(query, request, requester, busy)
            return
        request_id = self._next_id
        self._next_id += 1
        if len(raw) > MAX_REQUEST_PAYLOAD or not self._end.send_request(request_id, raw):
            self._answer(query, request, requester, NO_ANSWER)
            return
        self._pending[request_id] = _Pending(query, now + CONTROL_TIMEOUT_S, request, requester)

    def _mark(self, request: dict[str, Any]) -> dict[str, Any]:
        """A marker in the recording (a plan's step start and end, with its settings): an
        event of kind `mark` at the latest sensor time, before the request's audit event."""
        try:
            text, data = check_mark(request)
        except RequestError as exc:
            return {"ok": False, "error": str(exc)}
        t = self._last_t_s
        self._event({"t": t, "level": "info", "text": text, "kind": "mark", "data": data})
        return {"ok": True, "t": t}

    def _answer(
        self,
        query: zenoh.Query,
        request: dict[str, Any] | bytes,
        requester: dict[str, Any],
        reply: dict[str, Any],
    ) -> None:
        """Reply to a control query, and audit the request with its result."""
        self._event(audit.event(self._last_t_s, request, reply, requester))
        if self._warnings and isinstance(reply.get("status"), dict):
            reply = {**reply, "status": {**reply["status"], "security_warning": self._warnings}}
        self._reply(query, reply)

    def _reply(
        self, query: zenoh.Query, reply: dict[str, Any] | bytes, key: str | None = None
    ) -> None:
        text = reply if isinstance(reply, bytes) else json_text.dumps(reply)
        try:
            query.reply(key or self._keys["control"], text, encoding=JSON)
        except zenoh.ZError as exc:
            log.warning("could not reply to a control query: %s", exc)
        query.drop()  # sends the final answer now instead of at garbage collection

    def _expire_queries(self, now: float) -> None:
        for request_id in [i for i, p in self._pending.items() if now >= p.deadline_s]:
            log.warning("daemon did not answer control request %d", request_id)
            p = self._pending.pop(request_id)
            self._answer(p.query, p.request, p.requester, NO_ANSWER)

    def _handle_alive(self, token: str, put: bool) -> None:
        """A liveliness token of this rig's name came or went: another daemon's, once its
        session answers for it (`_attributed`), is a fault."""
        if token == self._own_token:
            return
        if not put:
            self._unattributed.discard(token)
            if token in self._duplicates:
                self._duplicates.discard(token)
                log.warning("the second daemon of rig %r is gone (%s)", self.rig, token)
            return
        log.warning(
            "liveliness token %s of rig %r: a second daemon once its session answers the"
            " rig's status; until then it is not taken for one",
            token,
            self.rig,
        )
        self._unattributed.add(token)
        self._attributed_s = -math.inf  # ask now

    def _attribute(self, now: float) -> None:
        """Ask every session for the rig's status while a token is unattributed, and take
        the answers that came (polled: a late one after shutdown has nothing to wake)."""
        while self._asking is not None:
            try:
                reply = self._asking.try_recv()
            except zenoh.ZError:  # all answers in
                self._asking = None
                break
            if reply is None:
                break
            if (zid := replier(reply)) is not None:
                self._attributed(zid)
        if not self._unattributed or now - self._attributed_s < ATTRIBUTE_PERIOD_S:
            return
        self._attributed_s = now
        try:
            self._asking = self._session.get(
                self._keys["status"], target=zenoh.QueryTarget.ALL, timeout=ATTRIBUTE_PERIOD_S
            )
        except zenoh.ZError as exc:
            log.warning("could not ask for the status of rig %r: %s", self.rig, exc)

    def _attributed(self, zid: str) -> None:
        """A session answered the rig's status: its token is another daemon's."""
        for token in [t for t in self._unattributed if token_session(t) == zid]:
            self._unattributed.discard(token)
            self._duplicate(token)

    def _duplicate(self, token: str) -> None:
        self._duplicates.add(token)
        reason = duplicate_text(self.rig, [token])
        log.error("%s", reason)
        self._end.send_notice({"kind": "duplicate_rig", "reason": reason})
        self._event(
            {"t": self._last_t_s, "level": "error", "text": reason, "kind": "duplicate_rig"}
        )

    def _handle_force_ref(self, payload: bytes, t_rx_s: float) -> None:
        try:
            force_n = parse_force_ref(payload)
        except ValueError as exc:
            text = f"malformed force_ref ignored: {exc}"
            log.warning("%s (payload %r)", text, payload[:80])
            self._event(
                {
                    "t": self._last_t_s,
                    "level": "warning",
                    "text": text,
                    "kind": "force_ref_malformed",
                }
            )
            return
        if not self._end.send_force_ref(force_n, t_rx_s):
            log.warning("force_ref dropped: the pipe to the loop is full")

    def _handle_loop_messages(self, messages: list[tuple[int, bytes]]) -> None:
        for mtype, payload in messages:
            try:
                self._handle_loop_message(mtype, payload)
            except Exception:  # a message that cannot be handled is logged, not fatal
                log.exception("handling a %s message from the loop failed", mtype)

    def _handle_loop_message(self, mtype: int, payload: bytes) -> None:
        if mtype == Msg.SAMPLES:
            batch = decode_samples(payload)
            if batch.size:
                self._batches.append(batch)
                self._last_t_s = float(batch["t"][-1])
                self._record("add_samples", batch)
        elif mtype == Msg.EVENT:
            self._event(decode_json(payload), payload)
        elif mtype == Msg.STATUS:
            # the loop sends one every 0.1 s; published on a change of state and every second
            now = time.monotonic()
            status = decode_json(payload)
            key = tuple(status.get(k) for k in _STATUS_KEY)
            payload = self._with_recording(status, payload)
            self._last_status, self._status_rx_s = payload, now
            self._status_out = self._with_warnings(payload)
            if key != self._last_status_key:
                self._last_status_key = key
                self._publish_status(self._status_out, now)
        elif mtype == Msg.REPLY:
            self._handle_reply(decode_json(payload))
        elif mtype == Msg.SUMMARY:
            self._summary = decode_json(payload)
            self._record("add_summary", self._summary)
        elif mtype == Msg.FRAMES:
            if self._bus_log is not None:
                self._bus_log.write(decode_frames(payload))
        elif mtype == Msg.STOP:
            log.info("STOP from the loop")
            self._stop = True
        else:
            log.warning("ignored unknown message type %d from the loop", mtype)

    def _handle_reply(self, reply: dict[str, Any]) -> None:
        pending = self._pending.pop(reply.pop("id", None), None)
        if pending is None:
            log.warning("reply to an unknown or expired request: %s", reply)
            return
        self._answer(pending.query, pending.request, pending.requester, reply)

    def _with_recording(self, status: dict[str, Any], payload: bytes) -> bytes:
        """The loop's status with the recording this process writes: path (absolute, as the
        run's catalog row has it: a plan step registered with it gets the file's sha256 when
        the daemon's run is registered), size at its latest check, samples sent (the loop
        reports only a failed one)."""
        if self._recorder is None or status.get("recording") is not None:
            return payload
        status["recording"] = {
            "path": str(self._recorder.path.resolve()),
            "bytes": self._recording_bytes,
            "frames": self._recorder.frames,
        }
        return json_text.dumps(status).encode()

    def _with_warnings(self, status: bytes) -> bytes:
        if not self._warnings:
            return status
        return json_text.dumps({**decode_json(status), "security_warning": self._warnings}).encode()

    def _event(self, event: dict[str, Any], raw: bytes | None = None) -> None:
        self._publish("events", raw if raw is not None else json_text.dumps(event))
        fields = {k: v for k, v in event.items() if k not in ("t", "level", "text")}
        self._record(
            "add_event",
            float(event.get("t", self._last_t_s)),
            str(event.get("level", "info")),
            str(event.get("text", "")),
            **fields,
        )

    def _publish_status(self, payload: bytes, now: float) -> None:
        self._publish("status", payload)
        self._status_sent_s = now

    def _publish(self, name: str, payload: bytes | str) -> None:
        pub = self._pubs.get(name)
        if pub is not None:
            pub.put(payload)

    def _publish_telemetry(self) -> None:
        if not self._batches:
            return
        batch = np.concatenate(self._batches)
        self._batches = []
        if "telemetry" in self._pubs:
            utc_start = (self._identity or {}).get("started_utc")
            self._publish("telemetry", telemetry_json(self.rig, batch, utc_start))

    def _record(self, method: str, *args: Any, **kwargs: Any) -> None:
        if self._recorder is None:
            return
        try:
            getattr(self._recorder, method)(*args, **kwargs)
        except Exception as exc:
            log.exception("recording failed; recording stopped")
            self._recording_lost(f"{exc}; {self._recorder.path} is truncated")

    def _check_recording(self, now: float) -> None:
        self._recording_checked_s = now
        if self._recorder is None:
            return
        try:
            self._recording_bytes = self._recorder.check_file()
        except OSError as exc:  # `RecordingError`: the file is gone, replaced or cut
            log.error("recording lost: %s", exc)
            self._recording_lost(str(exc))

    def _recording_lost(self, reason: str) -> None:
        """Keep telemetry alive; the recording is lost from here on, loudly: an event, and
        the loop is told (a fault: a test run whose record is gone is stopped)."""
        # told first: closing a stream whose writer hangs may hang too
        self._end.send_notice({"kind": "recording_failed", "reason": reason})
        self._publish(
            "events",
            json_text.dumps(
                {
                    "t": self._last_t_s,
                    "level": "error",
                    "text": f"recording failed; recording stopped: {reason}",
                    "kind": "recording_failed",
                    "reason": reason,
                }
            ),
        )
        recorder, self._recorder = self._recorder, None
        if recorder.failed:  # its file writer failed: closing could hang
            recorder.abandon()
        else:
            self._close_recorder_obj(recorder)

    def _close_recorder(self) -> None:
        recorder, self._recorder = self._recorder, None
        if recorder is not None:
            self._close_recorder_obj(recorder)

    @staticmethod
    def _close_recorder_obj(recorder: SampleSink) -> None:
        try:
            recorder.close()
        except Exception:
            log.exception("closing the recording failed")

    def _shutdown(self) -> None:
        # what the loop wrote just before stopping (summary, last samples) still counts
        for _ in range(_SHUTDOWN_READS):
            if self._end.eof or not select.select([self._end], [], [], 0)[0]:
                break
            self._handle_loop_messages(self._end.read_ready())
        self._publish_telemetry()
        for p in self._pending.values():
            self._answer(p.query, p.request, p.requester, {"ok": False, "error": "daemon stopping"})
        self._pending.clear()
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                log.warning("undeclare failed: %s", exc)
        self._entities = []
        self._close_recorder()
        self._register_run()
        os.close(self._wake_r)
        os.close(self._wake_w)

    def _register_run(self) -> None:
        """The finished run into its catalog (spooled locally where a lab's database cannot
        be reached; journalled beside its recording where no catalog takes it, replayed at
        the next registration or `mrrig runs`) and on `mrrig/<rig>/runs`. After the loop has
        ended: nothing waits on the database but this process's exit. A daemon that sent no
        summary (killed, crashed) is registered too, as `crashed`."""
        ident = self._identity
        if ident is None:
            return
        from mrrig.catalog import CatalogError, RecordError
        from mrrig.catalog.finished import run_record
        from mrrig.catalog.journal import register_journalled, replay

        if self._summary is None:
            log.error("run %s: the daemon ended without a summary", ident.get("run_id"))
        try:
            record = run_record(ident, self._summary, self._record_path)
        except RecordError as exc:
            log.error("run %s: no catalog record: %s", ident.get("run_id"), exc)
            return
        if self._session is not None:
            try:
                self._session.put(
                    self._keys["runs"], json_text.dumps(record.to_json()), encoding=JSON
                )
            except zenoh.ZError as exc:
                log.warning("publishing the run on %s failed: %s", self._keys["runs"], exc)
        if ident.get("catalog") is None:
            return
        try:
            where = register_journalled(record, ident["catalog"], ident.get("catalog_spool"))
        except CatalogError as exc:
            log.error("run %s not registered: %s", record.run_id, exc)
            return
        spooled = " (spooled: the catalog asked for was unreachable)" if where.spooled else ""
        log.info("run %s registered in %s%s", record.run_id, where.url, spooled)
        if self._record_path is not None:
            replay(self._record_path.parent)
