"""An observer's liveliness tokens of the rig's name neither fault an armed rig nor lock its
operator out (issue 40, finding 3): the daemon on configs/zenoh/rig.json5 with mutual TLS
against firmware_sim (a process module; the observer's other limits, on the sidecar alone, are
tests/test_observer_acl.py's, which hold the machine shared)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from mrrig.rigio import audit, client
from mrrig.rigio.canbus.bus import find_free_port
from mrrig.rigio.rig_topics import keys
from mrrig.rigio.zenoh_config import load_zenoh_config
from tests.conftest import rig_config
from tests.test_observer_acl import _drain, _fakes
from tests.test_zenoh_security import _lab, _open, _status, _template


@pytest.mark.process
def test_an_observers_token_neither_faults_an_armed_rig_nor_locks_the_operator_out(
    tmp_path: Path, bridge, procs
):
    """The daemon on configs/zenoh/rig.json5 (mutual TLS), armed by the operator: an
    observer's liveliness tokens of the rig's name (as a daemon's and plainly its own) leave it
    armed, with no `duplicate_rig` event, and the operator's requests are still taken."""
    rig = "armed"
    _lab(tmp_path)
    port = find_free_port()
    cfg = rig_config(
        tmp_path,
        bridge,
        None,
        rig={"name": rig},
        loop={"realtime": False},
        controller={"name": "constant", "current_a": 0.5},
        telemetry={
            "enabled": True,
            "zenoh_config": str(_template("rig.json5", tmp_path, port)),
            "rate_hz": 20.0,
        },
    )
    procs(["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge])
    procs(["-m", "mrrig", "run", "--config", str(cfg), "--no-record"])
    op_conf = load_zenoh_config(_template("operator.json5", tmp_path, port))
    operator = _open(op_conf)
    observer = _open(_template("observer.json5", tmp_path, port))
    try:
        deadline = time.monotonic() + 30
        while _status(operator, rig) is None and time.monotonic() < deadline:
            time.sleep(0.2)
        events = operator.declare_subscriber(keys(rig)["events"])
        claims = audit.claims(operator, op_conf)
        reply = client.query(operator, rig, {"cmd": "arm"}, timeout_s=3.0, claims=claims)
        assert reply["ok"] is True and reply["state"] == "ARMED", reply
        tokens = [observer.liveliness().declare_token(t) for t in _fakes(rig)]
        time.sleep(3.0)  # the sidecar would have faulted the rig within one frame of it
        status = _status(operator, rig)
        assert status is not None and status["fault"] != "duplicate_rig", status
        # armed still, unless the VM stalled the rig (a fault of its own, never this one)
        assert status["state"] == "ARMED" or status["fault"] not in (None, "duplicate_rig")
        marked = client.query(
            operator, rig, {"cmd": "mark", "text": "still mine"}, timeout_s=3.0, claims=claims
        )
        assert marked["ok"] is True, marked
        kinds = [json.loads(s.payload.to_bytes()).get("kind") for s in _drain(events)]
        assert "duplicate_rig" not in kinds, kinds
        alive = [str(r.ok.key_expr) for r in operator.liveliness().get(keys(rig)["alive"]) if r.ok]
        assert len(alive) == 1 and alive[0] not in _fakes(rig), alive
        for t in tokens:
            t.undeclare()
        events.undeclare()
    finally:
        observer.close()
        operator.close()
