"""`mrrig test PLAN.toml --rig NAME`: run a test plan on a live rig, step by step, with a
verdict per step, a table at the end and, on request, JUnit XML and HTML reports.

The rig is driven only through its public interfaces (control requests, status, telemetry over
Zenoh), so the same plan runs on the simulator, on vcan and at a real rig. `--sim` starts the
simulated rig first (the CAN bridge on 127.0.0.1, firmware_sim, the daemon with telemetry), as
`mrrig demo` does, and stops it at the end; for a plan of `hil` steps the daemon runs their
scenario (`--hil`), and the end prints each law's figures beside the reference's.

Exit codes: 0 every step passed; 1 a step failed or was aborted (a fault, Ctrl-C: the rig is
left disarmed, the reports still written); 2 the plan could not run (a plan error, no rig).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import logging
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from mrrig.cli_args import HelpFormatter, controllers_epilog
from mrrig.errors import MrrigError
from mrrig.plans.plan import load_plan
from mrrig.rigio import client

log = logging.getLogger(__name__)

SIM_START_S = 30.0  # how long --sim waits for the daemon's first status


class SimError(MrrigError, RuntimeError):
    """--sim: the simulated rig did not start."""


def add_run_arguments(ap: argparse.ArgumentParser) -> None:
    """What a plan's run takes besides the plan (`mrrig test`, `mrrig compare`): the Zenoh
    client config, the catalog and campaign of its steps' runs, the JUnit and HTML reports,
    and --sim with its configs."""
    ap.add_argument(
        "--zenoh-config",
        type=Path,
        help=f"Zenoh client config (default: {client.DEFAULT_CONFIG}; with --sim, both the"
        " client's and the daemon's on a free port of 127.0.0.1)",
    )
    ap.add_argument(
        "--catalog",
        help="register each step as a run in this catalog: an SQLite file or a postgresql://"
        " URL (default: $MRRIG_CATALOG, else recordings/catalog.sqlite)",
    )
    ap.add_argument(
        "--campaign",
        help="the campaign the steps' runs belong to in the catalog (`mrrig runs --campaign`;"
        " default: the plan's name and the UTC time it started)",
    )
    ap.add_argument("--junit", type=Path, help="write a JUnit XML report here")
    ap.add_argument("--html", type=Path, help="write a self-contained HTML report here")
    add_sim_arguments(ap)


def add_sim_arguments(ap: argparse.ArgumentParser) -> None:
    """--sim and the two configs it starts the simulated rig with (`simulated_rig`)."""
    ap.add_argument(
        "--sim",
        action="store_true",
        help="start the simulated rig first (bridge, firmware_sim, daemon) and stop it after",
    )
    ap.add_argument(
        "--config", type=Path, default=Path("configs/rig.toml"), help="--sim: the daemon's config"
    )
    ap.add_argument(
        "--sim-config", type=Path, default=Path("configs/sim.toml"), help="--sim: the simulator's"
    )


@contextlib.contextmanager
def simulated_rig(
    config: Path,
    sim_config: Path,
    zenoh_config: Path | None,
    adaptation: str | None = None,
    daemon_args: tuple[str, ...] = (),
    sim_args: tuple[str, ...] = (),
) -> Iterator[tuple[str, Path]]:
    """The CAN bridge, firmware_sim and a daemon (`config`, on the bridge's channel, no
    recording, `adaptation` "on"/"off" over the config's, `daemon_args` added to its `mrrig
    run`, `sim_args` to the simulator's), as `mrrig demo` starts them; yields the rig's name
    and the client's Zenoh config once it answers. `zenoh_config`: the client's (the daemon
    then on its config's); None: both on a free port of 127.0.0.1."""
    from mrrig.cli.demo import _stop, ensure_sim_model
    from mrrig.config import load_config
    from mrrig.rigio.canbus.bus import find_free_port, start_bridge, stop_bridge
    from mrrig.rigio.zenoh_config import write_loopback_configs

    cfg = load_config(config)
    if not cfg.telemetry.enabled:
        raise SimError(f"{config}: telemetry.enabled = false: a plan needs the rig's telemetry")
    if cfg.controller.model is not None:
        ensure_sim_model(cfg.controller.model)
    own_zenoh: list[str] = []
    if zenoh_config is None:
        # a port of its own: a second simulated rig, or a rig's daemon, here is not reached
        work = Path(tempfile.mkdtemp(prefix="mrrig-sim-"))
        daemon_zenoh, zenoh_config = write_loopback_configs(work, find_free_port())
        own_zenoh = ["--zenoh-config", str(daemon_zenoh)]
    port = find_free_port()
    channel = f"ws://127.0.0.1:{port}/"
    bridge = start_bridge(port)
    procs: list[tuple[subprocess.Popen, str]] = []
    try:
        # their own sessions: Ctrl-C reaches `mrrig test` alone, which disarms, ends the step,
        # writes the reports and then stops them
        sim = subprocess.Popen(
            [sys.executable, "-m", "firmware_sim", "--config", str(sim_config), "-c", channel]
            + ["--rig-config", str(config), *sim_args],  # the daemon's [can]: its rig profile
            start_new_session=True,
        )
        procs.append((sim, "firmware_sim"))
        time.sleep(1.0)  # the simulator connects and starts streaming
        if sim.poll() is not None:
            raise SimError(f"firmware_sim exited at start (code {sim.returncode})")
        cmd = [sys.executable, "-m", "mrrig", "run", "--config", str(config), *own_zenoh]
        if adaptation is not None:
            cmd += ["--adaptation", adaptation]
        cmd += daemon_args
        daemon = subprocess.Popen(
            [*cmd, "--bus-channel", channel, "--no-record"], start_new_session=True
        )
        procs.append((daemon, "daemon"))
        deadline = time.monotonic() + SIM_START_S
        while True:
            if daemon.poll() is not None:
                raise SimError(f"the daemon exited at start (code {daemon.returncode})")
            try:
                client.status(cfg.rig.name, zenoh_config, timeout_s=1.0)
                break
            except MrrigError:
                if time.monotonic() > deadline:
                    raise SimError(f"the daemon did not answer within {SIM_START_S:g} s") from None
                time.sleep(0.5)
        yield cfg.rig.name, zenoh_config
    finally:
        for proc, name in reversed(procs):
            _stop(proc, name)
        stop_bridge(bridge)
        if own_zenoh:
            shutil.rmtree(Path(own_zenoh[1]).parent, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    from mrrig.cli.main import version

    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter,
        prog="mrrig test",
        description=__doc__,
        epilog=controllers_epilog(),
    )
    ap.add_argument("plan", type=Path, help="the plan (TOML: [plan], [[step]]s)")
    ap.add_argument("--rig", help="the rig's name (default: the plan's [plan] rig)")
    add_run_arguments(ap)
    ap.add_argument(
        "--adaptation",
        choices=("on", "off"),
        help="--sim: the daemon's on-line adaptation (adaptation.enabled); a plan whose steps"
        " set `adaptation` needs it on",
    )
    args = ap.parse_args(argv)

    if args.adaptation is not None and not args.sim:
        ap.error("--adaptation: only with --sim (a live rig's daemon keeps its own config)")
    plan = load_plan(args.plan)  # a PlanError: one line, exit 2 (mrrig.cli.main)
    with contextlib.ExitStack() as stack:
        if args.sim:
            # a plan of hil steps: the daemon runs their scenario (`set_hil` sets each law)
            hil = () if plan.hil_scenario is None else ("--hil", str(plan.hil_scenario))
            rig_name, args.zenoh_config = stack.enter_context(
                simulated_rig(args.config, args.sim_config, args.zenoh_config, args.adaptation, hil)
            )
            if args.rig and args.rig != rig_name:
                raise SimError(f"--rig {args.rig}: the simulated rig ({args.config}) is {rig_name}")
        else:
            rig_name = args.rig or plan.rig
            if rig_name is None:
                ap.error("--rig: the plan names no rig ([plan] rig): give --rig NAME")
        return run_on(plan, rig_name, args, version())[0]


def run_on(plan, rig_name: str, args: argparse.Namespace, mrrig_version: str) -> tuple[int, list]:
    """Run `plan` on the rig and write the reports `args` asks for (`--junit`, `--html`,
    `--catalog`, `--zenoh-config`); the exit code and the steps' results."""
    from mrrig.api import Rig, default_catalog
    from mrrig.plans.interrupts import PlanSignals
    from mrrig.plans.report import Identity, write_html, write_junit
    from mrrig.plans.runner import overall, run_plan, table

    started = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    with Rig(rig_name, zenoh_config=args.zenoh_config) as rig:
        rig.status()  # no rig answering: one line, exit 2, before any step
        print(
            f"plan {plan.name} ({len(plan.steps)} steps) on rig {rig_name}, {started}", flush=True
        )
        # Ctrl-C, a kill or a dropped ssh session ends the step it comes in (the rig
        # disarmed, the step aborted with the signal named, the reports written), even where
        # this process was started with SIGINT ignored (a background job; pytest-xdist's
        # workers); a second one (a double Ctrl-C) does not cut the step's end, the catalog
        # rows or the reports
        with PlanSignals().installed() as stops:
            results, interrupted = run_plan(
                plan,
                rig,
                lambda line: print(line, flush=True),
                args.catalog or default_catalog(),
                args.campaign or f"{plan.name} {started}",
            )
            interrupted = interrupted or stops.received > 0
            print(table(results))
            verdict = overall(results)
            ended = " (interrupted)" if interrupted else ""
            print(f"plan {plan.name}: {verdict.upper()}{ended}")
            ident = Identity.of(plan.path, rig_name, mrrig_version, started)
            if args.junit:
                write_junit(args.junit, plan.name, ident, results)
                print(f"JUnit report: {args.junit}")
            if args.html:
                write_html(args.html, plan.name, ident, results)
                print(f"HTML report: {args.html}")
    return (0 if verdict == "passed" else 1), results
