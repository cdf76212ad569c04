"""Issue 34: a rig cut off from the lab's database during a run, then reconnected. The run goes
into the rig's local catalog (the spool), and `mrrig runs sync` brings it over exactly once.
A real PostgreSQL server (Debian's), stopped and started again by the test; the bridge, the
simulator and the daemon as processes."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from mrrig.rigio.canbus.bus import find_free_port
from tests.conftest import REPO, OutputWatch, rig_config
from tests.test_catalog import _as_postgres, _new_pg_database, _pg_bin

pytestmark = pytest.mark.process


class Server:
    """A PostgreSQL server in a temporary directory that the test can stop and start."""

    def __init__(self) -> None:
        bin_dir = _pg_bin()
        if bin_dir is None:
            pytest.skip("no PostgreSQL server installed (Debian's postgresql package)")
        self.bin = bin_dir
        self.base = Path(tempfile.mkdtemp(prefix="mrrig-pg-cut-"))
        self.data, self.port = self.base / "data", find_free_port()
        if os.geteuid() == 0:
            shutil.chown(self.base, "postgres", "postgres")
        initdb = [str(bin_dir / "initdb"), "-D", str(self.data), "-A", "trust", "-U", "postgres"]
        subprocess.run(
            _as_postgres([*initdb, "--no-sync", "-E", "UTF8", "--locale=C"]),
            check=True,
            capture_output=True,
        )
        self.admin = f"postgresql://postgres@127.0.0.1:{self.port}/postgres"

    def ctl(self, *args: str) -> None:
        options = f"-p {self.port} -k {self.base} -c listen_addresses=127.0.0.1 -c fsync=off"
        cmd = [str(self.bin / "pg_ctl"), "-D", str(self.data), "-l", str(self.base / "log")]
        subprocess.run(
            _as_postgres([*cmd, "-w", "-t", "60", "-o", options, *args]),
            check=True,
            capture_output=True,
        )


@pytest.fixture
def server() -> Iterator[Server]:
    s = Server()
    s.ctl("start")
    try:
        yield s
    finally:
        subprocess.run(
            _as_postgres([str(s.bin / "pg_ctl"), "-D", str(s.data), "-m", "immediate", "stop"]),
            capture_output=True,
        )
        shutil.rmtree(s.base, ignore_errors=True)


def _runs(catalog: str) -> list[dict]:
    listed = subprocess.run(
        [sys.executable, "-m", "mrrig", "runs", "--json", "--catalog", catalog],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    runs = json.loads(listed.stdout)
    assert listed.returncode == (0 if runs else 1), listed.stderr  # 1: no run (issue 40)
    return runs["runs"] if isinstance(runs, dict) else runs


def _sync(local: Path, lab: str) -> str:
    done = subprocess.run(
        [sys.executable, "-m", "mrrig", "runs", "sync", "--from", str(local), "--to", lab],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout + done.stderr


def test_a_rig_cut_off_from_the_lab_database_spools_its_run_and_sync_brings_it_once(
    tmp_path, bridge, procs, server
):
    lab = _new_pg_database(server.admin)
    _runs(lab)  # the lab's catalog exists (migrated) before the rig loses it
    local = tmp_path / "rig-local" / "catalog.sqlite"
    sim = procs(
        ["-m", "firmware_sim", "--config", "configs/sim.toml", "--bus-channel", bridge],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    assert OutputWatch(sim, "rig firmware on").seen.wait(30)
    cfg = rig_config(
        tmp_path,
        bridge,
        None,
        controller={"name": "constant", "current_a": 0.5},
        catalog={"url": lab, "spool": str(local)},
    )
    summary = tmp_path / "summary.json"
    daemon = procs(
        ["-m", "mrrig", "run", "--config", str(cfg), "--arm", "--duration", "3", "--record",
         str(tmp_path / "run.rrd"), "--summary-json", str(summary)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    out = OutputWatch(daemon, "loop running")
    assert out.seen.wait(60), out.text()
    server.ctl("-m", "immediate", "stop")  # the lab's database goes away during the run
    assert daemon.wait(timeout=60) in (0, 1), out.text()
    out.join()
    text = out.text()
    assert "Traceback" not in text, text[-3000:]
    assert "(spooled: the catalog asked for was unreachable)" in text, text[-2000:]
    run_id = json.loads(summary.read_text())["run_id"]
    assert [r["run_id"] for r in _runs(str(local))] == [run_id]

    server.ctl("start")  # reconnected
    first = _sync(local, lab)
    again = _sync(local, lab)
    print(first, again, sep="\n")
    found = _runs(lab)
    assert [r["run_id"] for r in found] == [run_id]
    assert first.startswith("sync: 1 copied, 0 updated, 0 already there"), first
    assert again.startswith("sync: 0 copied, 0 updated, 1 already there"), again
