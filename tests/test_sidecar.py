"""The sidecar as a real process with real Zenoh sessions on 127.0.0.1 (a port per test); the
test plays the control loop on the other end of the pipes."""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from mrrig.loop.samples import FIELDS, SAMPLE_DTYPE, RigState
from mrrig.offline.review import read_recording, verify_rrd
from mrrig.rigio import client, force_stream
from mrrig.rigio.canbus.bus import find_free_port
from mrrig.rigio.ipc import LoopEnd, Msg, SidecarEnd, make_channel
from mrrig.rigio.recording import Recorder
from mrrig.rigio.rig_topics import JSON, keys
from mrrig.rigio.sidecar import Sidecar
from mrrig.rigio.sidecar_process import start_sidecar
from mrrig.rigio.zenoh_config import INSECURE_WARNING, load_zenoh_config, local_config
from tests.conftest import wait_until, zenoh_configs

pytestmark = pytest.mark.process

RIG = "testrig"
CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _collect(sub: zenoh.Subscriber, n: int, timeout_s: float = 10.0) -> list[Any]:
    """The JSON payloads of the first `n` samples on `sub` (fewer on timeout)."""
    got: list[Any] = []

    def more() -> bool:
        while (sample := sub.try_recv()) is not None:
            got.append(json.loads(sample.payload.to_bytes()))
        return len(got) >= n

    wait_until(more, timeout_s)
    return got


@dataclass
class Rig:
    proc: subprocess.Popen[bytes]
    loop: LoopEnd
    observer: zenoh.Session
    client_config: zenoh.Config

    def alive_tokens(self) -> list[str]:
        replies = self.observer.liveliness().get(keys(RIG)["alive"], timeout=1.0)
        return [str(r.ok.key_expr) for r in replies if r.ok is not None]

    def poll_until(self, mtype: Msg, timeout_s: float = 5.0) -> Any:
        def got() -> Any:
            return next((p for m, p in self.loop.poll() if m == mtype), None)

        return wait_until(got, timeout_s)


@contextlib.contextmanager
def running_sidecar(tmp_path: Path, record: Path | None = None) -> Iterator[Rig]:
    """A sidecar process on its own port, an observer session, and the loop's pipe end."""
    conf_path, _, port = zenoh_configs(tmp_path)
    fds = make_channel()
    loop = LoopEnd(fds.loop_rx, fds.loop_tx)
    proc = start_sidecar(RIG, conf_path, fds, record=record, telemetry_hz=50)
    assert loop.wait_ready(30.0) is None  # as the daemon waits before its loop starts
    client_config = local_config("client", connect=[f"tcp/127.0.0.1:{port}"])
    # the sidecar may still be opening its listener: retry until it accepts
    observer = wait_until(
        lambda: _try_open(local_config("client", connect=[f"tcp/127.0.0.1:{port}"]))
    )
    r = Rig(proc, loop, observer, client_config)
    try:
        assert observer, "could not connect to the sidecar"
        assert wait_until(r.alive_tokens), "sidecar never declared its liveliness token"
        yield r
    finally:
        r.loop.send_stop()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if observer:
            observer.close()
        r.loop.close()


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    with running_sidecar(tmp_path) as r:
        yield r


def _try_open(conf: zenoh.Config) -> zenoh.Session | None:
    try:
        return zenoh.open(conf)
    except zenoh.ZError:
        return None


def _samples(n: int) -> np.ndarray:
    rng = np.random.default_rng(1)
    arr = np.zeros(n, SAMPLE_DTYPE)
    for name in FIELDS:
        arr[name] = rng.normal(size=n) * 1e3 if SAMPLE_DTYPE[name].kind == "f" else 0
    arr["t"] = np.arange(n) * 0.002
    arr["counter"] = np.arange(n) % 16
    arr["state"] = RigState.ARMED
    return arr


def test_samples_arrive_as_json_telemetry_with_equal_values(rig: Rig):
    sub = rig.observer.declare_subscriber(keys(RIG)["telemetry"])
    time.sleep(0.2)  # let the subscription reach the sidecar
    arr = _samples(200)
    for start in range(0, arr.size, 25):  # 50 ms batches, as the loop sends them
        assert rig.loop.send_samples(arr[start : start + 25])
    got: dict[str, list[Any]] = {name: [] for name in FIELDS}
    encodings = set()

    def collect() -> bool:
        sample = sub.try_recv()
        if sample is not None:
            encodings.add(str(sample.encoding))
            msg = json.loads(sample.payload.to_bytes())
            assert msg["rig"] == RIG
            for name in FIELDS:
                got[name] += msg["fields"][name]
        return len(got["t"]) >= arr.size

    assert wait_until(collect, step_s=0.001)
    sub.undeclare()
    assert encodings == {"application/json"}
    for name in FIELDS:
        assert np.array_equal(np.array(got[name], dtype=SAMPLE_DTYPE[name]), arr[name]), name


