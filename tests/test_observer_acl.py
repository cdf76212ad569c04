"""Observers only look (issue 40, finding 3): with mutual TLS and the shipped access control an
observer's certificate may subscribe to what the rig publishes, get its status and follow its
liveliness; every other message kind on every key of the rig is denied: its puts and deletes
reach nobody, its liveliness token neither shows nor faults the rig (`duplicate_rig`), its
queryables are never asked. Real sessions, real certificates, the real sidecar (the daemon,
armed: tests/test_observer_token_on_an_armed_rig.py)."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from mrrig.loop.samples import SAMPLE_DTYPE
from mrrig.rigio import certs
from mrrig.rigio.canbus.bus import find_free_port
from mrrig.rigio.ipc import LoopEnd, Msg, make_channel
from mrrig.rigio.rig_topics import alive_token, keys
from mrrig.rigio.sidecar_process import start_sidecar
from tests.test_zenoh_security import _lab, _open, _status, _template

PUBLISHED = ("telemetry", "status", "events", "runs")  # what the rig alone publishes
MARK = "observer-was-here"
OBSERVER_FORCE_N = 999.0  # a valid force_ref: refused for who sent it, not for its form
OPERATOR_FORCE_N = 321.0
FAKE_ZID = "1f2e3d4c5b6a79881f2e3d4c5b6a7988"  # a session id of no session


def _fakes(rig: str) -> tuple[str, str]:
    """The liveliness tokens the observer declares: one as a daemon's, one plainly its own."""
    return alive_token(rig, FAKE_ZID), f"mrrig/{rig}/alive/observer"


def _drain(sub: Any) -> list[zenoh.Sample]:
    out = []
    while (sample := sub.try_recv()) is not None:
        out.append(sample)
    return out


def _until(loop: LoopEnd, kind: Msg, timeout_s: float) -> list[tuple[Msg, Any]]:
    """The loop's messages until one of `kind` came (or the time is up)."""
    got: list[tuple[Msg, Any]] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not any(m == kind for m, _ in got):
        got += loop.poll()
        time.sleep(0.02)
    return got


def _misuse(observer: zenoh.Session, rig: str) -> tuple[list[Any], list[str]]:
    """Every message kind an observer might try on every key of the rig: its liveliness
    tokens, queryables and subscribers (to undeclare later) and the names its queryables
    were asked on."""
    k = keys(rig)
    asked: list[str] = []

    def serve(query: zenoh.Query, name: str) -> None:
        asked.append(name)
        query.reply(query.key_expr, MARK)
        query.drop()

    entities: list[Any] = [
        *(observer.liveliness().declare_token(token) for token in _fakes(rig)),
        *(
            observer.declare_queryable(k[name], lambda q, name=name: serve(q, name))
            for name in ("status", "control")
        ),
    ]
    time.sleep(0.5)
    for name in (*PUBLISHED, "control"):
        observer.put(k[name], MARK)
        observer.delete(k[name])
    observer.put(k["force_ref"], json.dumps({"force_n": OBSERVER_FORCE_N}))
    observer.delete(k["force_ref"])
    return entities, asked


def _breaches(
    rig: str,
    heard: dict[str, list[zenoh.Sample]],
    tokens: list[str],
    loop_msgs: list[tuple[Msg, Any]],
    asked: list[str],
    status_replies: list[bytes],
    observer_control: list[Any],
    eavesdropped: list[zenoh.Sample],
) -> list[str]:
    """What of the observer's misuse reached anyone, one line each."""
    out = []
    for samples in heard.values():
        for s in samples:
            if s.kind == zenoh.SampleKind.DELETE or s.payload.to_bytes() == MARK.encode():
                kind = "delete" if s.kind == zenoh.SampleKind.DELETE else "put"
                out.append(f"the observer's {kind} on {s.key_expr} was heard")
    out += [f"the observer's token {t} was seen" for t in tokens if t in _fakes(rig)]
    for m, payload in loop_msgs:
        if m == Msg.NOTICE and payload.get("kind") == "duplicate_rig":
            out.append(f"the rig was faulted: {payload['reason']}")
        if m == Msg.FORCE_REF and payload[0] == OBSERVER_FORCE_N:
            out.append("the observer's force_ref reached the loop")
        if m == Msg.REQUEST and json.loads(payload[1])["cmd"] == "disarm":
            out.append("the observer's control query reached the loop")
    out += [f"the observer's queryable on {name} was asked" for name in asked]
    out += ["the observer answered a status query" for r in status_replies if MARK.encode() in r]
    out += ["the observer's control query was answered" for _ in observer_control]
    out += [f"the observer heard {s.key_expr}" for s in eavesdropped]
    return out


