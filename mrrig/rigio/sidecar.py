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

Run: python -m mrrig.rigio.sidecar --rig NAME --zenoh-config FILE|'' --record PATH|'' --rx-fd N
--tx-fd M [--telemetry-hz 50] [--live-url URL] [--nice 10] [--insecure]; or
`start_sidecar(...)` from the daemon. An empty Zenoh config runs without Zenoh (recording only).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import queue
import select
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import zenoh

from mrrig import json_text
from mrrig.loop.samples import FIELDS, SAMPLE_DTYPE
from mrrig.rigio import audit
from mrrig.rigio.control import RequestError, check_mark, parse_request
from mrrig.rigio.ipc import (
    HEARTBEAT_PERIOD_S,
    MAX_REQUEST_PAYLOAD,
    ChannelFds,
    Msg,
    SidecarEnd,
    decode_frames,
    decode_json,
    decode_samples,
)
from mrrig.rigio.run_identity import operator_of
from mrrig.rigio.zenoh_config import (
    ZenohConfigError,
    check_secure,
    load_zenoh_config,
    zenoh_error_text,
)

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON
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
_FLOAT_FIELDS = tuple(f for f in FIELDS if SAMPLE_DTYPE[f].kind == "f")


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


def keys(rig: str) -> dict[str, str]:
    """The rig's Zenoh key expressions (spec/system.md); `alive` selects the liveliness tokens
    of every daemon of that name (`alive_token`)."""
    names = ("telemetry", "status", "events", "force_ref", "control", "runs")
    return {name: f"mrrig/{rig}/{name}" for name in names} | {"alive": f"mrrig/{rig}/alive/*"}


def alive_token(rig: str, session_id: str) -> str:
    """One daemon's liveliness token: with its session's id, so that two daemons of one name
    are two tokens (Zenoh shows two tokens of one key as one)."""
    return f"mrrig/{rig}/alive/{session_id}"


_DUPLICATE = "is already served on this Zenoh network"


def is_duplicate_text(error: str) -> bool:
    """Whether a start-up error is `duplicate_text`'s."""
    return _DUPLICATE in error


def duplicate_text(rig: str, others: list[str]) -> str:
    """The one line for a second daemon of the rig's name on the network."""
    return (
        f"rig {rig!r} {_DUPLICATE} (liveliness token"
        f" {', '.join(sorted(others))}): a second daemon of one name obeys every request"
        " meant for the first; stop one, or give this one another [rig] name"
    )


def token_session(token: str) -> str:
    """The session id an `alive_token` carries."""
    return token.rsplit("/", 1)[-1]


def replier(reply: zenoh.Reply) -> str | None:
    """The id of the session that sent a reply (None where Zenoh does not say)."""
    if reply.ok is None or reply.replier_id is None:
        return None
    return str(reply.replier_id.zid)


def alive_elsewhere(session: zenoh.Session, rig: str, timeout_s: float) -> list[str]:
    """The liveliness tokens of other daemons of the rig's name that this session reaches:
    those whose session also answers the rig's status. A token that none answers for is left
    to the running sidecar, which asks again every second (a daemon that has no status yet
    answers then)."""
    own = alive_token(rig, str(session.zid()))
    replies = session.liveliness().get(keys(rig)["alive"], timeout=timeout_s)
    tokens = [str(r.ok.key_expr) for r in replies if r.ok is not None]
    tokens = [t for t in tokens if t != own]
    if not tokens:
        return []
    status = session.get(keys(rig)["status"], target=zenoh.QueryTarget.ALL, timeout=timeout_s)
    answered = {replier(r) for r in status}
    return [t for t in tokens if token_session(t) in answered]


def telemetry_json(rig: str, batch: np.ndarray, utc_start: str | None = None) -> str:
    """Columnar telemetry message: {"rig", "fields": {name: [values]}}, and with the run's
    `utc_start` (ISO 8601: the UTC time of `t = 0`, the run identity's `started_utc`) the
    key `utc_start`, from which a client gives each sample its UTC time.

    Non-finite floats become null (JSON has no NaN/Infinity).
    """
    fields: dict[str, list[Any]] = {}
    for name in FIELDS:
        col = batch[name]
        values = col.tolist()
        if name in _FLOAT_FIELDS and not np.isfinite(col).all():
            values = [v if math.isfinite(v) else None for v in values]
        fields[name] = values
    message: dict[str, Any] = {"rig": rig, "fields": fields}
    if utc_start is not None:
        message["utc_start"] = utc_start
    return json.dumps(message, separators=(",", ":"))


