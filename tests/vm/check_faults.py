"""The VM check's faults (tests/vm/rig_on_vcan.sh): `mrrig run` ended in FAULT (exit 1). That
is expected where its faults are the sensor_timeout of the simulator's end (after the last
sensor frame) and, before it, only faults a stall measured inside the VM explains: the
simulator's own (`--stats`: the windows in which it ran late; software emulation stops the
whole guest now and then) or the daemon's, which the kernel measured (its summary's
`kernel_stalls`), or the daemon's CPU's, which tests/vm/cpu_stalls.py measured (the host
stopped that virtual CPU), by the rules of the process tests (tests/stall_proof.py). Any
other fault fails the check.

    python tests/vm/check_faults.py DAEMON_JSON SIM_JSON [CPU_STALLS_JSON]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout: tests.stall_proof

from tests.stall_proof import explain  # noqa: E402


def main(daemon_json: str, sim_json: str, cpu_json: str | None = None) -> int:
    s = json.loads(Path(daemon_json).read_text())
    faults = s["faults"]
    last = s["last_frame_t_s"]
    end = [f for f in faults if f.get("fault") == "sensor_timeout" and f["t"] >= last]
    during = [f for f in faults if f not in end]
    print(f"rig_on_vcan: faults {faults}; last sensor frame at t={last:.3f} s")
    if len(end) > 1 or not (end or during):
        print("rig_on_vcan: not the faults of a run that the simulator's end stopped")
        return 1
    if during:
        sim = json.loads(Path(sim_json).read_text())
        if cpu_json:  # the CPU's windows beside the simulator's, on the simulator's clock
            t0 = sim["clock_t0_s"]
            cpu = json.loads(Path(cpu_json).read_text())["stall_windows"]
            sim["stall_windows"] += [
                {**w, "start_s": w["start_s"] - t0, "end_s": w["end_s"] - t0} for w in cpu
            ]
        try:  # each explained, with its figure printed, or AssertionError naming the others
            explain(sim, during, s["clock_t0_s"], s.get("kernel_stalls"))
        except AssertionError as exc:
            print(f"rig_on_vcan: a fault while frames still came: {exc}")
            return 1
    print(
        "rig_on_vcan: exit 1 as documented: "
        + ("the simulator's end (sensor_timeout)" if end else "")
        + (" and " if end and during else "")
        + (f"{len(during)} fault(s) inside a stall measured in the VM" if during else "")
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
