"""Smoke test for SocketCAN on vcan0, run inside the VM.

Usage: `scripts/vcan-vm -- python tests/vm/smoke_socketcan.py`

Opens two python-can `socketcan` buses on vcan0, sends frames one way and back, and checks that
`candump -L vcan0` (running in the background) logged every one of them. Exits non-zero on any
failure.
"""

from __future__ import annotations

import argparse
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import can

CHANNEL = "vcan0"
RECV_TIMEOUT_S = 2.0
SEND_TIMEOUT_S = 1.0
CANDUMP_START_S = 0.5
# candump -L line: "(1700000000.123456) vcan0 123#DEADBEEF"
CANDUMP_LINE = re.compile(r"^\(\d+\.\d+\) (\S+) ([0-9A-F]+)#([0-9A-F]*)$")


def make_frames(base_id: int, count: int) -> list[can.Message]:
    """Distinct 11-bit frames with payloads that encode their index."""
    return [
        can.Message(
            arbitration_id=base_id + i,
            data=bytes((i + k) % 256 for k in range(8)),
            is_extended_id=False,
        )
        for i in range(count)
    ]


def transfer(tx: can.BusABC, rx: can.BusABC, frames: list[can.Message]) -> list[str]:
    """Send `frames` on `tx`, receive on `rx`; return the problems found."""
    problems = []
    for frame in frames:
        tx.send(frame, timeout=SEND_TIMEOUT_S)
        got = rx.recv(timeout=RECV_TIMEOUT_S)
        if got is None:
            problems.append(f"0x{frame.arbitration_id:03X}: nothing received")
        elif (got.arbitration_id, bytes(got.data), got.is_extended_id) != (
            frame.arbitration_id,
            bytes(frame.data),
            False,
        ):
            problems.append(f"0x{frame.arbitration_id:03X}: sent {frame}, received {got}")
    return problems


def read_candump(path: Path) -> set[tuple[int, bytes]]:
    """(id, data) of the frames on CHANNEL in a `candump -L` log."""
    seen = set()
    for line in path.read_text().splitlines():
        match = CANDUMP_LINE.match(line.strip())
        if match and match.group(1) == CHANNEL:
            seen.add((int(match.group(2), 16), bytes.fromhex(match.group(3))))
    return seen


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=5, help="frames each way")
    parser.add_argument("--candump-log", type=Path, help="where to keep the candump log")
    args = parser.parse_args()

    if not Path(f"/sys/class/net/{CHANNEL}").exists():
        print(f"FAIL: no {CHANNEL} interface (run inside scripts/vcan-vm)", file=sys.stderr)
        return 1
    candump = shutil.which("candump")
    if candump is None:
        print("FAIL: candump not found (install can-utils)", file=sys.stderr)
        return 1

    log_path = args.candump_log or Path(tempfile.mkdtemp()) / "candump.log"
    forward = make_frames(0x100, args.frames)
    backward = make_frames(0x200, args.frames)
    with log_path.open("w") as log_file:
        dump = subprocess.Popen([candump, "-L", CHANNEL], stdout=log_file)
        try:
            time.sleep(CANDUMP_START_S)
            with (
                can.Bus(interface="socketcan", channel=CHANNEL) as bus_a,
                can.Bus(interface="socketcan", channel=CHANNEL) as bus_b,
            ):
                problems = transfer(bus_a, bus_b, forward) + transfer(bus_b, bus_a, backward)
            time.sleep(CANDUMP_START_S)
        finally:
            dump.send_signal(signal.SIGINT)
            dump.wait(timeout=5)

    logged = read_candump(log_path)
    for frame in forward + backward:
        if (frame.arbitration_id, bytes(frame.data)) not in logged:
            problems.append(f"0x{frame.arbitration_id:03X}: missing from candump log {log_path}")

    for problem in problems:
        print(f"FAIL: {problem}", file=sys.stderr)
    if problems:
        return 1
    print(
        f"OK: {len(forward)} frames A->B and {len(backward)} B->A over {CHANNEL}, "
        f"{len(logged)} in candump log {log_path}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