def _is_disarm(query: zenoh.Query) -> bool:
    """Whether a queued control query is a well-formed disarm."""
    try:
        raw = query.payload.to_bytes() if query.payload else b""
        return len(raw) <= MAX_REQUEST_PAYLOAD and parse_request(raw)["cmd"] == "disarm"
    except (RequestError, AttributeError):
        return False


def parse_force_ref(payload: bytes) -> float:
    """A force_ref payload (JSON number or {"force_n": x}) -> finite force in N.

    Raises ValueError on anything else.
    """
    value = json.loads(payload)
    if isinstance(value, dict):
        value = value.get("force_n")
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError('expected a JSON number or {"force_n": number}')
    force_n = float(value)
    if not math.isfinite(force_n):
        raise ValueError("force is not finite")
    return force_n


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


def lower_priority(nice: int) -> None:
    """SCHED_BATCH + nice for this thread and the threads it starts later (Zenoh's): at
    normal priority the sidecar, woken by the loop's pipe writes, preempts the loop."""
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
        os.nice(nice)
    except (OSError, AttributeError) as exc:  # not Linux, or not permitted
        log.warning("could not lower the sidecar's priority: %s", exc)


def run_sidecar(
    rig: str,
    zenoh_config: str | Path | None,
    record: str | Path | None,
    rx_fd: int,
    tx_fd: int,
    telemetry_hz: float = 50.0,
    live_url: str | None = None,
    insecure: bool = False,
    can_log: tuple[str, str] | None = None,
    identity: dict[str, Any] | None = None,
) -> int:
    """Run until STOP, EOF, SIGTERM or SIGINT; returns the exit status: 0, 2 for a refused
    config (`check_secure`: off loopback without authentication and access control, unless
    `insecure`) or a daemon of the rig's name alive on the network, 3 if the session cannot
    open (port taken) or the recording cannot be written.

    Once its session and recording are open (or have failed) it sends READY to the loop, with
    the failure as one line: the daemon stops its start-up on it (a rig must not run
    unobserved)."""
    warnings: list[str] = []
    end = SidecarEnd(rx_fd, tx_fd)
    try:
        conf = load_zenoh_config(zenoh_config) if zenoh_config else None
        if conf is not None:
            warnings = check_secure(conf, str(zenoh_config), insecure)
        if identity is not None and not identity.get("operator"):
            identity = {**identity, "operator": operator_of(conf)}
    except ZenohConfigError as exc:
        log.debug("%s", exc)
        end.send_ready(str(exc))
        end.close()
        return 2
    # past a file size limit a write fails (EFBIG) instead of killing the process: the
    # recording then fails as on a full disk, and telemetry goes on
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    stop_early: list[int] = []  # a signal before the Sidecar exists still stops it
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda num, _frame: stop_early.append(num))
    recorder: SampleSink | None = None
    session: zenoh.Session | None = None
    bus_log = None
    try:
        # Zenoh first: a start that fails there (its port taken, another daemon of this
        # rig's name) leaves no stray recording or bus log behind
        try:
            session = zenoh.open(conf) if conf is not None else None
        except zenoh.ZError as exc:  # e.g. the listen port is taken
            text = zenoh_error_text(exc)
            hint = ""
            if "address already in use" in text.lower():
                hint = (
                    " (another daemon or zenohd listens there: stop it, or give this rig"
                    " another port in its Zenoh config)"
                )
            log.debug("%s: cannot open the Zenoh session: %s", zenoh_config, text)
            end.send_ready(f"{zenoh_config}: cannot open the Zenoh session: {text}{hint}")
            return 3
        others = alive_elsewhere(session, rig, DUPLICATE_CHECK_S) if session is not None else []
        if others:
            end.send_ready(duplicate_text(rig, others))
            return 2
        if can_log is not None:
            from mrrig.rigio.canlog import BusLogError, BusLogWriter

            try:
                bus_log = BusLogWriter(*can_log)
            except BusLogError as exc:
                end.send_ready(str(exc))
                return 3
        if record:
            from mrrig.rigio.recording import Recorder  # rerun is heavy: only when recording

            try:
                recorder = Recorder(
                    record, rig, flush_interval_s=0.5, live_url=live_url, identity=identity
                )
            except Exception as exc:  # noqa: BLE001 - reported to the daemon as one line
                text = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
                end.send_ready(f"cannot write the recording {record}: {text}")
                return 3
        sidecar = Sidecar(rig, session, end, recorder, telemetry_hz, warnings, bus_log, identity)
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, sidecar.request_stop)
        if stop_early:
            sidecar.request_stop()
        end.send_ready()
        sidecar.run()
    finally:
        if session is not None:
            session.close()
        if recorder is not None:
            recorder.close()  # idempotent; covers a failure before run() took it over
        if bus_log is not None:
            bus_log.close()
        end.close()
    log.info("sidecar stopped")
    if recorder is not None and recorder.failed:
        # rerun's exit handler waits for the file writer that failed, for ever: leave without
        logging.shutdown()
        os._exit(0)
    return 0


