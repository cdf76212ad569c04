"""The transport's own latency floor, for `mrrig bench loop`: a process that answers each valid
RigSensors frame with a SAFE DamperCommand echoing its counter, and does nothing else.

It opens the bus, raises its priority and freezes the garbage collector exactly as the daemon
does (same config), parses and packs through the same DBC codec, and measures latency the same
way (after `recv` returns -> after `send` returns). What the daemon adds on top is its own work:
Kalman filter, reference, controller, safety checks, bookkeeping.

    python -m mrrig.offline.bench.echo --config configs/rig.toml \
        --bus-channel ws://127.0.0.1:PORT/ \
        --summary-json echo.json        # stops on SIGTERM/SIGINT
"""

from __future__ import annotations

import argparse
import array
import gc
import logging
import signal
import time
from pathlib import Path

import numpy as np

from mrrig import json_text
from mrrig.cli_args import output_file
from mrrig.config import load_config
from mrrig.loop.daemon import loop_realtime
from mrrig.loop.summary import frame_gaps
from mrrig.offline.metrics import percentiles
from mrrig.rigio.canbus.bus import open_bus
from mrrig.rigio.canbus.codec import Codec

log = logging.getLogger(__name__)


def run(config: Path, bus_channel: str | None, summary_json: Path) -> dict:
    cfg = load_config(config)
    codec = Codec()
    packer, parser = codec.packer("DAEMON"), codec.parser()
    bus = open_bus(cfg.bus.interface, bus_channel or cfg.bus.channel, **cfg.bus.options)
    stop = False

    def _stop(_sig, _frame) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    waited_us = array.array("d")  # the bus's receive timestamp -> the read, as the daemon's
    work_us = array.array("d")
    send_us = array.array("d")
    rx_s = array.array("d")
    answered = 0
    try:
        while bus.recv(timeout=0) is not None:  # stale frames, as the daemon discards them
            pass
        gc.collect()
        gc.freeze()
        loop_realtime(cfg)
        recv, send, perf = bus.recv, bus.send, time.perf_counter
        while not stop:
            msg = recv(timeout=0.1)
            if msg is None:
                continue
            t_rx = perf()
            waited = max(time.time() - msg.timestamp, 0.0)
            p = parser.parse(msg.arbitration_id, msg.data, t_rx)
            if p.name != "RigSensors" or not p.ok:
                continue
            out = packer.message(
                "DamperCommand",
                {
                    "Mode": 0,
                    "CurrentSetpoint": 0.0,
                    "SensorCounterEcho": p.counter,
                    "ControllerId": 0,
                    "DesiredForce": 0.0,
                },
            )
            t_send = perf()
            send(out, timeout=cfg.bus.send_timeout_s)
            t_done = perf()
            rx_s.append(t_rx)
            waited_us.append(waited * 1e6)
            work_us.append((t_done - t_rx) * 1e6)
            send_us.append((t_done - t_send) * 1e6)
            answered += 1
    finally:
        gc.unfreeze()
        bus.shutdown()
    waited, work, snd = (
        np.frombuffer(a, dtype=np.float64) if answered else np.empty(0)
        for a in (waited_us, work_us, send_us)
    )
    summary = {
        "frames": answered,
        # receive gaps: what the transport did to a 2 ms stream (no work in this process)
        "frame_gap_ms": frame_gaps(np.frombuffer(rx_s, dtype=np.float64) if answered else []),
        "latency_us": percentiles(waited + work, qs=(50, 99, 99.9)),
        "latency_split_us": {
            k: percentiles(v, qs=(50, 99, 99.9))
            for k, v in (("waited", waited), ("work", work), ("send_call", snd))
        },
    }
    summary_json.write_text(json_text.dumps(summary, indent=2))
    p99 = summary["latency_us"]["p99"]
    log.info("echo: answered %d frames, latency p99 %.0f us", answered, p99)
    return summary


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mrrig.offline.bench.echo", description=__doc__)
    ap.add_argument("--config", type=Path, default=Path("configs/rig.toml"))
    ap.add_argument("--bus-channel", help="override the config's bus channel")
    ap.add_argument("--summary-json", type=output_file, required=True)
    args = ap.parse_args(argv)
    run(args.config, args.bus_channel, args.summary_json)
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    raise SystemExit(main())
