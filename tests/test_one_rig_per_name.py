"""One rig per name on a Zenoh network (issue 32, finding 2): two daemons of one `[rig] name`
both obeyed every request (`mrrig arm` armed both, the client saw one reply, `mrrig rigs` one
row). Each rig here is a real bridge, firmware_sim and `mrrig run` with its sidecar, on
127.0.0.1 with multicast scouting off; the CLI runs as a process."""

from __future__ import annotations

import contextlib
import json
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from mrrig.rigio import client, fleet
from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge
from tests.conftest import rig_config, start, stop, wait_until, write_json
from tests.test_lifecycle_errors import mrrig

pytestmark = pytest.mark.process
RIG = "dup"
SCOUT_OFF = {"multicast": {"enabled": False}}


def _endpoint(port: int) -> list[str]:
    return [f"tcp/127.0.0.1:{port}"]


@dataclass
class Rig:
    """A simulated rig: bridge, firmware_sim, and its daemon's config (not started)."""

    work: Path
    bridge: subprocess.Popen
    sim: subprocess.Popen
    config: Path
    zenoh_port: int
    client_config: Path

    def daemon(self, *args: str) -> subprocess.Popen:
        cmd = ["-m", "mrrig", "run", "--config", str(self.config), "--no-record"]
        cmd += ["--summary-json", str(self.work / "summary.json"), *args]
        with open(self.work / "daemon.log", "w") as log:  # its own copy stays open
            return start(cmd, stdout=subprocess.DEVNULL, stderr=log)

    def live(self) -> bool:
        try:
            with client.open_session(self.client_config) as session:
                return bool(fleet.live_rigs(session, 0.5))
        except client.ClientError:  # its sidecar does not listen yet
            return False


@contextlib.contextmanager
def simulated_rig(tmp_path: Path, label: str, connect: list[str] = ()) -> Iterator[Rig]:
    """A rig named RIG whose daemon's sidecar listens on a port of its own (and connects to
    `connect`), and a client config reaching it."""
    work = tmp_path / label
    work.mkdir()
    bport, zport = find_free_port(), find_free_port()
    bridge = start_bridge(bport)
    channel = f"ws://127.0.0.1:{bport}/"
    sim = start(["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", channel])
    peer = {"mode": "peer", "listen": {"endpoints": _endpoint(zport)}, "scouting": SCOUT_OFF}
    if connect:
        peer["connect"] = {"endpoints": list(connect)}
    zenoh_conf = write_json(work / "zenoh.json5", peer)
    client_conf = write_json(
        work / "client.json5",
        {"mode": "client", "connect": {"endpoints": _endpoint(zport)}, "scouting": SCOUT_OFF},
    )
    cfg = rig_config(
        work,
        channel,
        None,
        rig={"name": RIG},
        controller={"name": "constant", "current_a": 0.5},
        reference={"kind": "constant", "offset_n": 0.0},
        telemetry={"enabled": True, "zenoh_config": str(zenoh_conf), "rate_hz": 10.0},
    )
    try:
        yield Rig(work, bridge, sim, cfg, zport, client_conf)
    finally:
        stop(sim)
        stop_bridge(bridge)


def _summary(rig: Rig) -> dict:
    return json.loads((rig.work / "summary.json").read_text())


