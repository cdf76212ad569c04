"""A live simulated rig for the tests that drive one through its control plane only:
firmware_sim and a rig daemon as separate processes over a python-can-remote bridge, the
daemon publishing telemetry on Zenoh (127.0.0.1, scouting off) for a client config of its own.
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from tests.conftest import rig_config, start, stop, zenoh_configs
from tests.test_lifecycle_errors import NO_MODEL


@dataclass(frozen=True)
class LiveRig:
    name: str
    client_z: Path  # the Zenoh config a client of this rig opens
    config: Path  # the daemon's config
    channel: str  # the bridge's python-can-remote URL
    daemon: subprocess.Popen  # stopped by the test where it reads what the daemon wrote


def wait_status(client_cfg: Path, timeout_s: float = 120.0, *, rig: str) -> dict:
    """The rig's status, asked again every 0.5 s until its daemon answers (start-up)."""
    from mrrig.rigio import client

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return client.status(rig, client_cfg, 1.0)["status"]
        except client.ClientError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


@contextmanager
def live_rig(
    tmp: Path,
    name: str,
    *,
    rate_hz: float = 20.0,
    sim_args: Sequence[str] = (),
    daemon_args: Sequence[str] = (),
    daemon_stdout: IO[str] | None = None,
    **sections: Any,
) -> Iterator[LiveRig]:
    """firmware_sim (configs/sim.toml) and `mrrig run` on a config for rig `name` (the constant
    controller unless `sections` say otherwise, telemetry at `rate_hz`), answering its status
    when this yields; both stopped, and the bridge, on the way out."""
    from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge

    port = find_free_port()
    bridge = start_bridge(port)
    channel = f"ws://127.0.0.1:{port}/"
    daemon_z, client_z, _ = zenoh_configs(tmp)
    telemetry = {"enabled": True, "zenoh_config": str(daemon_z), "rate_hz": rate_hz}
    cfg = rig_config(tmp, channel, None, rig={"name": name}, telemetry=telemetry,
                     **{**NO_MODEL, **sections})  # fmt: skip
    sim = start(["-m", "firmware_sim", "--config", "configs/sim.toml", "-c", channel, *sim_args])
    out = {} if daemon_stdout is None else {"stdout": daemon_stdout}
    daemon = start(["-m", "mrrig", "run", "--config", str(cfg), *daemon_args], **out)
    try:
        wait_status(client_z, rig=name)
        yield LiveRig(name, client_z, cfg, channel, daemon)
    finally:
        stop(daemon)
        stop(sim)
        stop_bridge(bridge)
