"""`python -m firmware_sim` (or `mrrig sim`): the simulated rig firmware on a CAN bus.

    python -m firmware_sim --config configs/sim.toml --bus-channel ws://127.0.0.1:54701/ \\
        --fault estop@5:2 --duration 30 --stats sim-stats.json

Exit codes: 0 after SIGINT/SIGTERM or --duration, 1 on a bus error (one error line in the
log), 2 for a config that cannot be used.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import time
from pathlib import Path
from types import FrameType

from can_remote.websocket import WebsocketClosed

from firmware_sim.config import FAULT_KINDS, ConfigError, FaultSpec, load_config
from firmware_sim.firmware import Firmware
from firmware_sim.runner import RunStats, run, tune_process
from mrrig import json_text
from mrrig.cli_args import HelpFormatter, add_bus_options, output_file, positive
from mrrig.config import load_config as load_daemon_config
from mrrig.loop.realtime import leave_realtime
from mrrig.pycan import can
from mrrig.rigio.canbus import BusError, open_bus
from mrrig.rigio.canbus.profile import ProfileError, load_profile
from mrrig.rigio.canbus.profile_limits import firmware_limits

logger = logging.getLogger("firmware_sim")

DEFAULT_CONFIG = Path("configs/sim.toml")


def _fault_arg(text: str) -> FaultSpec:
    try:
        return FaultSpec.from_cli(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="mrrig sim", description=__doc__.splitlines()[0], formatter_class=HelpFormatter
    )
    ap.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="simulator TOML config")
    add_bus_options(ap, "[bus] ")
    ap.add_argument(
        "--fault",
        type=_fault_arg,
        action="append",
        default=[],
        metavar="KIND@START_S[:DUR_S]",
        help=f"inject a fault (repeatable); KIND: {', '.join(FAULT_KINDS)}",
    )
    ap.add_argument(
        "--rig-config",
        type=Path,
        metavar="DAEMON.toml",
        help="speak the rig profile of this daemon config ([can]: the lab's DBC and roles),"
        " not the simulator config's own [can]: one copy of the table for both",
    )
    ap.add_argument("--duration", type=positive, metavar="S", help="stop after S seconds")
    ap.add_argument("--stats", type=output_file, metavar="FILE", help="write run statistics (JSON)")
    ap.add_argument(
        "--measure-echo",
        action="store_true",
        help="take this process's own frames back from the bus (through the bridge) and report "
        "the windows in which the transport held them up (--stats: stall_windows)",
    )
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        logger.error("%s", exc)
        return 2
    interface = args.bus_interface or config.bus.interface
    channel = args.bus_channel or config.bus.channel
    try:
        # the sensor period is the DBC's: the simulator has no other
        limits = firmware_limits(config.actuator.stroke_m)
        can_of, source = config.can, str(args.config)
        if args.rig_config is not None:
            rig = load_daemon_config(args.rig_config)
            can_of, source = rig.can, rig.source
            logger.info("rig profile: [can] of %s", source)
        profile = load_profile(can_of.dbc, can_of.signals, None, source, limits)
        firmware = Firmware(config, profile, (*config.faults, *args.fault))
    except (ProfileError, ConfigError, ValueError) as exc:  # the profile, a plant file, ...
        logger.error("%s", exc)
        return 2
    if profile.protections_off:
        logger.info("%s", profile.startup_line())

    stopping = False

    def request_stop(signum: int, _frame: FrameType | None) -> None:
        nonlocal stopping
        stopping = True
        logger.info("%s: stopping", signal.Signals(signum).name)

    previous = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            bus = open_bus(interface, channel, receive_own_messages=args.measure_echo)
        except BusError as exc:  # a set-up error, as a bad config: exit 2
            logger.error("%s", exc)
            return 2
        logger.info(
            "rig firmware on %s %s, %d fault injections",
            interface,
            channel,
            len(config.faults) + len(args.fault),
        )
        tune_process(config.timing.realtime_priority, config.timing.poll_idle)
        stats = RunStats(
            measure_echo=args.measure_echo,
            stale_answer_age_s=config.commands.stale_answer_age_s,
        )
        rc = 0
        wall0, cpu0 = time.monotonic(), time.process_time()
        try:
            run(
                firmware,
                bus,
                stats,
                lead_s=config.timing.lead_s,
                spin_s=config.timing.spin_s,
                send_timeout_s=config.bus.send_timeout_s,
                duration_s=args.duration,
                should_stop=lambda: stopping,
                time_scale=config.timing.time_scale,
            )
        except (can.CanError, WebsocketClosed, OSError) as exc:
            logger.error("CAN bus error on %s %s: %s", interface, channel, exc)
            rc = 1
        wall_s, cpu_s = time.monotonic() - wall0, time.process_time() - cpu0
        _shutdown(bus)
        leave_realtime("firmware_sim")  # the summary and the exit must not starve another rig
        stats.finish()
        summary = stats.summary(firmware, wall_s, cpu_s)
        if args.stats is not None:
            args.stats.write_text(json_text.dumps(summary, indent=2) + "\n")
        p99 = summary["period_jitter_us"]["p99"]  # None: under two frames sent
        logger.info(
            "%d sensor frames in %.1f s, jitter p99 %s, CPU %.0f %%",
            stats.sensor_frames_sent,
            wall_s,
            "n/a" if p99 is None else f"{p99:.1f} us",
            100.0 * summary["cpu_fraction"],
        )
        return rc
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _shutdown(bus: can.BusABC) -> None:
    try:
        bus.shutdown()
    except Exception as exc:  # noqa: BLE001 - a dead bus may fail to close in any way
        logger.debug("bus shutdown: %s", exc)


if __name__ == "__main__":
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    sys.exit(main())
