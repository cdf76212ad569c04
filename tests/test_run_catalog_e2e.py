"""Issue 34: a daemon run registers itself in the run catalog (by its sidecar, after the loop),
carries its identity in its recording, and publishes itself on `mrrig/<rig>/runs`. The bridge,
the simulator and the daemon run as processes; the catalog is read back with `mrrig runs`."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import pytest

from mrrig.offline.review import read_recording
from mrrig.rigio import client
from mrrig.rigio.run_identity import file_sha256
from tests.conftest import REPO, OutputWatch, rig_config, zenoh_configs

pytestmark = pytest.mark.process


def test_a_daemon_run_is_in_the_catalog_in_its_recording_and_on_zenoh(tmp_path, bridge, procs):
    stats = tmp_path / "sim.json"
    sim = procs(
        ["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge,
         "--stats", str(stats)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    assert OutputWatch(sim, "rig firmware on").seen.wait(30)
    zconf, zclient, _ = zenoh_configs(tmp_path)
    cfg = rig_config(
        tmp_path,
        bridge,
        None,
        rig={"name": "cat1"},
        controller={"name": "constant", "current_a": 0.5},
        telemetry={"enabled": True, "zenoh_config": str(zconf)},
    )
    catalog = tmp_path / "lab" / "catalog.sqlite"
    rrd, summary_path = tmp_path / "run.rrd", tmp_path / "summary.json"
    published: list[dict] = []
    got = threading.Event()
    daemon = procs(
        ["-m", "mrrig", "run", "--config", str(cfg), "--arm", "--duration", "3", "--record",
         str(rrd), "--summary-json", str(summary_path), "--catalog", str(catalog),
         "--specimen", "SN-1234", "--tag", "smoke", "--operator", "alice"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    out = OutputWatch(daemon, "loop running")
    assert out.seen.wait(60), out.text()
    with client.open_session(zclient) as session:

        def on_run(sample) -> None:
            published.append(json.loads(sample.payload.to_bytes()))
            got.set()

        sub = session.declare_subscriber("mrrig/cat1/runs", on_run)
        rc = daemon.wait(timeout=60)
        got.wait(10)
        sub.undeclare()
    out.join()
    print(out.text()[-1500:])
    assert "Traceback" not in out.text(), out.text()[-3000:]
    assert rc in (0, 1), out.text()  # 1: ended in a fault (checked below against the catalog)
    summary = json.loads(summary_path.read_text())
    assert f"run {summary['run_id']} registered in sqlite" in out.text(), out.text()[-2000:]
    listed = subprocess.run(
        [sys.executable, "-m", "mrrig", "runs", "--json", "--catalog", str(catalog)],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert listed.returncode == 0, listed.stderr
    runs = json.loads(listed.stdout)
    runs = runs["runs"] if isinstance(runs, dict) else runs
    assert len(runs) == 1, runs
    run = runs[0]
    assert run["run_id"] == summary["run_id"]
    assert (run["rig"], run["specimen"], run["operator"]) == ("cat1", "SN-1234", "alice")
    assert run["tags"] == ["smoke"] and run["controller"] == "constant"
    assert run["controller_params"]["current_a"] == 0.5
    assert run["et"] == summary["et"]  # both through JSON: the same float, or both null
    assert run["faults_count"] == len(summary["faults"])
    assert run["latency_p99_us"] == pytest.approx(summary["latency_us"]["p99"])
    assert run["verdict"] == ("ok" if rc == 0 else "fault")
    assert run["recording_sha256"] == file_sha256(rrd)
    assert run["config_sha256"] == file_sha256(cfg)
    assert run["dbc_sha256"] == file_sha256(REPO / "configs" / "mrrig.dbc")
    # the recording says what it is, and the fleet heard of it
    ident = read_recording(rrd).identity
    assert ident is not None and ident["run_id"] == run["run_id"]
    assert ident["specimen"] == "SN-1234" and ident["config_sha256"] == run["config_sha256"]
    assert published and published[0]["run_id"] == run["run_id"], published
    assert published[0]["et"] == run["et"]