# the rig's Zenoh config and the clients' suffix, by topology
TOPOLOGIES = {
    "rig": ("rig.json5", ""),
    "router": ("rig-fleet.json5", ""),
    "usrpwd": ("rig-usrpwd.json5", "-usrpwd"),
}


@pytest.mark.parametrize("topology", sorted(TOPOLOGIES))
def test_an_observer_cannot_act_on_the_rig(tmp_path: Path, topology: str):
    """On the rig's own listener (configs/zenoh/rig.json5; rig-usrpwd.json5 with user names
    instead of certificates) and through a lab's router (router.json5, the rig on
    rig-fleet.json5): the observer's put and delete on every key,
    liveliness tokens of the rig's name, queryables on status and control, subscribers on
    force_ref and control and its control query reach no one; what it may do (subscribe to
    telemetry, status and events, get status, query the liveliness tokens) works, and so do the
    operator's control query and force_ref."""
    rig = "acl"
    k = keys(rig)
    d = _lab(tmp_path)
    certs.issue(d, "router", "router")
    port = find_free_port()
    router = _open(_template("router.json5", tmp_path, port)) if topology == "router" else None
    rig_file, suffix = TOPOLOGIES[topology]
    rig_conf = _template(rig_file, tmp_path, port)
    (d / "users.txt").write_text("observer:change-me\noperator:change-me\n")  # the templates'
    fds = make_channel(pipe_bytes=None)
    loop = LoopEnd(fds.loop_rx, fds.loop_tx)
    proc = start_sidecar(rig, rig_conf, fds)
    sessions: list[zenoh.Session] = []
    try:
        ready = [p for m, p in _until(loop, Msg.READY, 30.0) if m == Msg.READY]
        assert ready and not ready[0].get("error"), ready
        loop.send_status({"state": "IDLE", "armed": False})
        # two observers: one misbehaves, the other reads (a session's own subscribers and
        # queryables hear it inside the session, where no access control is)
        observer = _open(_template(f"observer{suffix}.json5", tmp_path, port))
        sessions.append(observer)
        reader = _open(_template(f"observer{suffix}.json5", tmp_path, port))
        sessions.append(reader)
        operator = _open(_template(f"operator{suffix}.json5", tmp_path, port))
        sessions.append(operator)
        # the others' view: the operator's subscribers on all the rig publishes, its tokens
        witness = {name: operator.declare_subscriber(k[name]) for name in PUBLISHED}
        tokens = operator.liveliness().declare_subscriber(k["alive"], history=True)
        # what the observer may do: subscribe
        reads = {name: reader.declare_subscriber(k[name]) for name in PUBLISHED}
        eavesdrop = [reader.declare_subscriber(k[name]) for name in ("force_ref", "control")]
        time.sleep(1.0)  # declarations settled: a put now reaches every subscriber it may

        entities, asked = _misuse(observer, rig)
        request = '{"cmd": "disarm"}'
        observer_control = [r.ok for r in reader.get(k["control"], payload=request, timeout=1.0)]
        observer_control = [r for r in observer_control if r is not None]
        # the rig publishes: telemetry, a state change, an event
        loop.send_samples(np.zeros(5, dtype=SAMPLE_DTYPE))
        loop.send_status({"state": "ARMED", "armed": True})
        loop.send_event({"t": 0.0, "level": "info", "text": "armed", "kind": "state"})
        # the operator drives: a force_ref, a control query (the test plays the loop and does
        # not answer it: the sidecar answers that the daemon did not)
        time.sleep(0.5)
        operator.put(k["force_ref"], json.dumps({"force_n": OPERATOR_FORCE_N}))
        operator_control = [
            r.ok.payload.to_bytes()
            for r in operator.get(
                k["control"],
                payload='{"cmd": "arm"}',
                target=zenoh.QueryTarget.ALL,
                timeout=3.0,
            )
            if r.ok
        ]
        status_replies = [
            r.ok.payload.to_bytes()
            for r in operator.get(k["status"], target=zenoh.QueryTarget.ALL, timeout=2.0)
            if r.ok
        ]
        observer_status = _status(reader, rig)
        observer_alive = [
            str(r.ok.key_expr) for r in reader.liveliness().get(k["alive"], timeout=2.0) if r.ok
        ]
        time.sleep(1.0)  # whatever is on its way has arrived
        loop_msgs = loop.poll()
        heard = {name: _drain(sub) for name, sub in witness.items()}
        seen = [str(s.key_expr) for s in _drain(tokens) if s.kind == zenoh.SampleKind.PUT]
        eavesdropped = [s for sub in eavesdrop for s in _drain(sub)]
        read = {name: _drain(sub) for name, sub in reads.items()}

        breaches = _breaches(
            rig, heard, seen, loop_msgs, asked, status_replies, observer_control, eavesdropped
        )
        assert breaches == [], "\n".join(breaches)

        # what is allowed works
        assert len(observer_alive) == 1 and seen == observer_alive, (observer_alive, seen)
        assert observer_status is not None and observer_status["state"] in ("IDLE", "ARMED")
        for name in ("telemetry", "status", "events"):
            assert read[name], f"the observer got no {name}"
            assert heard[name], f"the operator got no {name}"
        force = [p[0] for m, p in loop_msgs if m == Msg.FORCE_REF]
        assert force == [OPERATOR_FORCE_N], loop_msgs
        requests = [json.loads(p[1]) for m, p in loop_msgs if m == Msg.REQUEST]
        assert requests == [{"cmd": "arm"}], loop_msgs
        assert operator_control and b"daemon did not answer" in operator_control[0]
        for e in (*entities, *witness.values(), tokens, *reads.values(), *eavesdrop):
            e.undeclare()
    finally:
        for s in sessions:
            s.close()
        loop.send_stop()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        loop.close()
        if router is not None:
            router.close()


