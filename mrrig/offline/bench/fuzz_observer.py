"""Observer misuse, a part of `mrrig bench fuzz`: an observer's certificate against the rig's
sidecar on the shipped access control (configs/zenoh/rig.json5, mutual TLS, a lab CA made for
the run), on 127.0.0.1.

The real sidecar runs as a process; the bench plays its loop (status and events every
0.1 s). For the part's length an observer session does, at random: put or delete on every key
of the rig and beside them (`mrrig/<rig>/...`, with payloads that would be taken, such as
valid force references), declare liveliness tokens of the rig's name, and control queries; a
second observer session declares queryables on the rig's `status` and `control`. An operator
session watches all the rig publishes and its tokens, gets the status (every queryable) and
puts a force reference every second.

Counted as reached: an observer's put or delete that an operator's subscriber heard, a token
of the observer's the operator saw, a `duplicate_rig` fault, a force reference or control
request of the observer's at the loop, an observer's queryable asked, a control query of the
observer's answered. It must be 0; and the operator's force references and samples must
arrive (else the part saw nothing, and says so).
"""

from __future__ import annotations

import json
import logging
import random
import subprocess
import time
from collections import Counter
from pathlib import Path
from typing import Any

import zenoh

from mrrig.resources import shipped_dir
from mrrig.rigio import certs
from mrrig.rigio.canbus.bus import find_free_port
from mrrig.rigio.ipc import LoopEnd, Msg, make_channel
from mrrig.rigio.rig_topics import alive_token, keys
from mrrig.rigio.sidecar_process import start_sidecar
from mrrig.rigio.zenoh_config import load_zenoh_config

log = logging.getLogger(__name__)

RIG = "fuzz-acl"
PUBLISHED = ("telemetry", "status", "events", "runs")
MARK = "observer:"  # every payload of the observer's starts so
OBSERVER_FORCE_N = 1.0e6  # the observer's force references: 1e6 + n, the operator's below
OPERATOR_FORCE_N = 100.0
ACTIONS = ("put", "delete", "force_ref", "token", "queryable", "query")
PART_S = 30.0  # the part's length at most; else a tenth of the campaign
MAX_ENTITIES = 200  # the observer's tokens and queryables, at most
OPEN_TIMEOUT_S = 30.0


def _template(name: str, work: Path, port: int) -> Path:
    """A shipped Zenoh template with the run's certificate folder and port."""
    text = (shipped_dir() / "zenoh" / name).read_text()
    text = text.replace('"certs/', f'"{work}/certs/').replace(":7447", f":{port}")
    path = work / name
    path.write_text(text)
    return path


def _open(path: Path) -> zenoh.Session:
    conf = load_zenoh_config(path)
    deadline = time.monotonic() + OPEN_TIMEOUT_S
    while True:
        try:
            return zenoh.open(conf)
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise RuntimeError(f"{path}: no session with the rig's sidecar") from None
            time.sleep(0.3)


class _Witness:
    """The operator's view: every sample on what the rig publishes, the tokens it sees."""

    def __init__(self, operator: zenoh.Session) -> None:
        k = keys(RIG)
        self.reached: Counter[str] = Counter()
        self.heard = 0
        self._subs = [operator.declare_subscriber(k[n], self._on_sample) for n in PUBLISHED]
        self._alive = operator.liveliness().declare_subscriber(
            k["alive"], self._on_token, history=True
        )
        self.tokens: set[str] = set()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.heard += 1
        if sample.kind == zenoh.SampleKind.DELETE:
            self.reached["delete heard"] += 1
        elif sample.payload.to_bytes().startswith(MARK.encode()):
            self.reached["put heard"] += 1

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self.tokens.add(str(sample.key_expr))

    def close(self) -> None:
        for e in (*self._subs, self._alive):
            e.undeclare()


def _key(rng: random.Random) -> str:
    """A key of the rig's, or one beside them."""
    names = (*PUBLISHED, "control", "force_ref", "alive/x", "anything/else")
    return f"mrrig/{RIG}/{rng.choice(names)}"