def test_a_second_daemon_of_a_live_name_refuses_to_start_before_it_opens_the_bus(tmp_path):
    with simulated_rig(tmp_path, "a") as a:
        first = a.daemon()
        try:
            assert wait_until(a.live, 60), "the first daemon never came up"
            with simulated_rig(tmp_path, "b", connect=_endpoint(a.zenoh_port)) as b:
                record = b.work / "b.rrd"
                cmd = ["-m", "mrrig", "run", "--config", str(b.config), "--duration", "5"]
                cmd += ["--record", str(record)]
                second = start(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                out, err = second.communicate(timeout=90)
            assert second.returncode == 2, out + err
            lines = [line for line in err.splitlines() if line.startswith("error:")]
            assert len(lines) == 1 and "Traceback" not in err, err
            assert f"rig {RIG!r} is already served on this Zenoh network" in lines[0]
            assert f"mrrig/{RIG}/alive/" in lines[0]  # the live daemon's token
            # no hint to run without Zenoh: that daemon would open the served rig's bus
            assert "--no-telemetry" not in lines[0], lines[0]
            assert not record.exists(), "the refused daemon started a recording"
            # the running rig never heard of it: no fault, and it still answers alone
            status = client.status(RIG, a.client_config, timeout_s=5.0)["status"]
            assert status["fault"] is None, status
            assert first.poll() is None
        finally:
            stop(first)
    assert not _summary(a)["faults"], _summary(a)["faults"]


def test_two_live_daemons_of_one_name_fault_safe_and_every_client_says_so(tmp_path):
    """Two daemons that started apart (their networks joined later, through a router, as a
    rig that starts before its router does) each see the other's token: both fault SAFE,
    refuse to arm, and the CLI names the duplicate instead of acting on one reply."""
    with simulated_rig(tmp_path, "a") as a, simulated_rig(tmp_path, "b") as b:
        daemons = [a.daemon(), b.daemon()]
        router = None
        try:
            assert wait_until(a.live, 60) and wait_until(b.live, 60), "a daemon never came up"
            for rig in (a, b):
                assert client.status(RIG, rig.client_config, 5.0)["status"]["fault"] is None
            rport = find_free_port()
            router = zenoh.open(
                zenoh.Config.from_json5(
                    json.dumps(
                        {
                            "mode": "router",
                            "listen": {"endpoints": _endpoint(rport)},
                            "connect": {
                                "endpoints": _endpoint(a.zenoh_port) + _endpoint(b.zenoh_port)
                            },
                            "scouting": SCOUT_OFF,
                        }
                    )
                )
            )
            joined = write_json(
                tmp_path / "joined.json5",
                {
                    "mode": "client",
                    "connect": {"endpoints": _endpoint(rport)},
                    "scouting": SCOUT_OFF,
                },
            )
            with client.open_session(joined) as session:

                def answers(request: dict) -> list[dict]:
                    """Every daemon's reply (Zenoh's default consolidation keeps one)."""
                    replies = session.get(
                        f"mrrig/{RIG}/control",
                        payload=json.dumps(request),
                        timeout=5.0,
                        consolidation=zenoh.ConsolidationMode.NONE,
                    )
                    return [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok]

                def both_faulted() -> bool:
                    statuses = [a["status"] for a in answers({"cmd": "status"})]
                    return len(statuses) == 2 and all(
                        s["fault"] == "duplicate_rig" for s in statuses
                    )

                assert wait_until(both_faulted, 20), answers({"cmd": "status"})
                for status in [a["status"] for a in answers({"cmd": "status"})]:
                    assert status["state"] == "FAULT" and not status["armed"], status
                    assert "already served" in status["fault_reason"]
                # both refuse what the other would obey too; each stays SAFE
                for reply in answers({"cmd": "arm"}) + answers({"cmd": "reset"}):
                    assert reply["ok"] is False and "already served" in reply["error"], reply
                assert [a["status"]["armed"] for a in answers({"cmd": "status"})] == [False] * 2

            listed = mrrig("rigs", "--zenoh-config", str(joined), "--json")
            assert listed.returncode == 1, listed.stdout + listed.stderr
            [row] = json.loads(listed.stdout)
            assert row["rig"] == RIG and row["daemons"] == 2, row
            assert f"error: rig {RIG!r} is served by 2 daemons" in listed.stderr
            table = mrrig("rigs", "--zenoh-config", str(joined))
            assert "(x2 DUPLICATE)" in table.stdout, table.stdout
            for command in ("status", "arm", "disarm"):
                got = mrrig(command, "--rig", RIG, "--zenoh-config", str(joined))
                assert got.returncode == 2, got.stdout + got.stderr
                assert f"error: 2 daemons answered as rig {RIG!r}" in got.stderr, got.stderr
        finally:
            if router is not None:
                router.close()
            for proc in daemons:
                stop(proc)
    for rig in (a, b):
        faults = [f.get("fault") for f in _summary(rig)["faults"]]
        assert "duplicate_rig" in faults, faults
