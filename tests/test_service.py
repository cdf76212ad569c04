"""The system service: the shipped units pass `systemd-analyze verify`, and the daemon speaks
systemd's notify protocol (READY=1, WATCHDOG=1 at half of WatchdogSec, STOPPING=1 on SIGTERM)
to a notify socket of the test's own."""

from __future__ import annotations

import shutil
import signal
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mrrig.rigio.sdnotify import Notifier
from tests.conftest import REPO

UNITS = sorted((REPO / "configs" / "systemd").glob("*.service"))
INSTALL_DIR = "/opt/mrrig"


@pytest.mark.parametrize("unit", UNITS, ids=lambda p: p.name)
def test_systemd_analyze_verify_passes_on_the_shipped_unit(unit: Path, tmp_path: Path):
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze not installed (Debian package systemd; .ci/run installs it)")
    # the unit as installed, with this checkout in place of /opt/mrrig (verify checks that
    # ExecStart's program exists)
    installed = tmp_path / unit.name
    installed.write_text(unit.read_text().replace(INSTALL_DIR, str(REPO)))
    name = installed.name.replace("@.service", "@rig.service")
    proc = subprocess.run(
        [analyze, "verify", name], cwd=tmp_path, capture_output=True, text=True, timeout=60
    )
    # verify exits 0 on a mistyped value or key and only says so: its output must be empty
    assert proc.returncode == 0 and not (proc.stdout + proc.stderr).strip(), proc.stderr


def test_the_unit_has_what_the_loop_needs():
    text = (REPO / "configs/systemd/mrrig@.service").read_text()
    for line in (
        "Type=notify",
        "AmbientCapabilities=CAP_SYS_NICE CAP_IPC_LOCK",
        "LimitMEMLOCK=infinity",
        "Restart=on-failure",
        "KillSignal=SIGTERM",
        "ExecStart=/opt/mrrig/.venv/bin/mrrig run --config configs/%i.toml",
    ):
        assert line in text.splitlines(), line
    assert any(line.startswith("WatchdogSec=") for line in text.splitlines())


def _notify_socket(tmp_path: Path) -> tuple[socket.socket, Path]:
    path = tmp_path / "notify"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(0.2)
    return sock, path


def _daemon_config(tmp_path: Path) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(
        """
[rig]
name = "svc"
[bus]
interface = "virtual"
channel = "svc-test"
[loop]
realtime = false
[controller]
name = "constant"
current_a = 0.5
[telemetry]
enabled = false
[recording]
enabled = false
"""
    )
    return path


@pytest.mark.process
def test_daemon_notifies_ready_pets_the_watchdog_and_stops_on_sigterm(tmp_path: Path):
    sock, path = _notify_socket(tmp_path)
    watchdog_s = 0.2  # WatchdogSec=200ms: WATCHDOG=1 every 100 ms
    env = {
        "PATH": "/usr/bin:/bin",
        "NOTIFY_SOCKET": str(path),
        "WATCHDOG_USEC": str(int(watchdog_s * 1e6)),
        "PYTHONUNBUFFERED": "1",
    }
    proc = subprocess.Popen(
        [sys.executable, "-m", "mrrig", "run", "--config", str(_daemon_config(tmp_path))],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    messages: list[tuple[float, str]] = []
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                data = sock.recv(4096)
            except TimeoutError:
                continue
            messages.append((time.monotonic(), data.decode()))
            ready = [t for t, m in messages if m.startswith("READY=1")]
            if ready and time.monotonic() - ready[0] > 3.0:
                break
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
        sock.settimeout(1.0)
        try:
            messages.append((time.monotonic(), sock.recv(4096).decode()))
        except TimeoutError:
            pass
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        sock.close()
    kinds = [m.split("\n")[0] for _, m in messages]
    assert kinds[0] == "READY=1", kinds[:3]
    assert kinds[-1] == "STOPPING=1", kinds[-3:]
    assert proc.returncode == 0, out
    pets = [t for t, m in messages if m == "WATCHDOG=1"]
    gaps = [b - a for a, b in zip(pets, pets[1:], strict=False)]
    print(f"{len(pets)} WATCHDOG=1, gap median {statistics.median(gaps) * 1e3:.0f} ms")
    # the loop turns at least every sensor timeout (20 ms here): a pet 100-120 ms after the last
    assert len(pets) >= 20
    assert 0.095 <= statistics.median(gaps) <= 0.13, gaps


def test_a_notifier_without_a_listener_never_raises_or_blocks(tmp_path: Path):
    n = Notifier(str(tmp_path / "nobody"), watchdog_usec=1000)
    t0 = time.perf_counter()
    for _ in range(100):
        n.pet()
        n.ready()
    assert time.perf_counter() - t0 < 0.5
    assert n.dropped > 0
    n.close()
    assert not Notifier(None, 1000).enabled  # not under systemd: nothing at all


def test_the_abstract_namespace_address(tmp_path: Path):
    name = f"mrrig-test-{time.monotonic_ns()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        n = Notifier("@" + name)
        n.ready("up")
        assert sock.recv(100) == b"READY=1\nSTATUS=up"
        n.close()
    finally:
        sock.close()


@pytest.mark.process
def test_the_router_notifies_ready_and_pets_its_watchdog(tmp_path: Path):
    from mrrig.rigio.canbus.bus import find_free_port

    sock, path = _notify_socket(tmp_path)
    conf = tmp_path / "router.json5"
    conf.write_text(
        f'{{mode: "router", listen: {{endpoints: ["tcp/127.0.0.1:{find_free_port()}"]}}, '
        "scouting: {multicast: {enabled: false}}}"
    )
    env = {"PATH": "/usr/bin:/bin", "NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "200000"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "mrrig", "router", "--config", str(conf)],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    kinds: list[str] = []
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and kinds.count("WATCHDOG=1") < 5:
            try:
                kinds.append(sock.recv(4096).decode().split("\n")[0])
            except TimeoutError:
                assert proc.poll() is None, proc.communicate()[0]
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
        sock.settimeout(1.0)
        kinds.append(sock.recv(4096).decode())
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        sock.close()
    assert kinds[0] == "READY=1" and kinds.count("WATCHDOG=1") >= 5, kinds
    assert kinds[-1] == "STOPPING=1" and proc.returncode == 0, out
