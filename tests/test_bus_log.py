"""Bus logs: `mrrig run --can-log FILE` writes every frame the loop received or sent with
python-can's writers; the .blf and the candump .log decode with cantools and match the run's
recording (frame counts, the sensor frames' counters); `mrrig review --can-log` checks it and
`--html` writes one file with the figure embedded."""

from __future__ import annotations

import base64
import json
import re
import subprocess
import sys

import cantools
import pytest

from mrrig.offline.review import read_recording
from mrrig.rigio.canlog import check_bus_log, read_bus_log
from tests.conftest import REPO, rig_config, start, stop
from tests.stall_proof import explain
from tests.test_lifecycle_errors import NO_MODEL, mrrig, one_error_line

pytestmark = pytest.mark.process


def _run(tmp_path, bridge, log_name: str):
    cfg = rig_config(tmp_path, bridge, None, **NO_MODEL)
    rrd = tmp_path / f"{log_name}.rrd"
    log = tmp_path / log_name
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "mrrig",
            "run",
            "--config",
            str(cfg),
            "--duration",
            "3",
            "--arm",
            "--record",
            str(rrd),
            "--can-log",
            str(log),
            "--summary-json",
            str(tmp_path / f"{log_name}.json"),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    # 1: ended in FAULT; the fixture proves each fault a stall of the machine's (the bus log
    # holds every frame either way)
    assert proc.returncode in (0, 1), proc.stdout + proc.stderr
    assert f"bus log: {log}" in proc.stdout
    return rrd, log, json.loads((tmp_path / f"{log_name}.json").read_text())


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two 3 s runs against firmware_sim: one with a .blf, one with a candump .log. A fault
    of a run (a stall of this machine: no sensor frame within the timeout) must lie in a stall
    the simulator measured (tests/stall_proof.py); any other fails the module."""
    from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge

    tmp = tmp_path_factory.mktemp("buslog")
    port = find_free_port()
    bridge_proc = start_bridge(port)
    channel = f"ws://127.0.0.1:{port}/"
    stats = tmp / "sim.json"
    sim = start(
        ["-m", "firmware_sim", "--config", "configs/sim.toml", "-c", channel, "--measure-echo",
         "--stats", str(stats)]
    )  # fmt: skip
    try:
        runs = {name: _run(tmp, channel, name) for name in ("run.blf", "run.log")}
    finally:
        stop(sim)
        stop_bridge(bridge_proc)
    sim_stats = json.loads(stats.read_text())
    for _, _, summary in runs.values():
        explain(sim_stats, summary["faults"], summary["clock_t0_s"], summary["kernel_stalls"])
    return {name: (rrd, log) for name, (rrd, log, _) in runs.items()}


@pytest.mark.parametrize("name", ["run.blf", "run.log"])
def test_a_bus_log_decodes_with_cantools_and_matches_the_recording(runs, name):
    rrd, log = runs[name]
    rec = read_recording(rrd)
    db = cantools.database.load_file(str(REPO / "configs/mrrig.dbc"))
    names = {}
    sensor_counters, echoes = [], []
    for msg in read_bus_log(log):
        spec = db.get_message_by_frame_id(msg.arbitration_id)
        values = spec.decode(msg.data)
        names[spec.name] = names.get(spec.name, 0) + 1
        if spec.name == "RigSensors":
            assert msg.is_rx
            sensor_counters.append(values["E2E_Counter"])
        elif spec.name == "DamperCommand":
            assert not msg.is_rx
            echoes.append(values["SensorCounterEcho"])
    s = rec.summary
    assert names["RigSensors"] == s["sensor_frames_valid"] + s["sensor_frames_invalid"] > 1000
    assert names["DamperCommand"] == s["commands_sent"]
    assert names["ActuatorCommand"] >= 2  # the motion at start and its stop at the end
    assert s["can_log_dropped"] == 0
    # every recorded frame's counter is in the log, in order; the commands echo them
    check = check_bus_log(log, rec.samples, rec.summary)
    assert check.ok, check.text()
    assert check.counters_in_order and rec.samples.size > 1000
    assert set(echoes) <= set(range(16)) and len(echoes) >= rec.samples.size - 5


def test_review_checks_the_bus_log_and_writes_a_one_file_report(runs, tmp_path):
    rrd, log = runs["run.blf"]
    html = tmp_path / "report.html"
    proc = mrrig(
        "-q", "review", str(rrd), "--can-log", str(log), "--html", str(html), timeout_s=300
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "matches the recording" in proc.stdout
    text = html.read_text()
    assert "constant" in text and "Et" in text  # the title: controller and Et
    png = base64.b64decode(re.search(r"data:image/png;base64,([A-Za-z0-9+/=]+)", text)[1])
    assert png.startswith(b"\x89PNG") and len(png) > 20_000
    assert "<h2>Bus log</h2>" in text and "RigSensors" in text


def test_review_with_the_bus_log_of_another_run_says_mismatch(runs):
    rrd, _ = runs["run.blf"]
    _, other = runs["run.log"]
    proc = mrrig("-q", "review", str(rrd), "--can-log", str(other), timeout_s=300)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "MISMATCH" in proc.stdout


def test_an_unknown_bus_log_format_stops_start_up(tmp_path):
    cfg = rig_config(tmp_path, "ws://127.0.0.1:1/", None, **NO_MODEL)
    line = one_error_line(mrrig("run", "--config", str(cfg), "--can-log", "x.txt"))
    assert "unknown bus log format '.txt'" in line


# asammdf as absent, whether or not this environment has it: an import of a module that
# sys.modules holds as None fails, and importlib.util.find_spec gives None
_WITHOUT_ASAMMDF = (
    "import sys; sys.modules['asammdf'] = None; from mrrig.cli.main import main; sys.exit(main())"
)


def test_an_mf4_bus_log_without_asammdf_stops_start_up_before_anything_starts(tmp_path):
    cfg = rig_config(tmp_path, "ws://127.0.0.1:1/", None, **NO_MODEL)
    record, bus_log = tmp_path / "rec" / "run.rrd", tmp_path / "logs" / "run.mf4"
    args = ["--can-log", str(bus_log), "--record", str(record), "--no-telemetry"]
    proc = subprocess.run(
        [sys.executable, "-c", _WITHOUT_ASAMMDF, "run", "--config", str(cfg), *args],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    line = one_error_line(proc)
    assert "asammdf" in line and ".mf4" in line and str(bus_log) in line, line
    assert not record.parent.exists() and not bus_log.parent.exists()  # nothing started
