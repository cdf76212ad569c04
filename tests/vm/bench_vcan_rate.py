"""Benchmark: how fast two Python processes exchange frames over vcan0 inside the VM.

Usage: `scripts/vcan-vm -- python tests/vm/bench_vcan_rate.py [--seconds 3] [--rate-hz 500]`

A child process echoes every request frame back (the "daemon"); the parent (the "simulator")
runs (1) a free-running ping-pong and (2) a paced loop that sends one request per period to an
absolute deadline and expects the reply before the next one. Prints numbers; asserts nothing.
"""

from __future__ import annotations

import argparse
import statistics
import struct
import subprocess
import sys
import time
from pathlib import Path

import can

CHANNEL = "vcan0"
REQUEST_ID = 0x310
REPLY_ID = 0x311
STOP_ID = 0x31F
SEND_TIMEOUT_S = 0.1
SPIN_TAIL_S = 0.0005
PAYLOAD = struct.Struct("<Q")


def open_bus(can_id: int) -> can.BusABC:
    """A socketcan bus on CHANNEL that only receives `can_id`."""
    return can.Bus(
        interface="socketcan",
        channel=CHANNEL,
        can_filters=[{"can_id": can_id, "can_mask": 0x7FF, "extended": False}],
    )


def echo() -> int:
    """Reply to every request with the same payload; stop on STOP_ID."""
    with can.Bus(
        interface="socketcan",
        channel=CHANNEL,
        can_filters=[
            {"can_id": REQUEST_ID, "can_mask": 0x7FF, "extended": False},
            {"can_id": STOP_ID, "can_mask": 0x7FF, "extended": False},
        ],
    ) as bus:
        print("ready", flush=True)
        while True:
            msg = bus.recv(timeout=10.0)
            if msg is None or msg.arbitration_id == STOP_ID:
                return 0
            reply = can.Message(arbitration_id=REPLY_ID, data=msg.data, is_extended_id=False)
            bus.send(reply, timeout=SEND_TIMEOUT_S)


def request(seq: int) -> can.Message:
    return can.Message(arbitration_id=REQUEST_ID, data=PAYLOAD.pack(seq), is_extended_id=False)


def percentiles_us(values_s: list[float]) -> str:
    if not values_s:
        return "no samples"
    ordered = sorted(values_s)
    p99 = ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))]
    return (
        f"p50 {statistics.median(ordered) * 1e6:.0f} us, p99 {p99 * 1e6:.0f} us, "
        f"max {ordered[-1] * 1e6:.0f} us"
    )


def free_running(bus: can.BusABC, seconds: float) -> None:
    """Round trips back to back for `seconds`."""
    rtts_s = []
    seq = 0
    end = time.perf_counter() + seconds
    while (t0 := time.perf_counter()) < end:
        bus.send(request(seq), timeout=SEND_TIMEOUT_S)
        reply = bus.recv(timeout=1.0)
        if reply is None or PAYLOAD.unpack(reply.data)[0] != seq:
            print(f"free-running: lost reply to {seq}")
            break
        rtts_s.append(time.perf_counter() - t0)
        seq += 1
    print(
        f"free-running ping-pong: {len(rtts_s) / seconds:.0f} round trips/s; RTT "
        f"{percentiles_us(rtts_s)}"
    )


def sleep_until(deadline: float) -> None:
    """Sleep to an absolute perf_counter deadline, spinning for the last SPIN_TAIL_S."""
    remaining = deadline - time.perf_counter() - SPIN_TAIL_S
    if remaining > 0:
        time.sleep(remaining)
    while time.perf_counter() < deadline:
        pass


def paced(bus: can.BusABC, seconds: float, rate_hz: float) -> None:
    """One request per period; the reply must arrive before the next period starts."""
    period_s = 1.0 / rate_hz
    ticks = int(seconds * rate_hz)
    on_time = late = overruns = 0
    rtts_s, jitter_s = [], []
    start = time.perf_counter() + 0.05
    for seq in range(ticks):
        deadline = start + seq * period_s
        if time.perf_counter() > deadline:
            overruns += 1  # the previous period ran past this deadline
        else:
            sleep_until(deadline)
        t0 = time.perf_counter()
        jitter_s.append(t0 - deadline)
        bus.send(request(seq), timeout=SEND_TIMEOUT_S)
        next_deadline = deadline + period_s
        while True:
            reply = bus.recv(timeout=max(0.0, next_deadline - time.perf_counter()))
            if reply is None:
                late += 1
                break
            if PAYLOAD.unpack(reply.data)[0] == seq:
                rtts_s.append(time.perf_counter() - t0)
                on_time += 1
                break
            # a late reply to an earlier request: skip it
    elapsed_s = time.perf_counter() - start
    print(
        f"paced {rate_hz:.0f} Hz for {ticks} ticks: achieved {ticks / elapsed_s:.1f} Hz, "
        f"{on_time} replies in period, {late} late/missing ({100 * late / ticks:.2f} %), "
        f"{overruns} deadline overruns"
    )
    print(f"  send lateness {percentiles_us(jitter_s)}; RTT {percentiles_us(rtts_s)}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--rate-hz", type=float, action="append", help="paced rates (500)")
    parser.add_argument("--echo", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.echo:
        return echo()

    uptime_s = float(Path("/proc/uptime").read_text().split()[0])
    print(f"guest uptime at start: {uptime_s:.1f} s")
    child = subprocess.Popen(
        [sys.executable, __file__, "--echo"], stdout=subprocess.PIPE, text=True
    )
    try:
        if child.stdout is None or child.stdout.readline().strip() != "ready":
            print("FAIL: echo process did not start", file=sys.stderr)
            return 1
        with open_bus(REPLY_ID) as bus:
            free_running(bus, args.seconds)
            for rate_hz in args.rate_hz or [500.0]:
                paced(bus, args.seconds, rate_hz)
            bus.send(can.Message(arbitration_id=STOP_ID, is_extended_id=False))
        return child.wait(timeout=10)
    finally:
        if child.poll() is None:
            child.kill()


if __name__ == "__main__":
    sys.exit(main())
