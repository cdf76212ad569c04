"""Secure off loopback: the config rule (unit tests, nothing opened), the lab CA, and real Zenoh
sessions on 127.0.0.1 with mutual TLS or user-password and the shipped access control."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID

from mrrig.rigio import audit, certs, client, fleet
from mrrig.rigio.canbus.bus import find_free_port
from mrrig.rigio.ipc import LoopEnd, Msg, make_channel
from mrrig.rigio.rig_topics import alive_token, keys
from mrrig.rigio.sidecar_process import start_sidecar
from mrrig.rigio.zenoh_config import (
    INSECURE_WARNING,
    TEMPLATE,
    ZenohConfigError,
    check_secure,
    is_loopback,
    load_zenoh_config,
)
from tests.conftest import REPO, rig_config

ZENOH = REPO / "configs" / "zenoh"
SHIPPED = sorted(REPO.glob("configs/**/*.json5"))
SECURE_TEMPLATES = ("rig.json5", "rig-usrpwd.json5", "rig-fleet.json5", "router.json5")


def _conf(text: str) -> zenoh.Config:
    return zenoh.Config.from_json5(text)


def _moved(conf: zenoh.Config, host: str) -> zenoh.Config:
    """The same config with its endpoints on `host` (never opened here)."""
    for key in ("listen/endpoints", "connect/endpoints"):
        value = json.loads(conf.get_json(key))
        if isinstance(value, list) and value:
            conf.insert_json5(key, json.dumps([e.replace("127.0.0.1", host) for e in value]))
    return conf


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: str(p.relative_to(REPO)))
def test_every_shipped_config_keeps_multicast_scouting_off_and_stays_on_loopback(path: Path):
    conf = load_zenoh_config(path)
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    check_secure(conf, str(path))  # on loopback: no refusal, whatever its security


@pytest.mark.parametrize("name", SECURE_TEMPLATES)
def test_secure_templates_are_accepted_off_loopback(name: str):
    conf = _moved(load_zenoh_config(ZENOH / name), "10.1.2.3")
    assert check_secure(conf, name) == []


SCOUT_OFF = "scouting: {multicast: {enabled: false}}"
ACL = 'access_control: {enabled: true, default_permission: "deny"}'
MTLS = 'transport: {link: {tls: {root_ca_certificate: "ca.pem", enable_mtls: true}}}'


@pytest.mark.parametrize(
    ("text", "missing"),
    [
        (f'{{listen: {{endpoints: ["tcp/0.0.0.0:7447"]}}, {SCOUT_OFF}}}', "authentication"),
        (f"{{{SCOUT_OFF}}}", "authentication"),  # Zenoh's default listens on all interfaces
        ('{listen: {endpoints: ["tcp/127.0.0.1:7447"]}}', "authentication"),  # multicast on
        (
            f'{{mode: "client", connect: {{endpoints: ["tcp/rig1.lab:7447"]}}, {SCOUT_OFF}}}',
            "access_control",
        ),
        # TLS without client certificates authenticates only the listener
        (
            f'{{listen: {{endpoints: ["tls/10.0.0.5:7447"]}}, {SCOUT_OFF}, {ACL}, '
            'transport: {link: {tls: {root_ca_certificate: "ca.pem"}}}}',
            "authentication",
        ),
        # mutual TLS but one endpoint in clear
        (
            f'{{listen: {{endpoints: ["tls/10.0.0.5:7447", "tcp/10.0.0.5:7448"]}}, {SCOUT_OFF}, '
            f"{ACL}, {MTLS}}}",
            "authentication",
        ),
        (
            f'{{listen: {{endpoints: ["tls/10.0.0.5:7447"]}}, {SCOUT_OFF}, {MTLS}}}',
            "access_control",
        ),
        (
            f'{{listen: {{endpoints: ["tls/10.0.0.5:7447"]}}, {SCOUT_OFF}, {MTLS}, '
            'access_control: {enabled: true, default_permission: "allow"}}',
            "access_control",
        ),
        # a listener with user-password needs the dictionary to check the others against
        (
            f'{{listen: {{endpoints: ["tcp/10.0.0.5:7447"]}}, {SCOUT_OFF}, {ACL}, '
            'transport: {auth: {usrpwd: {user: "rig", password: "x"}}}}',
            "authentication",
        ),
    ],
)
def test_an_insecure_config_off_loopback_is_refused_with_one_line(text: str, missing: str):
    with pytest.raises(ZenohConfigError) as err:
        check_secure(_conf(text), "z.json5")
    message = str(err.value)
    assert "\n" not in message and message.startswith("z.json5: reaches beyond loopback")
    assert missing in message and TEMPLATE in message and "--insecure" in message
    warnings = check_secure(_conf(text), "z.json5", insecure=True)
    assert len(warnings) == 1 and warnings[0].startswith(INSECURE_WARNING)


def test_clients_accept_any_endpoint_and_mode(tmp_path: Path):
    path = tmp_path / "desk.json5"
    path.write_text(
        '{mode: "client", connect: {endpoints: ["tls/192.168.10.2:7447", "quic/rig1.lab:7447"]}}'
    )
    conf = load_zenoh_config(path)  # read, not refused: a client's own choice
    assert json.loads(conf.get_json("connect/endpoints")) == [
        "tls/192.168.10.2:7447",
        "quic/rig1.lab:7447",
    ]


@pytest.mark.parametrize(
    ("endpoint", "loopback"),
    [
        ("tcp/127.0.0.1:7447", True),
        ("tls/127.0.0.2:7447", True),
        ("tcp/[::1]:7447", True),
        ("tcp/[::ffff:127.0.0.1]:7447", True),
        ("tcp/[::ffff:10.0.0.5]:7447", False),
        ("tcp/localhost:7447", True),
        ("unixsock-stream//tmp/zenoh.sock", True),
        ("tcp/0.0.0.0:7447", False),
        ("tcp/[::]:7447", False),
        ("quic/192.168.1.20:7447", False),
        ("tls/rig1.lab:7447", False),
    ],
)
def test_loopback_endpoints(endpoint: str, loopback: bool):
    assert is_loopback(endpoint) is loopback


@pytest.mark.process
def test_daemon_refuses_an_insecure_zenoh_config_before_opening_the_bus(tmp_path: Path):
    zcfg = tmp_path / "open.json5"
    zcfg.write_text(f'{{listen: {{endpoints: ["tcp/0.0.0.0:7447"]}}, {SCOUT_OFF}}}')
    # a bus channel nothing serves: the refusal must come before the bus is opened
    cfg = rig_config(
        tmp_path, "ws://127.0.0.1:9/", None, telemetry={"enabled": True, "zenoh_config": str(zcfg)}
    )
    proc = subprocess.run(
        [sys.executable, "-m", "mrrig", "run", "--config", str(cfg), "--no-record"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {zcfg}: reaches beyond loopback")
    assert TEMPLATE in lines[0]


# ---- the lab CA ------------------------------------------------------------------------------


def test_certs_init_and_issue_make_a_chain_for_127_0_0_1(tmp_path: Path):
    d = tmp_path / "certs"
    assert certs.main(["--dir", str(d), "init"]) == 0
    assert certs.main(["--dir", str(d), "issue", "alice", "--role", "operator"]) == 0
    ca = x509.load_pem_x509_certificate((d / "ca.pem").read_bytes())
    cert = x509.load_pem_x509_certificate((d / "alice.pem").read_bytes())
    cert.verify_directly_issued_by(ca)
    assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "alice"
    unit = cert.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)[0].value
    assert unit == "operator"
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "127.0.0.1" in [str(ip) for ip in san.get_values_for_type(x509.IPAddress)]
    assert (d / "alice-key.pem").stat().st_mode & 0o077 == 0  # the key is the owner's only


def test_certs_refuse_to_replace_a_ca_and_need_one_to_issue(tmp_path: Path):
    d = tmp_path / "certs"
    with pytest.raises(certs.CertError, match="run `mrrig certs init` first"):
        certs.issue(d, "bob", "observer")
    certs.init_ca(d)
    with pytest.raises(certs.CertError, match="--force"):
        certs.init_ca(d)
    with pytest.raises(certs.CertError, match="unknown role"):
        certs.issue(d, "bob", "admin")


# ---- real sessions on 127.0.0.1 --------------------------------------------------------------


def _lab(tmp_path: Path) -> Path:
    """A lab CA with the shipped roles' certificates, and a second CA with an `operator`."""
    d = tmp_path / "certs"
    certs.init_ca(d)
    for name in ("rig", "observer", "operator"):
        certs.issue(d, name, name)
    other = tmp_path / "other-ca"
    certs.init_ca(other)
    certs.issue(other, "operator", "operator")
    return d