def run(work: Path, rng: random.Random, minutes: float) -> dict[str, Any]:
    """The part's counts, for a tenth of a campaign of `minutes` (PART_S at most): actions
    by kind, `observer_reached` by what reached (must be empty), `operator_force_refs` and
    `operator_samples_heard` (must not be 0)."""
    seconds = min(PART_S, minutes * 6.0)
    d = work / "certs"
    certs.init_ca(d)
    for role in ("rig", "observer", "operator"):
        certs.issue(d, role, role)
    port = find_free_port()
    fds = make_channel(pipe_bytes=None)
    loop = LoopEnd(fds.loop_rx, fds.loop_tx)
    proc = start_sidecar(RIG, _template("rig.json5", work, port), fds)
    sessions: list[zenoh.Session] = []
    entities: list[Any] = []
    actions: Counter[str] = Counter()
    asked: list[str] = []
    loop_msgs: list[tuple[Msg, Any]] = []
    try:
        observer = _open(_template("observer.json5", work, port))
        sessions.append(observer)
        # its queryables in a session of their own: a session's own queries reach its own
        # queryables inside it, where no access control is
        impostor = _open(_template("observer.json5", work, port))
        sessions.append(impostor)
        operator = _open(_template("operator.json5", work, port))
        sessions.append(operator)
        witness = _Witness(operator)
        own_tokens: set[str] = set()
        k = keys(RIG)
        n = 0
        t_end = time.monotonic() + seconds
        next_tick = next_second = 0.0
        while time.monotonic() < t_end:
            now = time.monotonic()
            if now >= next_tick:  # the rig's side, and the operator's
                next_tick = now + 0.1
                loop.send_status({"state": "ARMED", "armed": True})
                loop.send_event({"t": now, "level": "info", "text": "tick", "kind": "tick"})
                if now >= next_second:
                    next_second = now + 1.0
                    operator.put(k["force_ref"], json.dumps({"force_n": OPERATOR_FORCE_N}))
                    for r in operator.get(k["status"], target=zenoh.QueryTarget.ALL, timeout=0.5):
                        if r.ok is not None and r.ok.payload.to_bytes().startswith(MARK.encode()):
                            witness.reached["status answered by the observer"] += 1
            n += 1
            action = rng.choice(ACTIONS)
            actions[action] += 1
            if action == "put":
                observer.put(_key(rng), f"{MARK}{n}")
            elif action == "delete":
                observer.delete(_key(rng))
            elif action == "force_ref":
                observer.put(k["force_ref"], json.dumps({"force_n": OBSERVER_FORCE_N + n}))
            elif action == "token" and len(entities) < MAX_ENTITIES:
                token = alive_token(RIG, f"{n:032x}") if rng.random() < 0.5 else _key(rng)
                own_tokens.add(token)
                entities.append(observer.liveliness().declare_token(token))
            elif action == "queryable" and len(entities) < MAX_ENTITIES:
                name = rng.choice(("status", "control"))

                def serve(q: zenoh.Query, name: str = name) -> None:
                    asked.append(name)
                    q.reply(q.key_expr, f"{MARK}{name}")
                    q.drop()

                entities.append(impostor.declare_queryable(k[name], serve))
            elif action == "query":
                request = rng.choice(('{"cmd": "arm"}', '{"cmd": "disarm"}', "{}"))
                for r in observer.get(k["control"], payload=request, timeout=0.2):
                    if r.ok is not None and not r.ok.payload.to_bytes().startswith(MARK.encode()):
                        witness.reached["control answered to the observer"] += 1
            loop_msgs += loop.poll()
            time.sleep(rng.uniform(0.0, 0.02))
        time.sleep(1.0)  # what is on its way arrives
        loop_msgs += loop.poll()
        reached = Counter(witness.reached)
        reached["token seen"] += len(witness.tokens & own_tokens)
        reached["queryable asked"] += len(asked)
        operator_refs = 0
        for m, payload in loop_msgs:
            if m == Msg.NOTICE and payload.get("kind") == "duplicate_rig":
                reached["duplicate_rig fault"] += 1
            elif m == Msg.FORCE_REF and payload[0] >= OBSERVER_FORCE_N:
                reached["force_ref at the loop"] += 1
            elif m == Msg.FORCE_REF:
                operator_refs += 1
            elif m == Msg.REQUEST:
                reached["control request at the loop"] += 1
        witness.close()
        return {
            "observer_actions": sum(actions.values()),
            "observer_actions_by_kind": dict(actions),
            "observer_reached": {key: v for key, v in reached.items() if v},
            "operator_force_refs": operator_refs,
            "operator_samples_heard": witness.heard,
        }
    finally:
        for e in entities:
            e.undeclare()
        for s in sessions:
            s.close()
        loop.send_stop()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        loop.close()


def failures(part: dict[str, Any]) -> list[str]:
    """What of the part is not as it must be, by name."""
    out = [f"observer_reached {key}" for key in part["observer_reached"]]
    if part["operator_force_refs"] == 0 or part["operator_samples_heard"] == 0:
        out.append("operator_force_refs or operator_samples_heard 0: the part saw nothing")
    return out


def report(part: dict[str, Any]) -> str:
    return (
        f"  observer misuse (mTLS, shipped ACL): {part['observer_actions']} actions "
        f"{part['observer_actions_by_kind']}, reached the rig or the others: "
        f"{sum(part['observer_reached'].values())} {part['observer_reached']}; the operator's "
        f"force references at the loop {part['operator_force_refs']}"
    )
