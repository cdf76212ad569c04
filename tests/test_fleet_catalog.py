"""Issue 34's fleet acceptance: a router and three rigs (bridge, simulator and daemon each, as
processes), each run registered by its own sidecar in one shared catalog (an SQLite file on
this host, and a PostgreSQL server started by the test), and a fourth client finds all of
them with `mrrig runs --json`, their numbers equal to each daemon's summary."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge
from tests.conftest import REPO, rig_config, stop
from tests.test_catalog import _new_pg_database, pg_server  # noqa: F401 - the fixture

pytestmark = pytest.mark.process

SCOUT_OFF = {"multicast": {"enabled": False}}


@pytest.fixture(params=["sqlite", "postgresql"])
def shared_catalog(request, tmp_path) -> str:
    if request.param == "sqlite":
        return str(tmp_path / "lab" / "catalog.sqlite")
    return _new_pg_database(request.getfixturevalue("pg_server"))


def _write(path: Path, conf: dict) -> Path:
    path.write_text(json.dumps(conf))
    return path


def test_three_rigs_register_their_runs_in_one_catalog_a_fourth_client_finds_them(
    tmp_path, procs, shared_catalog
):
    port = find_free_port()
    endpoint = [f"tcp/127.0.0.1:{port}"]
    router = _write(
        tmp_path / "router.json5",
        {"mode": "router", "listen": {"endpoints": endpoint}, "scouting": SCOUT_OFF},
    )
    rig_conf = _write(
        tmp_path / "rig.json5",
        {"mode": "peer", "listen": {"endpoints": []}, "connect": {"endpoints": endpoint},
         "scouting": SCOUT_OFF},
    )  # fmt: skip
    procs(["-m", "mrrig", "router", "--config", str(router)])
    bridges, sims, daemons, summaries = [], {}, {}, {}
    try:
        for name in ("rig1", "rig2", "rig3"):
            bport = find_free_port()
            bridges.append(start_bridge(bport))
            channel = f"ws://127.0.0.1:{bport}/"
            work = tmp_path / name
            work.mkdir()
            sims[name] = procs(
                ["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", channel],
                stdout=subprocess.DEVNULL,
            )
            cfg = rig_config(
                work,
                channel,
                None,
                rig={"name": name, "specimen": f"SN-{name}"},
                controller={"name": "constant", "current_a": 0.5},
                telemetry={"enabled": True, "zenoh_config": str(rig_conf), "rate_hz": 10.0},
            )
            summaries[name] = work / "summary.json"
            daemons[name] = procs(
                ["-m", "mrrig", "run", "--config", str(cfg), "--arm", "--duration", "3",
                 "--record", str(work / "run.rrd"), "--summary-json", str(summaries[name]),
                 "--catalog", shared_catalog],
                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            )  # fmt: skip
        for daemon in daemons.values():
            out, _ = daemon.communicate(timeout=120)
            assert daemon.returncode in (0, 1), out  # 1: a fault; the catalog says so too
            assert "Traceback" not in out, out[-3000:]
            assert " registered in " in out and " (spooled" not in out, out[-2000:]
    finally:
        for proc in sims.values():
            stop(proc)
        for bridge in bridges:
            stop_bridge(bridge)
    listed = subprocess.run(
        [sys.executable, "-m", "mrrig", "runs", "--json", "--catalog", shared_catalog],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert listed.returncode == 0, listed.stderr
    runs = json.loads(listed.stdout)
    runs = runs["runs"] if isinstance(runs, dict) else runs
    by_rig = {r["rig"]: r for r in runs}
    assert sorted(by_rig) == ["rig1", "rig2", "rig3"], runs
    for name, path in summaries.items():
        s, r = json.loads(path.read_text()), by_rig[name]
        print(f"{name}: run {r['run_id']} Et {r['et']} faults {r['faults_count']}")
        assert r["run_id"] == s["run_id"]
        assert r["specimen"] == f"SN-{name}"
        assert r["et"] == s["et"]
        assert r["faults_count"] == len(s["faults"])
        assert r["latency_p50_us"] == s["latency_us"]["p50"]
        assert r["latency_p99_us"] == s["latency_us"]["p99"]
        assert r["verdict"] == ("ok" if s["exit_code"] == 0 else "fault")