def _template(name: str, tmp_path: Path, port: int) -> Path:
    """A shipped template with its certificate folder and port made the test's."""
    text = (ZENOH / name).read_text()
    text = text.replace('"certs/', f'"{tmp_path}/certs/').replace(":7447", f":{port}")
    path = tmp_path / name
    path.write_text(text)
    return path


def _open(path: Path | zenoh.Config, timeout_s: float = 30.0) -> zenoh.Session:
    conf = path if isinstance(path, zenoh.Config) else load_zenoh_config(path)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return zenoh.open(conf)
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)


def _refused(conf: zenoh.Config) -> bool:
    try:
        zenoh.open(conf).close()
    except zenoh.ZError:
        return True
    return False


def _fields(session: zenoh.Session, rig: str, seconds: float) -> dict[str, list]:
    """The telemetry of `seconds` from now, longer (up to 10 s) until there is some."""
    sub = session.declare_subscriber(keys(rig)["telemetry"])
    got: dict[str, list] = {}
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < (seconds if got else 10.0):
            sample = sub.try_recv()
            if sample is None:
                time.sleep(0.01)
                continue
            for name, values in json.loads(sample.payload.to_bytes())["fields"].items():
                got.setdefault(name, []).extend(values)
    finally:
        sub.undeclare()
    return got