def start_sidecar(
    rig: str,
    zenoh_config: str | Path | None,
    fds: ChannelFds,
    record: str | Path | None = None,
    telemetry_hz: float = 50.0,
    live_url: str | None = None,
    insecure: bool = False,
    can_log: tuple[str | Path, str] | None = None,
    identity: dict[str, Any] | None = None,
) -> subprocess.Popen[bytes]:
    """Start the sidecar process on the sidecar's ends of `fds`, and close those ends here.

    `zenoh_config` None: no Zenoh at all (recording only); `record` None: no recording;
    `can_log` (path, channel name written in it): the bus log of `mrrig.rigio.canlog`.

    The child gets its own session (process group), so a Ctrl-C at the terminal reaches only
    the daemon, which then sends its summary and STOP.
    """
    cmd = [
        sys.executable,
        "-m",
        "mrrig.rigio.sidecar",
        "--rig",
        rig,
        "--zenoh-config",
        str(zenoh_config or ""),
        "--record",
        str(record or ""),
        "--rx-fd",
        str(fds.sidecar_rx),
        "--tx-fd",
        str(fds.sidecar_tx),
        "--telemetry-hz",
        str(telemetry_hz),
    ]
    if live_url:
        cmd += ["--live-url", live_url]
    if insecure:
        cmd.append("--insecure")
    if can_log is not None:
        cmd += ["--can-log", str(can_log[0]), "--can-log-channel", can_log[1]]
    if identity is not None:
        cmd += ["--identity", json_text.dumps(identity)]
    proc = subprocess.Popen(cmd, pass_fds=fds.sidecar_fds(), start_new_session=True)
    # the loop must see EOF / EPIPE when the sidecar dies, so it holds no copy of these
    os.close(fds.sidecar_rx)
    os.close(fds.sidecar_tx)
    return proc


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mrrig.rigio.sidecar", description=__doc__)
    parser.add_argument("--rig", required=True)
    parser.add_argument("--zenoh-config", required=True, help="'' for no Zenoh (recording only)")
    parser.add_argument("--record", default="", help="recording path; '' records nothing")
    parser.add_argument("--rx-fd", type=int, required=True)
    parser.add_argument("--tx-fd", type=int, required=True)
    parser.add_argument("--telemetry-hz", type=float, default=50.0)
    parser.add_argument("--live-url", default=None, help="also stream to a Rerun viewer")
    parser.add_argument(
        "--nice",
        type=int,
        default=10,
        help="niceness increment (SCHED_BATCH too), so waking the sidecar "
        "does not preempt the control loop; 0 keeps the priority",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="allow a config off loopback without authentication and access control "
        "(a closed lab network); warned in every status and the recording",
    )
    parser.add_argument("--can-log", default=None, help="bus log file (.blf, .asc, .log, ...)")
    parser.add_argument("--can-log-channel", default="can0", help="channel name in the bus log")
    parser.add_argument("--log-level", default="INFO")
    parser.add_argument("--identity", default=None, help="the run's identity (JSON)")
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=args.log_level, format="%(asctime)s sidecar %(levelname)s %(name)s: %(message)s"
    )
    if args.nice:
        lower_priority(args.nice)
    return run_sidecar(
        args.rig,
        args.zenoh_config or None,
        args.record or None,
        args.rx_fd,
        args.tx_fd,
        args.telemetry_hz,
        args.live_url,
        args.insecure,
        (args.can_log, args.can_log_channel) if args.can_log else None,
        json.loads(args.identity) if args.identity else None,
    )


if __name__ == "__main__":
    sys.exit(main())