def test_non_finite_telemetry_values_are_sent_as_null(rig: Rig):
    sub = rig.observer.declare_subscriber(keys(RIG)["telemetry"])
    time.sleep(0.2)
    arr = _samples(3)
    arr["f_model"] = [1.5, math.nan, math.inf]
    rig.loop.send_samples(arr)
    sample = wait_until(sub.try_recv)
    sub.undeclare()
    assert json.loads(sample.payload.to_bytes())["fields"]["f_model"] == [1.5, None, None]


def _answer_one_request(loop: LoopEnd, seen: list[dict[str, Any]]) -> None:
    def answer() -> bool:
        for mtype, payload in loop.poll():
            if mtype == Msg.REQUEST:
                request_id, raw = payload
                seen.append({**json.loads(raw), "id": request_id})
                replies = loop.reply_writer()
                replies.send_reply({"id": request_id, "ok": True, "state": "ARMED"})
                replies.close()
                return True
        return False

    wait_until(answer, timeout_s=5.0, step_s=0.002)


def test_control_query_is_forwarded_as_request_and_the_loops_reply_returned(rig: Rig):
    seen: list[dict[str, Any]] = []
    player = threading.Thread(target=_answer_one_request, args=(rig.loop, seen))
    player.start()
    reply = client.arm(RIG, rig.client_config)
    player.join()
    assert reply == {"ok": True, "state": "ARMED"}
    assert seen[0]["cmd"] == "arm" and isinstance(seen[0]["id"], int)


@pytest.mark.parametrize("payload", ["{not json", "[1, 2]", '"arm"', b"\xff\xfe"])
def test_malformed_control_request_gets_an_error_reply_without_reaching_the_loop(rig: Rig, payload):
    replies = list(rig.observer.get(keys(RIG)["control"], payload=payload, timeout=2.0))
    assert len(replies) == 1 and replies[0].ok is not None
    reply = json.loads(replies[0].ok.payload.to_bytes())
    assert reply["ok"] is False and reply["error"]
    time.sleep(0.1)
    assert [m for m, _ in rig.loop.poll() if m != Msg.HEARTBEAT] == []


def test_every_control_request_is_an_audit_event_with_its_requester(rig: Rig):
    events = rig.observer.declare_subscriber(keys(RIG)["events"])
    time.sleep(0.2)
    player = threading.Thread(target=_answer_one_request, args=(rig.loop, []))
    player.start()
    client.arm(RIG, rig.client_config)
    player.join()
    rig.observer.get(keys(RIG)["control"], payload="{not json", timeout=2.0).recv()
    got = [e for e in _collect(events, 2) if e["kind"] == "audit"]
    events.undeclare()
    accepted, refused = got
    assert accepted["request"] == {"cmd": "arm"} and accepted["result"]["ok"] is True
    assert accepted["level"] == "info" and "control arm from" in accepted["text"]
    claimed = accepted["requester"]["claimed"]
    assert set(claimed) >= {"zid", "user", "host"}
    assert refused["request"] == {"raw": "{not json"} and refused["result"]["ok"] is False
    assert refused["level"] == "warning" and "refused: invalid request" in refused["text"]
    assert "claimed" not in refused["requester"]  # a bare get() says nothing about itself


def test_forged_claims_make_one_printable_bounded_audit_line(rig: Rig):
    """Issue 40, finding 14: a newline in a claimed host forged a second audit line, ANSI
    escapes reached the terminal, a 3 MB host went into the event; over real Zenoh."""
    events = rig.observer.declare_subscriber(keys(RIG)["events"])
    time.sleep(0.2)
    forged = {"zid": "0", "user": "eve\x1b[2J", "host": "pc\nINFO audit: control arm from root"}
    client.query(rig.observer, RIG, {"cmd": "mark", "text": "m"}, claims=forged)
    client.query(rig.observer, RIG, {"cmd": "mark", "text": "m"}, claims={"host": "h" * 3_000_000})
    got = [e for e in _collect(events, 4) if e["kind"] == "audit"]
    events.undeclare()
    assert len(got) == 2
    for e in got:
        assert "\n" not in e["text"] and "\x1b" not in e["text"] and len(e["text"]) < 1000
    assert "eve\\x1b[2J" in got[0]["text"] and "pc\\x0aINFO" in got[0]["text"]
    host = got[1]["requester"]["claimed"]["host"]
    assert host.startswith("hhh") and host.endswith("more characters]") and len(host) < 400


