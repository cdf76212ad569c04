"""Issue 42's acceptance: the tutorial (docs/tutorial.md) walked in a fresh clone of this
checkout's commit, as a lab would on its first day: its own DBC (Motorola signals, no E2E), a
minimal config, characterize on the simulator, train, deploy by `set_model`, a four-step
campaign; then `mrrig runs --specimen` lists each step with its own Et, the model's sha256 as
deployed and a checked recording, and `mrrig export --run ID` holds that step's rows only.

Every command is the clone's CLI in a process of its own (cwd the clone, its code first on the
path, its default catalog `recordings/catalog.sqlite`); kept short: a 6-run matrix, the fastest
training, 3 s steps."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from mrrig.rigio.canbus.bus import find_free_port
from tests.conftest import REPO, stop, wait_until, zenoh_configs

pytestmark = pytest.mark.process

SPECIMEN = "SN-MR-042"
CAMPAIGN = "SN-MR-042-day1"
RIG = "lab"

# the lab's firmware: its own IDs, big-endian (Motorola) signals, mm, kN and mA, no counter or
# CRC, 500 Hz
DBC = """VERSION "a lab rig: Motorola signals, no E2E, 500 Hz"

NS_ :
\tCM_
\tBA_DEF_
\tBA_
\tVAL_
\tBA_DEF_DEF_

BS_:

BU_: RIG HOST

BO_ 528 Sensors: 8 RIG
 SG_ Position : 7|24@0- (0.001,0) [-50|50] "mm" HOST
 SG_ Load : 31|24@0- (1E-005,0) [-80|80] "kN" HOST
 SG_ Enabled : 55|1@0+ (1,0) [0|1] "" HOST
 SG_ EStop : 54|1@0+ (1,0) [0|1] "" HOST
 SG_ Fault : 53|1@0+ (1,0) [0|1] "" HOST
 SG_ Coil : 51|12@0+ (1,0) [0|4095] "mA" HOST

BO_ 529 Command: 8 HOST
 SG_ Active : 7|1@0+ (1,0) [0|1] "" RIG
 SG_ Current : 15|16@0+ (0.1,0) [0|5000] "mA" RIG
 SG_ Force : 31|24@0- (1E-005,0) [-80|80] "kN" RIG

BO_ 530 Motion: 8 HOST
 SG_ Waveform : 7|4@0+ (1,0) [0|3] "" RIG
 SG_ Amplitude : 15|16@0+ (0.01,0) [0|655.35] "mm" RIG
 SG_ Frequency : 31|16@0+ (0.001,0) [0|65.535] "Hz" RIG

BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 528 2;
BA_ "GenMsgCycleTime" BO_ 529 2;
BA_ "GenMsgCycleTime" BO_ 530 100;
VAL_ 530 Waveform 3 "HOLD" 2 "RANDOM" 1 "SINE" 0 "STOP" ;
"""

# the minimal config: the rig, the bus, the profile (roles left out are absent), the loop's
# tolerances for the simulator, and the constant controller until a model is deployed (network
# inversion, the default, needs a model file)
CONFIG = """[rig]
name = "lab"
specimen = "SN-MR-042"
operator = "walk"

[bus]
interface = "remote"
channel = "{channel}"

[can]
dbc = "lab-rig.dbc"

[can.signals]
displacement = "Sensors.Position"
force = "Sensors.Load"
actuator_enabled = "Sensors.Enabled"
estop = "Sensors.EStop"
firmware_fault = "Sensors.Fault"
coil_current = "Sensors.Coil"
command_mode = "Command.Active"
command_setpoint = "Command.Current"
desired_force = "Command.Force"
actuator_waveform = "Motion.Waveform"
actuator_amplitude = "Motion.Amplitude"
actuator_frequency = "Motion.Frequency"

[loop]
timeout_periods = 10    # the simulator over the Python bridge, as configs/rig.toml: it stalls
max_frame_age_s = 0.01  # for ms on a busy machine (the defaults are a real bus's 3 and 1 period)

[controller]
name = "constant"
"""

MATRIX = """[matrix]
amplitudes_m = [0.010, 0.020]
freqs_hz = [2.0]
currents_a = [0.0, 0.9, 1.8]
settle_s = 0.6
duration_s = 0.5
attempts = 3

