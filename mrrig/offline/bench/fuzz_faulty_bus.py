"""`mrrig bench fuzz`'s faulty bus and lost runs (issue 40).

A faulty bus: a real client (`mrrig test`, a one-step plan holding the rig armed at 0.5 A on
a sine) arms the rig; then the simulator is held up 0.1 s every 0.6 s (SIGSTOP, SIGCONT: a
sensor timeout, a transport fault, each time). The client may re-arm at most 3 times in any
10 s (`mrrig.rigio.rearm`): its step must end aborted `faulty bus`, not pass on a rig reset
every second. A step that passed, or ended for another reason, counts as `faulty_bus_not_aborted`
(the count must be 0).

Lost runs: every daemon start of the bench records to its own .rrd; once the rig is stopped,
the journals beside the recordings are replayed (`mrrig.catalog.journal.replay`) and each
recording must be in the bench's catalog (`runs_missing_from_catalog` must be 0).
"""

from __future__ import annotations

import os
import signal
import subprocess
import textwrap
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mrrig.offline.bench.fuzz_lease import client_arms

FAULTY_EVERY_S = 60.0  # a faulty-bus episode this often in the fuzz phase (the first at half)
STALL_S, STALL_EVERY_S = 0.1, 0.6  # the simulator held up this long, this often
MAX_STALLS = 30  # the step is aborted at the 4th fault: 30 leave it room on a loaded machine
ARM_WAIT_S = 30.0  # the client's start-up and its arm, on a loaded machine
END_WAIT_S = 60.0  # the step's end: disarm, catalog row, report

Ask = Callable[[dict[str, Any]], dict[str, Any] | None]

_PLAN = """\
    [plan]
    name = "fuzz faulty bus"
    [[step]]
    name = "faulty bus"
    duration_s = 30
    settle_s = 0.5
    actuator = { waveform = "sine", amplitude_m = 0.005, frequency_hz = 1.0 }
    controller = { name = "constant", current_a = 0.5 }
    reference = { kind = "constant" }
    criteria = { faults = "transport" }
    """


@dataclass
class FaultyBus:
    episodes: int = 0
    aborted: int = 0  # steps aborted `faulty bus`, as they must be
    not_aborted: list[str] = field(default_factory=list)  # how the others ended
    never_armed: int = 0  # clients that did not get the rig armed (a fault in the way)
    stalls: int = 0

    def counts(self) -> dict[str, Any]:
        return {
            "faulty_bus_episodes": self.episodes,
            "faulty_bus_aborted": self.aborted,
            "faulty_bus_not_aborted": len(self.not_aborted),
            "faulty_bus_not_aborted_how": self.not_aborted[:5],
            "faulty_bus_never_armed": self.never_armed,
            "faulty_bus_stalls": self.stalls,
        }


def _step_outcome(junit: Path) -> str:
    """The step's verdict and reason from the client's JUnit report."""
    if not junit.is_file():
        return "no JUnit report"
    case = ET.parse(junit).find(".//testcase")
    if case is None:
        return "no testcase in the JUnit report"
    for kind in ("error", "failure"):
        node = case.find(kind)
        if node is not None:
            return f"{kind}: {node.get('message', '')}"
    return "passed"


def faulty_bus_step(
    ask: Ask, rig: str, zenoh_config: Path, sim_pid: int, work: Path, result: FaultyBus
) -> None:
    """From IDLE: `mrrig test` arms the rig for its step; the simulator is stalled every
    STALL_EVERY_S until the client ends (or MAX_STALLS); its step must be aborted `faulty
    bus`."""
    n = result.episodes
    result.episodes += 1
    plan, junit = work / f"faulty-bus-{n}.toml", work / f"faulty-bus-{n}.xml"
    plan.write_text(textwrap.dedent(_PLAN))
    cmd = ["test", str(plan), "--rig", rig, "--zenoh-config", str(zenoh_config)]
    proc = client_arms(ask, [*cmd, "--junit", str(junit)], ARM_WAIT_S)
    if proc is None:
        result.never_armed += 1
        ask({"cmd": "disarm"})
        return
    try:
        time.sleep(STALL_EVERY_S)
        for _ in range(MAX_STALLS):
            if proc.poll() is not None:
                break
            os.kill(sim_pid, signal.SIGSTOP)
            try:
                time.sleep(STALL_S)
            finally:
                os.kill(sim_pid, signal.SIGCONT)
            result.stalls += 1
            time.sleep(STALL_EVERY_S - STALL_S)
        try:
            proc.wait(timeout=END_WAIT_S)
        except subprocess.TimeoutExpired:
            result.not_aborted.append(f"the client ran on {END_WAIT_S:g} s after the stalls")
            return
        outcome = _step_outcome(junit)
        if outcome.startswith("error: ") and "faulty bus" in outcome:
            result.aborted += 1
        else:
            result.not_aborted.append(outcome[:200])
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        ask({"cmd": "disarm"})


def runs_missing(recordings: list[Path], catalog: Path) -> list[str]:
    """The recordings whose run is not in `catalog`, once the journals beside them are
    replayed (a run is never lost: in the catalog, or journalled and replayed here)."""
    from mrrig.catalog import find_runs
    from mrrig.catalog.journal import replay

    folders = {p.parent for p in recordings}
    for folder in folders:
        replay(folder, str(catalog))
    known = set()
    if catalog.is_file():
        known = {Path(r.recording_path).resolve() for r in find_runs(catalog) if r.recording_path}
    return [p.name for p in recordings if p.is_file() and p.resolve() not in known]