def test_the_audit_is_in_the_recording(tmp_path: Path):
    path = tmp_path / "run.rrd"
    with running_sidecar(tmp_path, record=path) as r:
        player = threading.Thread(target=_answer_one_request, args=(r.loop, []))
        player.start()
        client.arm(RIG, r.client_config)
        player.join()
    audits = [e for e in read_recording(path).events if e["kind"] == "audit"]
    assert len(audits) == 1
    assert audits[0]["request"] == {"cmd": "arm"} and audits[0]["result"]["ok"] is True
    assert audits[0]["requester"]["claimed"]["zid"]


def test_status_is_answered_to_a_query_once_there_is_one(rig: Rig):
    def status() -> list[Any]:
        replies = rig.observer.get(keys(RIG)["status"], timeout=1.0)
        return [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]

    assert status() == []
    rig.loop.send_status({"state": "IDLE", "controller": "constant"})
    assert wait_until(status) == [{"state": "IDLE", "controller": "constant"}]


def test_an_insecure_sidecar_warns_in_every_status_and_the_recording(tmp_path: Path):
    """The warnings `check_secure(..., insecure=True)` returns (an insecure config off
    loopback, which a test does not open) on a sidecar that listens on 127.0.0.1."""
    _, _, port = zenoh_configs(tmp_path)
    warning = f"{INSECURE_WARNING} (z.json5: 'tcp/0.0.0.0:7447')"
    path = tmp_path / "run.rrd"
    fds = make_channel(pipe_bytes=None)
    loop = LoopEnd(fds.loop_rx, fds.loop_tx)
    end = SidecarEnd(fds.sidecar_rx, fds.sidecar_tx)
    session = zenoh.open(local_config("peer", listen=[f"tcp/127.0.0.1:{port}"]))
    observer = zenoh.open(local_config("client", connect=[f"tcp/127.0.0.1:{port}"]))
    sidecar = Sidecar(RIG, session, end, Recorder(path, RIG), 50.0, [warning])
    thread = threading.Thread(target=sidecar.run)
    try:
        sub = observer.declare_subscriber(keys(RIG)["status"])
        thread.start()
        time.sleep(0.3)
        loop.send_status({"state": "IDLE"})
        published = json.loads(wait_until(sub.try_recv).payload.to_bytes())
        assert published.pop("recording")["path"] == str(path)  # what this process writes
        assert published == {"state": "IDLE", "security_warning": [warning]}
        sub.undeclare()
        player = threading.Thread(
            target=lambda: wait_until(
                lambda: [
                    loop.send_reply({"id": p["id"], "ok": True, "status": {"state": "IDLE"}})
                    for m, p in loop.poll()
                    if m == Msg.REQUEST
                ],
                timeout_s=5.0,
            )
        )
        player.start()
        reply = client.query(observer, RIG, {"cmd": "status"}, timeout_s=3.0)
        player.join()
        assert reply["status"]["security_warning"] == [warning]
    finally:
        loop.send_stop()
        thread.join(10)
        observer.close()
        session.close()
        loop.close()
        end.close()
    events = read_recording(path).events
    assert any(e["kind"] == "insecure" and e["text"] == warning for e in events), events


def test_unanswered_request_gets_daemon_did_not_answer(rig: Rig):
    reply = client.status(RIG, rig.client_config, timeout_s=3.0)
    assert reply == {"ok": False, "error": "daemon did not answer"}
    # no status from the loop lately: the request went on to it
    assert json.loads(rig.poll_until(Msg.REQUEST)[1])["cmd"] == "status"


def test_force_ref_is_forwarded_with_its_receive_time(rig: Rig):
    t_before = time.monotonic()
    rig.observer.put(keys(RIG)["force_ref"], "123.5")
    assert rig.poll_until(Msg.FORCE_REF)[0] == 123.5
    rig.observer.put(keys(RIG)["force_ref"], json.dumps({"force_n": -7.25}))
    force_n, t_rx_s = rig.poll_until(Msg.FORCE_REF)
    assert force_n == -7.25
    # the sidecar's time.monotonic() is the same clock as ours (CLOCK_MONOTONIC)
    assert t_before <= t_rx_s <= time.monotonic()


