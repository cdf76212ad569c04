"""A fleet on 127.0.0.1: a router (`mrrig router`), three simulated rigs (bridge, firmware_sim
and daemon each, the sidecars connecting to the router) and the CLI through the router."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest
import zenoh

from mrrig.rigio import fleet
from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge
from mrrig.rigio.rig_topics import alive_token
from tests.conftest import rig_config, stop, wait_until, write_json
from tests.stall_proof import check_answers, windows
from tests.test_lifecycle_errors import mrrig

pytestmark = pytest.mark.process
SCOUT_OFF = {"multicast": {"enabled": False}}


def _try_open(conf: Path) -> zenoh.Session | None:
    try:
        return zenoh.open(zenoh.Config.from_file(str(conf)))
    except zenoh.ZError:
        return None


def test_watch_all_prints_one_line_per_rig_and_nothing_without_rigs(tmp_path: Path):
    port = find_free_port()
    router = zenoh.open(
        zenoh.Config.from_json5(
            json.dumps(
                {
                    "mode": "router",
                    "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                    "scouting": SCOUT_OFF,
                }
            )
        )
    )
    conf = write_json(
        tmp_path / "c.json5",
        {
            "mode": "client",
            "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
            "scouting": SCOUT_OFF,
        },
    )
    rig = zenoh.open(zenoh.Config.from_file(str(conf)))
    try:
        token = rig.liveliness().declare_token(alive_token("bench1", str(rig.zid())))
        pub = rig.declare_publisher("mrrig/bench1/telemetry")
        fields = {"t": [0.0, 0.002], "f_des": [1.0, 2.0], "f_meas": [1.5, 2.5], "i_cmd": [0, 0.1]}
        fields |= {"latency_us": [100.0, 200.0], "state": [1, 1]}
        out = io.StringIO()
        stop = threading.Event()

        def feed() -> None:
            while not stop.wait(0.05):
                pub.put(json.dumps({"rig": "bench1", "fields": fields}))

        feeder = threading.Thread(target=feed)
        feeder.start()
        try:
            n = fleet.watch_all(conf, duration_s=2.2, out=out)
        finally:
            stop.set()
            feeder.join()
        lines = out.getvalue().splitlines()
        assert n > 0 and len(lines) == 2, lines
        assert all(line.startswith("bench1 ") and "state ARMED" in line for line in lines)
        pub.undeclare()
        token.undeclare()
        out = io.StringIO()
        assert fleet.watch_all(conf, duration_s=1.1, out=out) == 0
        assert out.getvalue().splitlines() == ["no live rigs"]
    finally:
        rig.close()
        router.close()


def test_a_router_three_rigs_and_the_cli(tmp_path: Path, procs):
    port = find_free_port()
    endpoint = [f"tcp/127.0.0.1:{port}"]
    router_conf = write_json(
        tmp_path / "router.json5",
        {"mode": "router", "listen": {"endpoints": endpoint}, "scouting": SCOUT_OFF},
    )
    client_conf = write_json(
        tmp_path / "client.json5",
        {"mode": "client", "connect": {"endpoints": endpoint}, "scouting": SCOUT_OFF},
    )
    # as configs/zenoh/rig-fleet.json5: a peer listening nowhere, so that a rig may start
    # before the router (here they do)
    rig_conf = write_json(
        tmp_path / "rig.json5",
        {
            "mode": "peer",
            "listen": {"endpoints": []},
            "connect": {"endpoints": endpoint},
            "scouting": SCOUT_OFF,
        },
    )
    bridges, channels, daemons, sims = {}, {}, {}, {}
    try:
        for name in ("rig1", "rig2", "rig3"):
            bport = find_free_port()
            bridges[name] = start_bridge(bport)
            channels[name] = f"ws://127.0.0.1:{bport}/"
            work = tmp_path / name
            work.mkdir()
            cfg = rig_config(
                work,
                channels[name],
                None,
                rig={"name": name},
                controller={"name": "constant", "current_a": 0.5},
                reference={"kind": "constant", "offset_n": 0.0},
                telemetry={"enabled": True, "zenoh_config": str(rig_conf), "rate_hz": 10.0},
            )
            daemons[name] = procs(
                ["-m", "mrrig", "run", "--config", str(cfg), "--no-record"],
                stdout=subprocess.DEVNULL,
            )
        procs(["-m", "mrrig", "router", "--config", str(router_conf)])
        session = wait_until(lambda: _try_open(client_conf), 60, step_s=0.5)
        assert session is not None, "the router never listened"
        with contextlib.closing(session):

            def names() -> list[str]:
                return [r.name for r in fleet.live_rigs(session, 0.5)]

            # every daemon's loop is up before its simulator starts: no frame goes unanswered
            assert wait_until(lambda: names() == ["rig1", "rig2", "rig3"], 90), names()
            for name in daemons:
                sims[name] = procs(
                    [
                        "-m",
                        "firmware_sim",
                        "--config",
                        "configs/sim.toml",
                        "--bus-channel",
                        channels[name],
                        "--measure-echo",
                        "--stats",
                        str(tmp_path / f"{name}-sim.json"),
                    ]
                )
            time.sleep(1.0)

            listed = mrrig("rigs", "--zenoh-config", str(client_conf), "--json")
            assert listed.returncode == 0, listed.stderr
            rows = json.loads(listed.stdout)
            assert [r["rig"] for r in rows] == ["rig1", "rig2", "rig3"]
            assert all(r["controller"] == "constant" and r["state"] for r in rows), rows

            # which rigs armed: their own state events (a transport fault of this loaded VM
            # may end rig2's ARMED state before a status is read; it cannot arm another rig)
            events = session.declare_subscriber("mrrig/*/events")
            time.sleep(0.3)
            armed = mrrig("arm", "--rig", "rig2", "--zenoh-config", str(client_conf))
            assert armed.returncode == 0, armed.stdout + armed.stderr
            assert json.loads(armed.stdout)["state"] == "ARMED"
            time.sleep(1.0)
            armed_rigs = set()
            while (sample := events.try_recv()) is not None:
                event = json.loads(sample.payload.to_bytes())
                if event.get("kind") == "state" and event["reason"].startswith("armed"):
                    armed_rigs.add(fleet.rig_of(sample.key_expr))
            events.undeclare()
            assert armed_rigs == {"rig2"}
            states = {r.name: r.status["state"] for r in fleet.live_rigs(session)}
            assert states["rig1"] != "ARMED" and states["rig3"] != "ARMED", states

            os.kill(daemons["rig3"].pid, signal.SIGKILL)
            t_kill = time.monotonic()
            assert wait_until(lambda: "rig3" not in names(), 2.0, step_s=0.05), names()
            gone_s = time.monotonic() - t_kill
            print(f"rig3 gone from the list {gone_s * 1e3:.0f} ms after SIGKILL of its daemon")
            assert names() == ["rig1", "rig2"]
            time.sleep(2.0)  # rig1 and rig2 keep running past the kill
            table = mrrig("rigs", "--zenoh-config", str(client_conf))
            assert [line.split()[0] for line in table.stdout.splitlines()[1:]] == ["rig1", "rig2"]
        # the simulators stop first, so every frame they sent had a daemon to answer it: each
        # frame a simulator sent on time got exactly one command (tests/stall_proof.py, rule 1)
        for name in ("rig1", "rig2"):
            sims[name].send_signal(signal.SIGTERM)
            assert sims[name].wait(timeout=30) == 0
            stats = json.loads((tmp_path / f"{name}-sim.json").read_text())
            print(name, stats["sensor_frames_sent"], "frames sent", stats["answers"])
            print(f"  on time: {stats['answers_on_time']}; stall windows:")
            print("".join(f"    {w}\n" for w in windows(stats)), end="")
            assert stats["sensor_frames_sent"] > 2500, stats
            check_answers(stats)
    finally:
        for proc in [*sims.values(), *daemons.values()]:
            stop(proc)
        for bridge in bridges.values():
            stop_bridge(bridge)
