"""The sidecar's process: `start_sidecar` starts it from the daemon, `run_sidecar` opens its
Zenoh session and recording, says READY (or the one line why not) and runs the `Sidecar`
(mrrig.rigio.sidecar) until STOP, EOF, SIGTERM or SIGINT.

Run: python -m mrrig.rigio.sidecar_process --rig NAME --zenoh-config FILE|'' --record PATH|''
--rx-fd N --tx-fd M [--telemetry-hz 50] [--live-url URL] [--nice 10] [--insecure]; or
`start_sidecar(...)` from the daemon. An empty Zenoh config runs without Zenoh (recording only).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import zenoh

from mrrig import json_text
from mrrig.rigio.ipc import ChannelFds, SidecarEnd
from mrrig.rigio.rig_topics import alive_elsewhere, duplicate_text
from mrrig.rigio.run_identity import operator_of
from mrrig.rigio.sidecar import DUPLICATE_CHECK_S, SampleSink, Sidecar
from mrrig.rigio.zenoh_config import (
    ZenohConfigError,
    check_secure,
    load_zenoh_config,
    zenoh_error_text,
)

log = logging.getLogger(__name__)


def lower_priority(nice: int) -> None:
    """SCHED_BATCH + nice for this thread and the threads it starts later (Zenoh's): at
    normal priority the sidecar, woken by the loop's pipe writes, preempts the loop."""
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
        os.nice(nice)
    except (OSError, AttributeError) as exc:  # not Linux, or not permitted
        log.warning("could not lower the sidecar's priority: %s", exc)


def run_sidecar(
    rig: str,
    zenoh_config: str | Path | None,
    record: str | Path | None,
    rx_fd: int,
    tx_fd: int,
    telemetry_hz: float = 50.0,
    live_url: str | None = None,
    insecure: bool = False,
    can_log: tuple[str, str] | None = None,
    identity: dict[str, Any] | None = None,
) -> int:
    """Run until STOP, EOF, SIGTERM or SIGINT; returns the exit status: 0, 2 for a refused
    config (`check_secure`: off loopback without authentication and access control, unless
    `insecure`) or a daemon of the rig's name alive on the network, 3 if the session cannot
    open (port taken) or the recording cannot be written.

    Once its session and recording are open (or have failed) it sends READY to the loop, with
    the failure as one line: the daemon stops its start-up on it (a rig must not run
    unobserved)."""
    warnings: list[str] = []
    end = SidecarEnd(rx_fd, tx_fd)
    try:
        conf = load_zenoh_config(zenoh_config) if zenoh_config else None
        if conf is not None:
            warnings = check_secure(conf, str(zenoh_config), insecure)
        if identity is not None and not identity.get("operator"):
            identity = {**identity, "operator": operator_of(conf)}
    except ZenohConfigError as exc:
        log.debug("%s", exc)
        end.send_ready(str(exc))
        end.close()
        return 2
    # past a file size limit a write fails (EFBIG) instead of killing the process: the
    # recording then fails as on a full disk, and telemetry goes on
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    stop_early: list[int] = []  # a signal before the Sidecar exists still stops it
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda num, _frame: stop_early.append(num))
    recorder: SampleSink | None = None
    session: zenoh.Session | None = None
    bus_log = None
    try:
        # Zenoh first: a start that fails there (its port taken, another daemon of this
        # rig's name) leaves no stray recording or bus log behind
        try:
            session = zenoh.open(conf) if conf is not None else None
        except zenoh.ZError as exc:  # e.g. the listen port is taken
            text = zenoh_error_text(exc)
            hint = ""
            if "address already in use" in text.lower():
                hint = (
                    " (another daemon or zenohd listens there: stop it, or give this rig"
                    " another port in its Zenoh config)"
                )
            log.debug("%s: cannot open the Zenoh session: %s", zenoh_config, text)
            end.send_ready(f"{zenoh_config}: cannot open the Zenoh session: {text}{hint}")
            return 3
        others = alive_elsewhere(session, rig, DUPLICATE_CHECK_S) if session is not None else []
        if others:
            end.send_ready(duplicate_text(rig, others))
            return 2
        if can_log is not None:
            from mrrig.rigio.canlog import BusLogError, BusLogWriter

            try:
                bus_log = BusLogWriter(*can_log)
            except BusLogError as exc:
                end.send_ready(str(exc))
                return 3
        if record:
            from mrrig.rigio.recording import Recorder  # rerun is heavy: only when recording

            try:
                recorder = Recorder(
                    record, rig, flush_interval_s=0.5, live_url=live_url, identity=identity
                )
            except Exception as exc:  # noqa: BLE001 - reported to the daemon as one line
                text = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
                end.send_ready(f"cannot write the recording {record}: {text}")
                return 3
        sidecar = Sidecar(rig, session, end, recorder, telemetry_hz, warnings, bus_log, identity)
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, sidecar.request_stop)
        if stop_early:
            sidecar.request_stop()
        end.send_ready()
        sidecar.run()
    finally:
        if session is not None:
            session.close()
        if recorder is not None:
            recorder.close()  # idempotent; covers a failure before run() took it over
        if bus_log is not None:
            bus_log.close()
        end.close()
    log.info("sidecar stopped")
    if recorder is not None and recorder.failed:
        # rerun's exit handler waits for the file writer that failed, for ever: leave without
        logging.shutdown()
        os._exit(0)
    return 0


