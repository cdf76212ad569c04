"""Errors of the set-up a rig's operator meets (a bus that is not there, a port in use, no
daemon, a telemetry process that cannot start: tests/test_telemetry_start_failure.py, a process
module): each is one `error:` line with what to do, exit code 2, no traceback and no Rust
source path; a closed pipe ends quietly. No rig runs here: the machine is held shared."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest

from mrrig.rigio.canbus.bus import find_free_port
from tests.conftest import REPO, rig_config, zenoh_configs

NO_MODEL = {"controller": {"name": "constant", "current_a": 0.5}}


def mrrig(*args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mrrig", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )


def one_error_line(proc: subprocess.CompletedProcess) -> str:
    """The run's error line, checked: exit 2, one `error:` line, no traceback, no Rust path."""
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2, out
    assert "Traceback" not in out and ".rs:" not in out, out
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, out
    others = [line for line in proc.stderr.splitlines() if line.strip() and " INFO " not in line]
    assert others == errors, out  # nothing but progress logs besides the one line
    return errors[0]


def test_run_with_no_bridge_names_the_bridge_command(tmp_path):
    port = find_free_port()
    cfg = rig_config(tmp_path, f"ws://127.0.0.1:{port}/", None, **NO_MODEL)
    line = one_error_line(mrrig("run", "--config", str(cfg), "--duration", "1"))
    assert f"mrrig bridge --port {port}" in line


def test_run_on_a_socketcan_bus_that_is_not_there_says_what_to_check(tmp_path):
    cfg = rig_config(tmp_path, "ws://127.0.0.1:1/", None, **NO_MODEL)
    line = one_error_line(mrrig("run", "--config", str(cfg), "-i", "socketcan", "-c", "mrrigtest0"))
    assert "channel='mrrigtest0'" in line
    # this machine's kernel has no CAN at all; on one with CAN the interface is missing
    assert "no SocketCAN" in line or "ip link set up mrrigtest0" in line


def test_the_simulator_with_no_bridge_says_so_in_one_line():
    port = find_free_port()
    proc = mrrig("sim", "-c", f"ws://127.0.0.1:{port}/", "--duration", "1")
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if " INFO " not in ln and ln.strip()]
    assert len(lines) == 1 and f"mrrig bridge --port {port}" in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def test_bridge_on_a_port_in_use(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        line = one_error_line(mrrig("bridge", "--port", str(taken.getsockname()[1])))
    assert "already in use" in line and "mrrig bridge --port" in line


def test_status_without_a_daemon(tmp_path):
    _, client, _ = zenoh_configs(tmp_path)
    line = one_error_line(mrrig("status", "--zenoh-config", str(client), "--timeout", "1"))
    assert "is the daemon running?" in line


def test_a_closed_pipe_is_quiet_and_the_figure_is_still_written(tmp_path):
    from tests.test_recording import run_events, synthetic_run, write_recording

    rrd = tmp_path / "run.rrd"
    s = synthetic_run(1000)
    write_recording(rrd, s, run_events(s), {"frames_received": s.size})
    png = tmp_path / "run.png"
    r, w = os.pipe()
    os.close(r)  # the reader is gone before the first line
    with open(w, "w") as stdout:
        proc = subprocess.run(
            [sys.executable, "-m", "mrrig", "-q", "review", str(rrd), "--plot", str(png)],
            cwd=REPO,
            stdout=stdout,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
            check=False,
        )
    assert proc.returncode == 141, proc.stderr
    assert proc.stderr == ""
    assert png.stat().st_size > 10_000


@pytest.mark.parametrize(
    "args",
    [["status", "--debug", "--help"], ["-q", "status", "--help"], ["status", "-q", "--help"]],
)
def test_global_options_before_or_after_the_command(args):
    proc = mrrig(*args)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage: mrrig status")


def test_version_and_help_show_defaults():
    proc = mrrig("--version")
    assert proc.returncode == 0 and proc.stdout.startswith("mrrig ")
    assert mrrig("sim", "--help").stdout.startswith("usage: mrrig sim")
    run_help = mrrig("run", "--help").stdout
    assert "-i INTERFACE, --interface INTERFACE, --bus-interface INTERFACE" in run_help
    assert "-c CHANNEL, --channel CHANNEL, --bus-channel CHANNEL" in run_help
    assert "(default: 2.0)" in mrrig("status", "--help").stdout


def test_old_bus_option_names_still_work(tmp_path):
    port = find_free_port()
    cfg = rig_config(tmp_path, "ws://127.0.0.1:1/", None, **NO_MODEL)
    channel = f"ws://127.0.0.1:{port}/"
    line = one_error_line(mrrig("run", "--config", str(cfg), "--bus-channel", channel))
    assert f"mrrig bridge --port {port}" in line
