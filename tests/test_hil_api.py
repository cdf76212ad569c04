"""HIL runs from Python (issue 41, item 7: `mrrig.api` access): `run_hil` on a rig over real
Zenoh on 127.0.0.1. The rig's control endpoint is a Zenoh queryable answering from a real
in-process `Daemon` running `[hil]` (its `hil.status()`, its `set_hil` through the daemon's own
`scenario_with` and `set_scenario`); what `run_hil` refuses, it refuses before arming (no `arm`
asked). The run itself on the simulated rig is tests/test_hil_sim.py's (`follow`, which
`run_hil` ends in). In-process; a few seconds."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import zenoh

import mrrig.api
from mrrig.api import HilRunError, Rig, run_hil
from mrrig.config import load_config
from mrrig.loop.daemon import Daemon
from mrrig.loop.hil_loop import scenario_with
from mrrig.rigio.rig_topics import keys
from mrrig.rigio.zenoh_config import load_zenoh_config
from tests.conftest import REPO, rig_config, zenoh_configs

RIG = "hil-api-test"


def test_dir_of_mrrig_api_lists_the_hil_faces():
    names = dir(mrrig.api)
    for name in ("run_hil", "hil_tracking", "HilResult", "HilRunError", "load_scenario"):
        assert name in names and getattr(mrrig.api, name) is not None
    assert "run_reference" in names


def _stroke(tmp_path):
    t = np.arange(0, 2.001, 0.001)
    x = 0.005 * np.clip(np.minimum(t, 2 - t) / 0.5, 0, 1) * np.sin(2 * np.pi * 2 * t)
    path = tmp_path / "stroke.csv"
    path.write_text("t_s,x_m\n" + "\n".join(f"{a:.3f},{b:.7f}" for a, b in zip(t, x, strict=True)))
    return path


def _serve(tmp_path, hil_scenario: str | None):
    """A Zenoh control endpoint on 127.0.0.1 answering as a daemon with `[hil]` (or without)."""
    sections = {} if hil_scenario is None else {"hil": {"scenario": hil_scenario}}
    config = rig_config(
        tmp_path,
        "unused",
        None,
        bus={"interface": "virtual"},
        controller={"name": "constant", "current_a": 0.5},
        **sections,
    )
    daemon = Daemon(load_config(config))
    daemon_conf, client_conf, _ = zenoh_configs(tmp_path)
    session = zenoh.open(load_zenoh_config(daemon_conf))
    asked: list[dict] = []

    def on_query(query: zenoh.Query) -> None:
        req = json.loads(query.payload.to_string())
        asked.append(req)
        if req["cmd"] == "status":
            status = {"state": "IDLE", "fault": None}
            if daemon.hil is not None:
                status["hil"] = daemon.hil.status()
            reply = {"ok": True, "status": status}
        elif req["cmd"] == "set_hil":
            fields = {k: v for k, v in req.items() if k != "cmd"}
            daemon.hil.set_scenario(scenario_with(daemon.hil.configured, fields, "set_hil"))
            reply = {"ok": True}
        else:
            reply = {"ok": False, "error": f"not in this test: {req['cmd']}"}
        query.reply(query.key_expr, json.dumps(reply))
        query.drop()

    queryable = session.declare_queryable(keys(RIG)["control"], on_query)
    time.sleep(0.3)
    return session, queryable, client_conf, asked


def _ask(tmp_path, hil_scenario, **kw) -> tuple[str, list[dict]]:
    session, queryable, client_conf, asked = _serve(tmp_path, hil_scenario)
    try:
        with Rig(RIG, client_conf, timeout_s=5.0) as rig, pytest.raises(HilRunError) as err:
            run_hil(rig, **kw)
    finally:
        queryable.undeclare()
        session.close()
    return str(err.value), asked


def test_a_rig_without_hil_is_refused_in_one_line(tmp_path):
    why, asked = _ask(tmp_path, None)
    assert why == f"rig {RIG} runs no hybrid simulation (its daemon has no [hil] scenario)"
    assert asked == [{"cmd": "status"}]


def test_run_hil_sets_the_next_run_and_refuses_a_scenario_that_is_not_the_daemon_s(tmp_path):
    stroke = _stroke(tmp_path)
    other = REPO / "configs/hil/quarter-car.toml"
    why, asked = _ask(tmp_path, str(stroke), law="passive-hard", duration_s=1.5, scenario=other)
    assert asked == [
        {"cmd": "status"},
        {"cmd": "set_hil", "law": "passive-hard", "duration_s": 1.5},
        {"cmd": "status"},
    ]  # no arm
    assert why.startswith(f"rig {RIG}'s daemon runs scenario {stroke} (sha256 ")
    assert why.endswith(f"which {other} here is not") and "\n" not in why


def test_a_stroke_file_changed_since_the_daemon_read_it_is_refused_before_arming(tmp_path):
    """The daemon checked the record it read at start; the file here is what the reference
    and the client's feasibility check would read: another one is refused."""
    stroke = _stroke(tmp_path)
    session, queryable, client_conf, asked = _serve(tmp_path, str(stroke))
    try:
        stroke.write_text(stroke.read_text().replace("t_s,x_m\n", "t_s,x_m\n\n"))
        with Rig(RIG, client_conf, timeout_s=5.0) as rig, pytest.raises(HilRunError) as err:
            run_hil(rig)
    finally:
        queryable.undeclare()
        session.close()
    assert asked == [{"cmd": "status"}]
    assert f"which {stroke} here is not" in str(err.value)