def start_sidecar(
    rig: str,
    zenoh_config: str | Path | None,
    fds: ChannelFds,
    record: str | Path | None = None,
    telemetry_hz: float = 50.0,
    live_url: str | None = None,
    insecure: bool = False,
    can_log: tuple[str | Path, str] | None = None,
    identity: dict[str, Any] | None = None,
) -> subprocess.Popen[bytes]:
    """Start the sidecar process on the sidecar's ends of `fds`, and close those ends here.

    `zenoh_config` None: no Zenoh at all (recording only); `record` None: no recording;
    `can_log` (path, channel name written in it): the bus log of `mrrig.rigio.canlog`.

    The child gets its own session (process group), so a Ctrl-C at the terminal reaches only
    the daemon, which then sends its summary and STOP.
    """
    cmd = [
        sys.executable,
        "-m",
        "mrrig.rigio.sidecar_process",
        "--rig",
        rig,
        "--zenoh-config",
        str(zenoh_config or ""),
        "--record",
        str(record or ""),
        "--rx-fd",
        str(fds.sidecar_rx),
        "--tx-fd",
        str(fds.sidecar_tx),
        "--telemetry-hz",
        str(telemetry_hz),
    ]
    if live_url:
        cmd += ["--live-url", live_url]
    if insecure:
        cmd.append("--insecure")
    if can_log is not None:
        cmd += ["--can-log", str(can_log[0]), "--can-log-channel", can_log[1]]
    if identity is not None:
        cmd += ["--identity", json_text.dumps(identity)]
    proc = subprocess.Popen(cmd, pass_fds=fds.sidecar_fds(), start_new_session=True)
    # the loop must see EOF / EPIPE when the sidecar dies, so it holds no copy of these
    os.close(fds.sidecar_rx)
    os.close(fds.sidecar_tx)
    return proc


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m mrrig.rigio.sidecar_process", description=__doc__
    )
    parser.add_argument("--rig", required=True)
    parser.add_argument("--zenoh-config", required=True, help="'' for no Zenoh (recording only)")
    parser.add_argument("--record", default="", help="recording path; '' records nothing")
    parser.add_argument("--rx-fd", type=int, required=True)
    parser.add_argument("--tx-fd", type=int, required=True)
    parser.add_argument("--telemetry-hz", type=float, default=50.0)
    parser.add_argument("--live-url", default=None, help="also stream to a Rerun viewer")
    parser.add_argument(
        "--nice",
        type=int,
        default=10,
        help="niceness increment (SCHED_BATCH too), so waking the sidecar "
        "does not preempt the control loop; 0 keeps the priority",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="allow a config off loopback without authentication and access control "
        "(a closed lab network); warned in every status and the recording",
    )
    parser.add_argument("--can-log", default=None, help="bus log file (.blf, .asc, .log, ...)")
    parser.add_argument("--can-log-channel", default="can0", help="channel name in the bus log")
    parser.add_argument("--log-level", default="INFO")
    parser.add_argument("--identity", default=None, help="the run's identity (JSON)")
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=args.log_level, format="%(asctime)s sidecar %(levelname)s %(name)s: %(message)s"
    )
    if args.nice:
        lower_priority(args.nice)
    return run_sidecar(
        args.rig,
        args.zenoh_config or None,
        args.record or None,
        args.rx_fd,
        args.tx_fd,
        args.telemetry_hz,
        args.live_url,
        args.insecure,
        (args.can_log, args.can_log_channel) if args.can_log else None,
        json.loads(args.identity) if args.identity else None,
    )


if __name__ == "__main__":
    sys.exit(main())