def test_malformed_force_ref_is_an_event_and_not_forwarded(rig: Rig):
    events = rig.observer.declare_subscriber(keys(RIG)["events"])
    time.sleep(0.2)
    for bad in ["abc", '{"x": 1}', "true", "NaN"]:
        rig.observer.put(keys(RIG)["force_ref"], bad)
    got = _collect(events, 4)
    events.undeclare()
    assert [e["kind"] for e in got] == ["force_ref_malformed"] * 4
    assert [m for m, _ in rig.loop.poll() if m != Msg.HEARTBEAT] == []


def test_events_are_published_one_message_each(rig: Rig):
    sub = rig.observer.declare_subscriber(keys(RIG)["events"])
    time.sleep(0.2)
    sent = [
        {"t": 1.0, "level": "error", "text": "bad CRC", "kind": "fault"},
        {"t": 1.5, "level": "info", "text": "re-armed", "kind": "state"},
    ]
    for event in sent:
        rig.loop.send_event(event)
    got = _collect(sub, 2)
    sub.undeclare()
    assert got == sent


def test_status_is_published_on_change_and_repeated_every_second(rig: Rig):
    sub = rig.observer.declare_subscriber(keys(RIG)["status"])
    time.sleep(0.2)
    status = {"state": "IDLE", "armed": False}
    rig.loop.send_status(status)
    rig.loop.send_status(status)  # unchanged: not published again at once
    first = wait_until(sub.try_recv)
    t_first = time.monotonic()
    assert json.loads(first.payload.to_bytes()) == status
    repeat = wait_until(sub.try_recv, timeout_s=3.0)
    sub.undeclare()
    assert json.loads(repeat.payload.to_bytes()) == status
    assert time.monotonic() - t_first > 0.5  # the repeat, not the duplicate


def test_liveliness_token_is_gone_after_stop(rig: Rig):
    [token] = rig.alive_tokens()  # one, with the session's id: mrrig/<rig>/alive/<id>
    assert token.startswith(f"mrrig/{RIG}/alive/")
    rig.loop.send_stop()
    assert rig.proc.wait(timeout=10) == 0
    assert wait_until(lambda: not rig.alive_tokens(), timeout_s=5.0)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signal_stops_the_sidecar_with_exit_0(rig: Rig, signum):
    rig.proc.send_signal(signum)
    assert rig.proc.wait(timeout=10) == 0


def test_eof_of_the_loop_pipe_stops_the_sidecar(rig: Rig):
    rig.loop.close()
    assert rig.proc.wait(timeout=10) == 0
    dummy = make_channel(pipe_bytes=None)  # for the fixture's teardown
    os.close(dummy.sidecar_rx)
    os.close(dummy.sidecar_tx)
    rig.loop = LoopEnd(dummy.loop_rx, dummy.loop_tx)


def test_watch_prints_live_numbers(rig: Rig):
    out = io.StringIO()
    arr = _samples(500)

    def feed() -> None:
        for start in range(0, arr.size, 25):
            rig.loop.send_samples(arr[start : start + 25])
            time.sleep(0.05)

    feeder = threading.Thread(target=feed)
    feeder.start()
    n = client.watch(RIG, rig.client_config, duration_s=1.3, out=out)
    feeder.join()
    assert n > 0
    line = out.getvalue().splitlines()[0]
    assert "f_des" in line and "latency p99" in line and "state ARMED" in line