[output]
directory = "recordings/characterization"
"""

_STEP = """
[[step]]
name = "{name}"
duration_s = 3
settle_s = 0.7
actuator = {{ waveform = "sine", amplitude_m = {amplitude_m}, frequency_hz = {freq_hz} }}
controller = {controller}
reference = {{ kind = "bouc_wen", preset = "rig-current", current_a = 0.8, current_amp_a = 0.5, \
current_freq_hz = 0.5 }}
criteria = {{ faults = "transport", peak_current_a_max = 2.0 }}
"""
STEPS = [
    ("passive 0.8 A", 0.010, 1.0, '{ name = "constant", current_a = 0.8 }'),
    ("inversion 10 mm 1 Hz", 0.010, 1.0, '{ name = "network_inversion" }'),
    ("inversion 15 mm 1 Hz", 0.015, 1.0, '{ name = "network_inversion" }'),
    ("inversion 10 mm 2 Hz", 0.010, 2.0, '{ name = "network_inversion" }'),
]
PLAN = '[plan]\nname = "first-day"\nrig = "lab"\n' + "".join(
    _STEP.format(name=n, amplitude_m=a, freq_hz=f, controller=c) for n, a, f, c in STEPS
)


def _clone(dest: Path) -> Path:
    """A fresh clone of this checkout's commit: the committed files only (no models/, no
    recordings, nothing ignored or uncommitted)."""
    head = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True, check=True
    ).stdout.strip()
    subprocess.run(["git", "clone", "-q", "--no-checkout", str(REPO), str(dest)], check=True)
    subprocess.run(["git", "-C", str(dest), "checkout", "-q", head], check=True)
    return dest


class Clone:
    """The clone's `mrrig` in processes of their own, in the clone, its code first."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.env = dict(os.environ, PYTHONPATH=str(root), PYTHONUNBUFFERED="1")
        self.env.pop("MRRIG_CATALOG", None)  # the tutorial's catalog: recordings/catalog.sqlite
        self.background: list[subprocess.Popen] = []

    def run(self, *args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "mrrig", *args],
            cwd=self.root, env=self.env, capture_output=True, text=True, timeout=timeout_s,
        )  # fmt: skip

    def ok(self, *args: str, timeout_s: float = 60.0) -> str:
        p = self.run(*args, timeout_s=timeout_s)
        assert p.returncode == 0, f"mrrig {' '.join(args)}: rc {p.returncode}\n{p.stdout}{p.stderr}"
        return p.stdout

    def start(self, *args: str, log: str) -> subprocess.Popen:
        out = open(self.root / log, "w")  # noqa: SIM115 - closed with the test's tmp_path
        p = subprocess.Popen(
            [sys.executable, "-m", "mrrig", *args],
            cwd=self.root, env=self.env, stdout=out, stderr=subprocess.STDOUT,
        )  # fmt: skip
        self.background.append(p)
        return p

    def stop_all(self) -> None:
        for p in reversed(self.background):
            stop(p)


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git to clone the checkout")
def test_the_tutorial_in_a_fresh_clone_leaves_a_test_record(tmp_path):
    t0 = time.monotonic()
    laps: list[str] = []

    def lap(what: str) -> None:
        laps.append(f"{what} {time.monotonic() - t0:.1f} s")

    lab = Clone(_clone(tmp_path / "clone"))
    root = lab.root
    assert not (root / "models").exists()  # nothing but the committed files

    # 1. the rig: the lab's DBC and a minimal config; the profile checks out
    port = find_free_port()
    channel = f"ws://127.0.0.1:{port}/"
    (root / "lab").mkdir()
    (root / "lab/lab-rig.dbc").write_text(DBC)
    (root / "lab/lab.toml").write_text(CONFIG.format(channel=channel))
    (root / "lab/matrix.toml").write_text(MATRIX)
    (root / "lab/first-day.toml").write_text(PLAN)
    daemon_z, client_z, _ = zenoh_configs(tmp_path)
    check = lab.ok("dbc", "check", "--config", "lab/lab.toml")
    assert "lab-rig.dbc: ok" in check and "no CRC" in check

    try:
        # the simulator speaks the lab's profile (the daemon's config) over a bridge
        lab.start("bridge", "--port", str(port), log="bridge.log")
        assert wait_until(lambda: _listening(port), timeout_s=15.0), "the bridge never listened"
        lab.start("sim", "--config", "configs/sim.toml", "--rig-config", "lab/lab.toml",
                  "-c", channel, log="sim.log")  # fmt: skip

        lap("clone+check")
        # 2. characterize (the tool runs the loop itself)
        out = lab.ok(
            "characterize", "--config", "lab/matrix.toml", "--rig-config", "lab/lab.toml",
            "--no-telemetry", timeout_s=90,
        )  # fmt: skip
        assert "characterization complete: 6 runs" in out
        matrix = "recordings/characterization/matrix.csv"

        lap("characterize")
        # 3. train: two models, the second the one deployed by set_model
        fast = ["--features", "manual", "--no-supervised", "--epochs", "30", "--restarts", "1",
                "--cv-folds", "0", "--hidden", "10"]  # fmt: skip
        lab.ok("train", matrix, "--out", "models/lab-forward.json", *fast, timeout_s=90)
        lab.ok("train", matrix, "--out", "models/lab-forward-v2.json", "--seed", "1", *fast,
               timeout_s=90)  # fmt: skip
        deployed = _sha256(root / "models/lab-forward-v2.json")
        assert deployed != _sha256(root / "models/lab-forward.json")

        lap("train")
        # 4. the daemon, then the model: set_controller from constant, a better one by set_model
        daemon = lab.start(
            "run", "--config", "lab/lab.toml", "--zenoh-config", str(daemon_z), log="daemon.log"
        )
        z = ["--rig", RIG, "--zenoh-config", str(client_z)]
        assert wait_until(
            lambda: lab.run("status", *z, "--timeout", "1").returncode == 0, timeout_s=60.0
        ), (root / "daemon.log").read_text()
        lab.ok("control", *z, json.dumps({"cmd": "set_controller", "name": "network_inversion",
                                           "model": "models/lab-forward.json"}))  # fmt: skip
        lab.ok(
            "control", *z, json.dumps({"cmd": "set_model", "path": "models/lab-forward-v2.json"})
        )
        status = lab.ok("status", *z)
        assert f"model models/lab-forward-v2.json (sha256 {deployed[:12]})" in status, status
        assert f"specimen {SPECIMEN}" in status

        lap("daemon+deploy")
        # 5. the campaign
        p = lab.run("test", "lab/first-day.toml", *z, "--campaign", CAMPAIGN,
                    "--html", "day1.html", timeout_s=120)  # fmt: skip
        assert p.returncode in (0, 1), p.stdout + p.stderr  # a step's verdict is not the point
        assert "plan first-day" in p.stdout and (root / "day1.html").is_file()
        daemon.send_signal(2)  # Ctrl-C: the daemon's run is registered with its recording closed
        assert daemon.wait(timeout=30) == 0, (root / "daemon.log").read_text()
    finally:
        lab.stop_all()

    lap("plan")
    # 6. the record: each step a run with its own Et, the model as deployed, its recording checked
    listed = lab.ok("runs", "--specimen", SPECIMEN).splitlines()
    for name, _, _, controller in STEPS:
        (line,) = [line for line in listed if f"first-day/{name}" in line]
        assert (deployed[:12] in line) == ("network_inversion" in controller), line
    runs = json.loads(lab.ok("runs", "--specimen", SPECIMEN, "--json"))
    steps = [r for r in runs if r["campaign"] == CAMPAIGN]
    # the daemon's own run, the one with a recording (the matrix's runs are left out)
    (own,) = [r for r in runs if r["plan"] is None and r["recording_path"] is not None]
    assert [r["step"] for r in steps] == [name for name, *_ in STEPS]
    ets = [r["et"] for r in steps]
    assert all(et is not None and 0 < et < 10 for et in ets), ets
    assert len({round(et, 6) for et in [*ets, own["et"]]}) == 5, (ets, own["et"])  # each its own
    assert steps[0]["controller"] == "constant" and steps[0]["model_sha256"] is None
    for r in steps[1:]:
        assert r["controller"] == "network_inversion"
        assert (r["model_path"], r["model_sha256"]) == ("models/lab-forward-v2.json", deployed)
    for r in steps:
        assert (r["specimen"], r["rig"], r["operator"] is not None) == (SPECIMEN, RIG, True)
        assert r["dbc_sha256"] == _sha256(root / "lab/lab-rig.dbc")
        assert r["recording_path"] == own["recording_path"]  # the file, as the daemon's run
        assert r["recording_sha256"] == own["recording_sha256"] is not None
        shown = lab.ok("runs", "show", r["run_id"][:8])  # exit 1 where unchecked or changed
        assert "recording             unchanged" in shown, shown

    lap("runs")
    # the export of one step: its rows only
    step = steps[2]
    lab.ok("export", "--run", step["run_id"][:8], "--to", "parquet", "--out", "step3.parquet")
    df = pd.read_parquet(root / "step3.parquet")
    start = pd.Timestamp(step["started_utc"])
    end = pd.Timestamp(step["ended_utc"])
    assert start <= df["utc"].min() and df["utc"].max() <= end
    span_s = (end - start).total_seconds()
    assert 0.8 * span_s * 500 <= len(df) <= span_s * 500 + 50, (len(df), span_s)
    assert len(df) < own["duration_s"] * 500 / 2  # not the daemon's whole recording
    lap("export")
    print(f"walkthrough: {', '.join(laps)}; step Et {ets}, the daemon's {own['et']}")
