"""Check a `candump -L` log of a sim + daemon run with the project's DBC.

Usage: python tests/vm/check_candump.py LOG --i-max 2.0 [--min-frames N]

Checks: every frame's CRC and counter valid (no repeated counter, no lost frame on the daemon's
messages), every valid RigSensors frame inside the daemon's run answered by exactly one
DamperCommand echoing its counter, in order, and no setpoint above the limit. Prints the counts
and the rate held; exits 1 on any failure.
"""

from __future__ import annotations

import argparse
import sys

from mrrig.rigio.canbus.codec import Codec

SENSORS, STATUS, COMMAND, ACTUATOR = 0x110, 0x111, 0x210, 0x211


def read_candump(path: str) -> list[tuple[float, int, bytes]]:
    frames = []
    for line in open(path):
        parts = line.split()
        if len(parts) < 3 or "#" not in parts[2]:
            continue
        fid, data = parts[2].split("#", 1)
        frames.append((float(parts[0].strip("()")), int(fid, 16), bytes.fromhex(data)))
    return frames


def check(frames, i_max: float, min_frames: int) -> list[str]:
    parser = Codec().parser()
    errors: list[str] = []
    seq = []  # ("S", counter) / ("C", echo)
    n = {"sensors": 0, "commands": 0, "active": 0, "status": 0, "actuator": 0}
    t_cmd = []
    for t, fid, data in frames:
        p = parser.parse(fid, data, t)
        if not p.ok:
            errors.append(f"t={t:.6f} 0x{fid:x}: {p.reason}")
            continue
        if p.lost_frames and fid in (COMMAND, ACTUATOR):
            errors.append(f"t={t:.6f} 0x{fid:x}: {p.lost_frames} frames lost (counter jump)")
        if fid == SENSORS:
            n["sensors"] += 1
            seq.append(("S", p.counter, t, None))
        elif fid == COMMAND:
            n["commands"] += 1
            n["active"] += p.values["Mode"] == 1
            t_cmd.append(t)
            seq.append(("C", int(p.values["SensorCounterEcho"]), t, int(p.values["Mode"])))
            if p.values["CurrentSetpoint"] > i_max + 1e-9:
                errors.append(f"t={t:.6f}: setpoint {p.values['CurrentSetpoint']} A > {i_max} A")
        elif fid == STATUS:
            n["status"] += 1
        elif fid == ACTUATOR:
            n["actuator"] += 1
    if not t_cmd:
        return errors + ["no DamperCommand at all"]
    first = next(i for i, e in enumerate(seq) if e[0] == "C")
    last = max(i for i, e in enumerate(seq) if e[0] == "C")
    starts = [i for i in range(first) if seq[i][0] == "S" and seq[i][1] == seq[first][1]]
    if not starts:
        return errors + ["the first command answers no sensor frame"]
    last_s = max(i for i, e in enumerate(seq) if e[0] == "S")
    # commands after the last sensor frame: its answer, then the daemon's own SAFE commands
    # once the simulator had stopped (sensor timeout, stop); those must be SAFE
    tail = [e for e in seq[last_s + 1 : last + 1] if e[0] == "C"]
    answer_to_last = tail[:1] if tail and tail[0][1] == seq[last_s][1] else []
    after = len(tail) - len(answer_to_last)
    window = seq[starts[-1] : last_s + 1] + answer_to_last
    sensors = [c for k, c, _, _ in window if k == "S"]
    echoes = [c for k, c, _, _ in window if k == "C"]
    mismatch = next(
        (i for i, (a, b) in enumerate(zip(sensors, echoes, strict=False)) if a != b), None
    )
    if mismatch is not None:
        errors.append(
            f"command {mismatch} echoes {echoes[mismatch]}, sensor frame had {sensors[mismatch]}"
        )
    if len(echoes) > len(sensors) or len(sensors) - len(echoes) > 1:
        errors.append(f"{len(sensors)} sensor frames but {len(echoes)} commands in the window")
    if len(echoes) < min_frames:
        errors.append(f"only {len(echoes)} answered frames (want >= {min_frames})")
    if any(mode != 0 for _, _, _, mode in tail[len(answer_to_last) :]):
        errors.append("an ACTIVE command after the simulator stopped")
    span = window[-1][2] - window[0][2]
    print(
        f"candump check: {len(frames)} frames; in the daemon's window {len(sensors)} sensor "
        f"frames, {len(echoes)} commands ({n['active']} ACTIVE) over {span:.1f} s = "
        f"{len(sensors) / span if span else 0:.0f} Hz; {n['status']} RigStatus, "
        f"{n['actuator']} ActuatorCommand; {after} SAFE commands after the simulator stopped; "
        f"{len(errors)} errors"
    )
    return errors


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("log")
    ap.add_argument("--i-max", type=float, required=True)
    ap.add_argument("--min-frames", type=int, default=100)
    args = ap.parse_args()
    errors = check(read_candump(args.log), args.i_max, args.min_frames)
    for e in errors[:20]:
        print("FAIL:", e)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