def test_streamed_csv_profile_reaches_the_loop_in_order(rig: Rig, tmp_path: Path):
    csv = tmp_path / "profile.csv"
    csv.write_text("t_s,force_n\n0,0\n0.1,100\n")
    fn, length_s = force_stream.csv_profile(csv)
    with client.open_session(rig.client_config) as session:
        pub = session.declare_publisher(keys(RIG)["force_ref"], encoding=JSON)
        n = round(length_s * 50) + 1
        sent = force_stream.stream(pub, lambda k: fn(k / 50) if k < n else None, 50.0)
        pub.undeclare()
    forces = []
    wait_until(
        lambda: (
            forces.extend(p[0] for m, p in rig.loop.poll() if m == Msg.FORCE_REF)
            or len(forces) >= sent
        ),
        timeout_s=5.0,
    )
    assert sent == 6
    assert forces == pytest.approx([0, 20, 40, 60, 80, 100])


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("t_s,force_n\n0,0\n0.1,abc\n0.2,100\n", r"profile\.csv:3: expected t_s,force_n"),
        ("0,0\n0.1\n0.2,100\n", r"profile\.csv:2: expected t_s,force_n"),
        ("t_s,force_n\n0,0\n0.1,nan\n", r"profile\.csv:3: t_s and force_n must be finite"),
        ("t_s,force_n\n0,0\n", "needs at least two rows"),
        ("t_s,force_n\n0,0\n0,5\n", "strictly increasing"),
    ],
)
def test_a_bad_force_profile_row_is_named_not_skipped(tmp_path: Path, text: str, expected: str):
    csv = tmp_path / "profile.csv"
    csv.write_text(text)
    with pytest.raises(ValueError, match=expected):
        force_stream.load_force_csv(csv)


@pytest.mark.parametrize(
    "text",
    [
        "force_n,t_s\n0,0\n100,0.1\n",  # the header read by name, not by position
        "step,t_s,note,force_n\n1,0,a,0\n2,0.1,b,100\n",  # other columns left alone
        "0,0\n0.1,100\n",  # no header: t_s, force_n
    ],
)
def test_a_force_profile_header_is_read_by_name(tmp_path: Path, text: str):
    csv = tmp_path / "profile.csv"
    csv.write_text(text)
    t_s, force_n = force_stream.load_force_csv(csv)
    assert t_s.tolist() == [0.0, 0.1] and force_n.tolist() == [0.0, 100.0]


def test_a_force_profile_header_without_the_columns_is_an_error(tmp_path: Path):
    csv = tmp_path / "profile.csv"
    csv.write_text("time,force\n0,0\n0.1,100\n")
    with pytest.raises(ValueError, match=r"profile\.csv:1: header 'time,force' has no column"):
        force_stream.load_force_csv(csv)


def test_a_force_profile_may_have_a_header_and_blank_lines(tmp_path: Path):
    csv = tmp_path / "profile.csv"
    csv.write_text("t_s,force_n\n0,0\n\n0.1,100\n")
    t_s, force_n = force_stream.load_force_csv(csv)
    assert t_s.tolist() == [0.0, 0.1] and force_n.tolist() == [0.0, 100.0]


def test_send_force_names_each_fault_by_its_code_then_its_reason():
    # the code is what a script tests (a transport fault is set aside by code, not by the
    # words of its reason); each fault once, however many samples saw it
    latest = force_stream._LatestStatus()
    result = force_stream.SendResult()
    progress = force_stream._Progress(None, 1.0, latest, result)
    timeout = {"state": "FAULT", "fault": "sensor_timeout", "fault_reason": "no sensor frame"}
    for k, status in enumerate([{"state": "ARMED"}, timeout, timeout, {"state": "IDLE"}]):
        latest.status = status
        progress(k * 0.01, 100.0)
    assert result.faults == ["sensor_timeout: no sensor frame"]


def test_request_without_a_daemon_is_a_clear_error(tmp_path: Path):
    port = find_free_port()
    with pytest.raises(client.ClientError, match="daemon"):
        client.request(
            RIG, {"cmd": "status"}, local_config("client", connect=[f"tcp/127.0.0.1:{port}"])
        )
    lonely = local_config("peer", listen=[f"tcp/127.0.0.1:{port}"])
    with pytest.raises(client.ClientError, match="no daemon answered on mrrig/testrig/control"):
        client.request(RIG, {"cmd": "status"}, lonely, timeout_s=0.3)


def test_shipped_zenoh_configs_are_accepted():
    assert json.loads(load_zenoh_config(CONFIGS / "zenoh-daemon.json5").get_json("mode")) == "peer"
    load_zenoh_config(CONFIGS / "zenoh-client.json5")


def test_sidecar_refuses_a_bad_config_with_exit_2(tmp_path: Path):
    path = tmp_path / "z.json5"
    path.write_text('{listen: {endpoints: ["tcp/127.0.0.1:7447"]')  # broken: never opened
    fds = make_channel(pipe_bytes=None)
    loop = LoopEnd(fds.loop_rx, fds.loop_tx)
    try:
        proc = start_sidecar(RIG, path, fds)
        assert proc.wait(timeout=10) == 2
        error = loop.wait_ready(1.0)  # what the daemon stops its start-up with
        assert error is not None and "\n" not in error and str(path) in error
    finally:
        loop.close()