def test_a_token_no_daemon_answers_for_does_not_fault_the_rig(tmp_path: Path):
    """Where a session may declare tokens (loopback, no access control): a token of the rig's
    name whose session does not serve the rig's status is logged, not a `duplicate_rig`
    fault; once that session answers the status (a second daemon, as it starts), it is."""
    rig = "attr"
    port = find_free_port()
    conf = tmp_path / "z.json5"
    conf.write_text(
        f'{{mode: "peer", listen: {{endpoints: ["tcp/127.0.0.1:{port}"]}}, '
        "scouting: {multicast: {enabled: false}}}"
    )
    fds = make_channel(pipe_bytes=None)
    loop = LoopEnd(fds.loop_rx, fds.loop_tx)
    proc = start_sidecar(rig, conf, fds)
    other = None
    try:
        ready = [p for m, p in _until(loop, Msg.READY, 30.0) if m == Msg.READY]
        assert ready and not ready[0].get("error"), ready
        loop.send_status({"state": "ARMED", "armed": True})
        other = _open(
            zenoh.Config.from_json5(
                f'{{mode: "client", connect: {{endpoints: ["tcp/127.0.0.1:{port}"]}}, '
                "scouting: {multicast: {enabled: false}}}"
            )
        )
        token = other.liveliness().declare_token(alive_token(rig, str(other.zid())))
        msgs = _until(loop, Msg.NOTICE, 3.0)  # three rounds of asking
        assert [p for m, p in msgs if m == Msg.NOTICE] == []
        status = other.declare_queryable(
            keys(rig)["status"],
            lambda q: (q.reply(keys(rig)["status"], '{"state": "IDLE"}'), q.drop()),
        )
        notices = [p for m, p in _until(loop, Msg.NOTICE, 5.0) if m == Msg.NOTICE]
        assert [n["kind"] for n in notices] == ["duplicate_rig"], notices
        assert alive_token(rig, str(other.zid())) in notices[0]["reason"]
        status.undeclare()
        token.undeclare()
    finally:
        if other is not None:
            other.close()
        loop.send_stop()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        loop.close()
