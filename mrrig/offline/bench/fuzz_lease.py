"""`mrrig bench fuzz`'s clients killed while armed (issue 40): a client that holds the rig
(`mrrig arm --hold`, renewing its lease) is SIGKILLed at a random moment; the daemon must
leave ARMED within the lease's timeout. A rig still ARMED `SLACK_S` beyond it is an armed
stretch without a live lease (the count must be 0)."""

from __future__ import annotations

import random
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

KILL_EVERY_S = 15.0  # a killed client this often in the fuzz phase
HOLD_S = (0.5, 4.0)  # how long the client holds the rig armed before it is killed
ARM_WAIT_S = 20.0  # a client's start-up and its arm, on a loaded machine
# the status the bench reads is the loop's latest (sent every 0.1 s, cached up to 0.5 s by the
# telemetry process), read every POLL_S
SLACK_S = 1.0
POLL_S = 0.05

Ask = Callable[[dict[str, Any]], dict[str, Any] | None]


@dataclass
class KilledClients:
    kills: int = 0
    never_armed: int = 0  # clients that did not get the rig armed (a fault in the way)
    armed_without_lease: int = 0  # still ARMED beyond the lease's timeout + SLACK_S
    left_armed_s: list[float] = field(default_factory=list)  # kill -> the rig not ARMED

    def counts(self) -> dict[str, Any]:
        return {
            "clients_killed": self.kills,
            "clients_never_armed": self.never_armed,
            "armed_without_lease": self.armed_without_lease,
            "left_armed_after_kill_s_max": max(self.left_armed_s, default=None),
        }


def _state(ask: Ask) -> str | None:
    return ((ask({"cmd": "status"}) or {}).get("status") or {}).get("state")


def client_arms(ask: Ask, cmd: list[str], wait_s: float) -> subprocess.Popen | None:
    """From IDLE: the client `cmd` (an mrrig command) started; it once the rig is ARMED
    within `wait_s`, else None (the client ended or did not arm it: killed, waited for)."""
    ask({"cmd": "disarm"})
    ask({"cmd": "reset"})
    proc = subprocess.Popen(
        [sys.executable, "-m", "mrrig", "-q", *cmd],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + wait_s
    while _state(ask) != "ARMED":
        if proc.poll() is not None or time.monotonic() > deadline:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
            return None
        time.sleep(POLL_S)
    return proc


def client_config(endpoints: list[str], work: Path) -> Path:
    """A Zenoh client config file (127.0.0.1, scouting off) for the killed clients."""
    import json

    path = work / "zenoh-client.json5"
    conf = {
        "mode": "client",
        "connect": {"endpoints": endpoints},
        "scouting": {"multicast": {"enabled": False}},
    }
    path.write_text(json.dumps(conf))
    return path


def kill_a_client(
    ask: Ask,
    rig: str,
    zenoh_config: Path,
    lease_timeout_s: float,
    rng: random.Random,
    result: KilledClients,
) -> None:
    """From IDLE: `mrrig arm --hold` arms the rig and renews its lease; SIGKILL after a random
    HOLD_S; then how long the rig stays ARMED."""
    cmd = ["arm", "--rig", rig, "--hold", "--zenoh-config", str(zenoh_config)]
    proc = client_arms(ask, cmd, ARM_WAIT_S)
    if proc is None:
        result.never_armed += 1
        return
    try:
        time.sleep(rng.uniform(*HOLD_S))
        proc.kill()
        t_kill = time.monotonic()
        result.kills += 1
        while _state(ask) == "ARMED":
            if time.monotonic() - t_kill > lease_timeout_s + SLACK_S:
                result.armed_without_lease += 1
                ask({"cmd": "disarm"})
                return
            time.sleep(POLL_S)
        result.left_armed_s.append(time.monotonic() - t_kill)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