def test_sigterm_still_writes_a_complete_recording(tmp_path: Path):
    path = tmp_path / "run.rrd"
    arr = _samples(300)
    with running_sidecar(tmp_path, record=path) as r:
        r.loop.send_samples(arr)
        r.loop.send_event({"t": 0.1, "level": "error", "text": "bad CRC", "kind": "fault"})
        r.loop.send_summary({"frames": 300})
        time.sleep(0.3)  # let the sidecar take them before the signal
        r.proc.send_signal(signal.SIGTERM)
        assert r.proc.wait(timeout=10) == 0
    verify_rrd(path)  # whole: its end marker written
    rec = read_recording(path)
    assert rec.samples.tobytes() == arr.tobytes()
    assert [(e["level"], e["text"], e["kind"]) for e in rec.events] == [
        ("error", "bad CRC", "fault")
    ]
    assert rec.summary == {"frames": 300}


def test_sidecar_exits_3_when_its_port_is_taken(tmp_path: Path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        path = tmp_path / "z.json5"
        path.write_text(
            f'{{listen: {{endpoints: ["tcp/127.0.0.1:{taken.getsockname()[1]}"]}},'
            " scouting: {multicast: {enabled: false}}}"
        )
        fds = make_channel(pipe_bytes=None)
        loop = LoopEnd(fds.loop_rx, fds.loop_tx)
        try:
            proc = start_sidecar(RIG, path, fds)
            assert proc.wait(timeout=10) == 3
            error = loop.wait_ready(1.0)
            assert "Address already in use" in error and ".rs:" not in error
            assert "\n" not in error
        finally:
            loop.close()


def test_recording_only_sidecar_needs_no_zenoh(tmp_path: Path):
    path = tmp_path / "run.rrd"
    arr = _samples(100)
    fds = make_channel()
    loop = LoopEnd(*fds.loop_fds())
    try:
        proc = start_sidecar(RIG, None, fds, record=path)
        loop.send_samples(arr)
        loop.send_stop()
        assert proc.wait(timeout=20) == 0
    finally:
        loop.close()
    assert read_recording(path).samples.tobytes() == arr.tobytes()


def test_a_disarm_that_waited_past_the_answer_timeout_is_still_passed_on(tmp_path: Path):
    """The sidecar's main thread held up (a loaded machine: three rigs and their plans on two
    CPUs) past the answer timeout while an arm and a disarm wait in its inbox: the arm is
    answered busy, unread, but the disarm reaches the loop (CI: a plan's step aborted on
    `disarm: busy: the control plane is overloaded`)."""
    _, _, port = zenoh_configs(tmp_path)
    fds = make_channel(pipe_bytes=None)
    loop = LoopEnd(fds.loop_rx, fds.loop_tx)
    end = SidecarEnd(fds.sidecar_rx, fds.sidecar_tx)
    session = zenoh.open(local_config("peer", listen=[f"tcp/127.0.0.1:{port}"]))
    observer = zenoh.open(local_config("client", connect=[f"tcp/127.0.0.1:{port}"]))
    sidecar = Sidecar(RIG, session, end, None, 50.0)
    # the queries reach the inbox while the main loop is not serving yet: held up
    early = session.declare_queryable(keys(RIG)["control"], sidecar._on_query)
    thread = threading.Thread(target=sidecar.run)
    try:
        control = keys(RIG)["control"]
        arm = observer.get(control, payload='{"cmd": "arm"}', timeout=5.0)
        disarm = observer.get(control, payload='{"cmd": "disarm"}', timeout=5.0)
        time.sleep(1.5)  # past CONTROL_TIMEOUT_S (1 s) in the inbox
        thread.start()
        requests = wait_until(
            lambda: [json.loads(p[1]) for m, p in loop.poll() if m == Msg.REQUEST], 5.0
        )
        assert requests == [{"cmd": "disarm"}]
        replies = loop.reply_writer()
        replies.send_reply({"id": 1, "ok": True, "state": "IDLE"})
        replies.close()
        assert json.loads(next(iter(arm)).ok.payload.to_bytes()) == {
            "ok": False,
            "error": "busy: the control plane is overloaded",
        }
        assert json.loads(next(iter(disarm)).ok.payload.to_bytes())["ok"] is True
    finally:
        early.undeclare()
        loop.send_stop()
        thread.join(10)
        observer.close()
        session.close()
        loop.close()