def _status(session: zenoh.Session, rig: str) -> dict | None:
    for reply in session.get(keys(rig)["status"], timeout=2.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None


@pytest.mark.process
def test_mtls_and_access_control_with_the_daemon(tmp_path: Path, bridge, procs):
    """Observer reads but cannot drive; operator arms; no certificate or another CA's: no
    session. The observer's control queries and force_ref puts are dropped by the rig's access
    control: they never reach the daemon, so the audit on `events` shows only what did."""
    rig = "sec"
    _lab(tmp_path)
    port = find_free_port()
    rig_conf = _template("rig.json5", tmp_path, port)
    cfg = rig_config(
        tmp_path,
        bridge,
        None,
        rig={"name": rig},
        loop={"realtime": False},
        controller={"name": "constant", "current_a": 0.5},
        reference={"kind": "zenoh", "timeout_s": 5.0},
        telemetry={"enabled": True, "zenoh_config": str(rig_conf), "rate_hz": 20.0},
    )
    procs(["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge])
    procs(["-m", "mrrig", "run", "--config", str(cfg), "--no-record"])
    observer = _open(_template("observer.json5", tmp_path, port))
    operator = None
    try:
        # no client certificate, a certificate of another CA, plain TCP: no session at all
        bare = zenoh.Config.from_json5(
            f'{{mode: "client", connect: {{endpoints: ["tls/127.0.0.1:{port}"]}}, {SCOUT_OFF}, '
            f'transport: {{link: {{tls: {{root_ca_certificate: "{tmp_path}/certs/ca.pem"}}}}}}}}'
        )
        assert _refused(bare)
        foreign = load_zenoh_config(_template("operator.json5", tmp_path, port))
        foreign.insert_json5(
            "transport/link/tls/connect_certificate",
            json.dumps(str(tmp_path / "other-ca/operator.pem")),
        )
        foreign.insert_json5(
            "transport/link/tls/connect_private_key",
            json.dumps(str(tmp_path / "other-ca/operator-key.pem")),
        )
        assert _refused(foreign)
        plain = zenoh.Config.from_json5(
            f'{{mode: "client", connect: {{endpoints: ["tcp/127.0.0.1:{port}"]}}, {SCOUT_OFF}}}'
        )
        assert _refused(plain)

        # the observer reads status and telemetry ...
        deadline = time.monotonic() + 30
        status = None
        while status is None and time.monotonic() < deadline:
            status = _status(observer, rig)
        assert status is not None and status["state"] in ("IDLE", "FAULT"), status
        assert _fields(observer, rig, 1.0)["t"], "the observer got no telemetry"
        # ... but cannot drive the rig: no reply, nothing changes
        for request in ({"cmd": "arm"}, {"cmd": "set_controller", "name": "heaviside"}):
            with pytest.raises(client.ClientError, match="no daemon answered"):
                client.query(observer, rig, request, timeout_s=1.0)
        received0 = status["force_refs_received"]
        pub = observer.declare_publisher(keys(rig)["force_ref"])
        for _ in range(20):
            pub.put(json.dumps({"force_n": 1234.0}))
            time.sleep(0.02)
        pub.undeclare()
        seen = _fields(observer, rig, 0.5)
        assert 1234.0 not in seen["f_des"]
        status = _status(observer, rig)
        assert status["state"] != "ARMED" and status["controller"] == "constant", status
        assert status["force_refs_received"] == received0, status

        # the operator's force reference arrives; it arms, and sees its audit events
        op_conf = load_zenoh_config(_template("operator.json5", tmp_path, port))
        operator = _open(op_conf)
        events = operator.declare_subscriber(keys(rig)["events"])
        pub = operator.declare_publisher(keys(rig)["force_ref"])
        # a settled session: a Zenoh client drops puts that match no subscriber it was told
        # of, and the rig's access control must tell operators of force_ref's (its first
        # second's puts went through without: CI, loaded, saw none arrive in 10 s)
        time.sleep(2.0)
        # put until the daemon has counted one, as send-force does
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            pub.put(json.dumps({"force_n": 1234.0}))
            time.sleep(0.02)
            status = _status(operator, rig)
            if status and status["force_refs_received"] > received0:
                break
        assert 1234.0 in _fields(operator, rig, 0.5)["f_des"]
        pub.put(json.dumps({"force_n": 1234.0}))  # fresh for the arm (stale after 5 s)
        pub.undeclare()
        claims = audit.claims(operator, op_conf)
        reply = client.query(operator, rig, {"cmd": "arm"}, timeout_s=3.0, claims=claims)
        assert reply["ok"] is True and reply["state"] == "ARMED", reply
        # refused whatever the rig's state since the arm (a stall may have faulted it)
        request = {"cmd": "no_such_cmd"}
        refused = client.query(operator, rig, request, timeout_s=3.0, claims=claims)
        assert refused["ok"] is False, refused
        audits = []
        deadline = time.monotonic() + 5
        while len(audits) < 2 and time.monotonic() < deadline:
            sample = events.try_recv()
            if sample is None:
                time.sleep(0.02)
                continue
            event = json.loads(sample.payload.to_bytes())
            if event.get("kind") == "audit":
                audits.append(event)
        events.undeclare()
        assert audits[0]["request"]["cmd"] == "arm"
        assert json.loads(audits[1]["request"]["raw"]) == {"cmd": "no_such_cmd"}  # unparsed
        assert [a["result"]["ok"] for a in audits] == [True, False]
        assert "unknown command 'no_such_cmd'" in audits[1]["result"]["error"]
        for a in audits:
            claimed = a["requester"]["claimed"]
            assert claimed["cert_cn"] == "operator"
            assert claimed["zid"] == str(operator.info.zid())
            # what Zenoh authenticated: the certificate on the link of that session
            assert a["requester"]["link"]["auth"] == "operator"
            assert a["text"].startswith("control ") and "from operator (authenticated" in a["text"]
    finally:
        observer.close()
        if operator is not None:
            operator.close()


@pytest.mark.process
def test_user_password_and_access_control(tmp_path: Path):
    """The sidecar on the user-password template: a wrong password gets no session; the
    observer's control query never reaches the loop; the operator's does."""
    (tmp_path / "certs").mkdir()
    (tmp_path / "certs" / "users.txt").write_text("operator:op-secret\nobserver:ob-secret\n")
    port = find_free_port()
    conf = _template("rig-usrpwd.json5", tmp_path, port)
    fds = make_channel(pipe_bytes=None)
    loop = LoopEnd(fds.loop_rx, fds.loop_tx)
    proc = start_sidecar("pw", conf, fds)

    def user(name: str, password: str) -> zenoh.Config:
        c = load_zenoh_config(_template(f"{name}-usrpwd.json5", tmp_path, port))
        c.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
        return c

    sessions = []
    try:
        operator = _open(user("operator", "op-secret"))
        sessions.append(operator)
        observer = _open(user("observer", "ob-secret"))
        sessions.append(observer)
        assert _refused(user("operator", "wrong"))
        with pytest.raises(client.ClientError, match="no daemon answered"):
            client.query(observer, "pw", {"cmd": "arm"}, timeout_s=1.0)
        assert [m for m, _ in loop.poll() if m == Msg.REQUEST] == []  # it never reached the loop
        # the operator's reaches it (the test plays the loop and does not answer), and its
        # audit has the link of its session (Zenoh 1.10 names no user on a user-password link:
        # its auth identifier is empty; the user stays what the client claims)
        events = operator.declare_subscriber(keys("pw")["events"])
        time.sleep(0.3)
        claims = audit.claims(operator, user("operator", "op-secret"))
        reply = client.query(operator, "pw", {"cmd": "arm"}, timeout_s=3.0, claims=claims)
        assert reply == {"ok": False, "error": "daemon did not answer"}
        requests = [json.loads(p[1]) for m, p in loop.poll() if m == Msg.REQUEST]
        assert [r["cmd"] for r in requests] == ["arm"]
        sample = events.recv()
        events.undeclare()
        event = json.loads(sample.payload.to_bytes())
        assert event["kind"] == "audit" and event["result"]["ok"] is False
        assert event["requester"]["link"]["zid"] == str(operator.info.zid())
        assert event["requester"]["claimed"]["zenoh_user"] == "operator"
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


def test_the_router_templates_access_control(tmp_path: Path):
    """A fleet's router (configs/zenoh/router.json5) and a rig's sidecar session on
    configs/zenoh/rig-fleet.json5, mutual TLS: through the router an observer reads the rig's
    status, liveliness and telemetry, and its control query and force_ref never reach the rig;
    an operator's do."""
    d = _lab(tmp_path)
    certs.issue(d, "router", "router")
    port = find_free_port()
    router = _open(_template("router.json5", tmp_path, port))
    sessions = []
    try:
        rig = _open(_template("rig-fleet.json5", tmp_path, port))
        sessions.append(rig)
        reached: list[str] = []

        def on_control(query: zenoh.Query) -> None:
            reached.append("control")
            query.reply(keys("rig")["control"], '{"ok": true}')
            query.drop()

        entities = [
            rig.declare_queryable(keys("rig")["control"], on_control),
            rig.declare_queryable(
                keys("rig")["status"],
                lambda q: (q.reply(keys("rig")["status"], '{"state": "IDLE"}'), q.drop()),
            ),
            rig.declare_subscriber(keys("rig")["force_ref"], lambda s: reached.append("force")),
            rig.liveliness().declare_token(alive_token("rig", str(rig.zid()))),
        ]
        telemetry = rig.declare_publisher(keys("rig")["telemetry"])
        entities.append(telemetry)
        for role, may_drive in (("observer", False), ("operator", True)):
            s = _open(_template(f"{role}.json5", tmp_path, port))
            sessions.append(s)
            got: list[int] = []
            sub = s.declare_subscriber(keys("rig")["telemetry"], lambda _s, got=got: got.append(1))
            alive = [r.ok for r in s.liveliness().get(fleet.ALIVE, timeout=2.0) if r.ok]
            status = [r.ok for r in s.get("mrrig/*/status", timeout=2.0) if r.ok]
            assert len(alive) == 1 and len(status) == 1, role
            deadline = time.monotonic() + 5
            while not got and time.monotonic() < deadline:
                telemetry.put("{}")
                time.sleep(0.1)
            assert got, f"{role}: no telemetry"
            reached.clear()
            replies = [r.ok for r in s.get(keys("rig")["control"], timeout=1.0) if r.ok]
            s.put(keys("rig")["force_ref"], "1")
            time.sleep(0.5)
            assert (len(replies) == 1) is may_drive, role
            assert sorted(reached) == (["control", "force"] if may_drive else []), role
            sub.undeclare()
        for e in entities:
            e.undeclare()
    finally:
        for s in sessions:
            s.close()
        router.close()
