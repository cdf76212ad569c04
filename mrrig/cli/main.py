"""`mrrig`: one entry point, one subcommand per job.

Ordinary errors (a bad config, a missing model, no daemon answering, a bus that cannot be
opened) print one `error: ...` line and exit 2; `--debug` shows the traceback instead.
`--debug` and `-q` may come before or after the subcommand. Output cut short by a closed
pipe (`mrrig review ... | head`) ends quietly.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from mrrig.cli_args import HelpFormatter
from mrrig.errors import MrrigError

# subcommand -> (module with main(argv) -> int, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("mrrig.cli.demo", "simulator + daemon: a 20 s force-tracking run and its summary"),
    "run": ("mrrig.loop.run_command", "run the rig daemon (mrrig run --config configs/rig.toml)"),
    "sim": ("firmware_sim.__main__", "run the simulated rig firmware"),
    "bridge": ("mrrig.rigio.canbus.bridge", "serve a virtual CAN channel on 127.0.0.1"),
    "status": ("mrrig.cli.client", "print the daemon's status (Zenoh)"),
    "arm": ("mrrig.cli.client", "arm the daemon for one lease (--hold: until Ctrl-C)"),
    "disarm": ("mrrig.cli.client", "disarm the daemon: commands become SAFE 0 A"),
    "reset": ("mrrig.cli.client", "acknowledge the daemon's FAULT (to IDLE), before arm"),
    "watch": ("mrrig.cli.client", "live numbers from the daemon's telemetry"),
    "send-force": ("mrrig.cli.client", "stream a desired-force profile to the daemon"),
    "control": ("mrrig.cli.client", "send one JSON control request and print the reply"),
    "review": ("mrrig.cli.review", "print the metrics of a Rerun recording (.rrd)"),
    "export": ("mrrig.cli.export", "a recording as Parquet, CSV or MDF4, columns with units"),
    "characterize": ("mrrig.offline.characterize", "run the characterization matrix on the rig"),
    "identify": ("mrrig.cli.identify", "a twin of a measured damper (Bouc-Wen fit): plant file"),
    "train": ("mrrig.cli.train", "train the forward network from recorded data"),
    "evaluate": ("mrrig.offline.evaluate", "a forward model's Et and inverse RMSE on data, --plot"),
    "validate": ("mrrig.offline.validate", "force-tracking validation of a model on the rig"),
    "bench": (
        "mrrig.offline.bench.cli",
        "benchmarks: paper, drift, loop, matrix, estimation, inversion, train",
    ),
    "certs": ("mrrig.rigio.certs", "a lab CA and certificates for Zenoh mutual TLS (init, issue)"),
    "router": ("mrrig.rigio.router", "a Zenoh router where a fleet of rigs and their clients meet"),
    "rigs": ("mrrig.rigio.fleet", "list the live rigs: state, controller, fault (Zenoh)"),
    "runs": ("mrrig.cli.runs", "the run catalog: find, show, compare, sync and register runs"),
    "dbc": ("mrrig.cli.dbc", "check a rig profile (DBC + [can.signals]); show its mapping"),
    "test": ("mrrig.cli.test", "run a test plan (TOML steps with criteria) on a live rig"),
    "compare": ("mrrig.cli.compare", "the paper's controllers on your damper, Et side by side"),
    "tune": ("mrrig.cli.tune", "tune the controller's free parameters by closed-loop trials"),
    "hil": ("mrrig.cli.hil", "a hybrid simulation scenario (quarter car, building): --reference"),
}


GLOBAL_FLAGS = {"--debug": "debug", "-q": "quiet", "--quiet": "quiet"}


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("mrrig")
    except PackageNotFoundError:
        return "unknown (not installed)"


def split_global_flags(argv: list[str]) -> tuple[set[str], list[str]]:
    """The global flags wherever they are (before `--`), and the rest in order."""
    found, rest = set(), []
    for k, arg in enumerate(argv):
        if arg == "--":
            rest += argv[k:]
            break
        if arg in GLOBAL_FLAGS:
            found.add(GLOBAL_FLAGS[arg])
        else:
            rest.append(arg)
    return found, rest


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(
        prog="mrrig", description=__doc__.splitlines()[0], formatter_class=HelpFormatter
    )
    ap.add_argument("--version", action="version", version=f"mrrig {version()}")
    ap.add_argument(
        "--debug", action="store_true", help="show tracebacks and debug logs (also after COMMAND)"
    )
    ap.add_argument(
        "-q", "--quiet", action="store_true", help="warnings and errors only (also after COMMAND)"
    )
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_) in COMMANDS.items():
        sub.add_parser(name, help=help_, add_help=False)
    flags, argv = split_global_flags(argv)
    # split at the subcommand: everything after it belongs to the subcommand's own parser
    head = []
    while argv and argv[0].startswith("-"):
        head.append(argv.pop(0))
    if argv:
        head.append(argv.pop(0))
    args = ap.parse_args(head)
    if args.command is None:
        ap.print_help()
        return 2
    debug, quiet = "debug" in flags, "quiet" in flags
    level = logging.DEBUG if debug else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    module_name, _ = COMMANDS[args.command]
    if args.command == "run":
        from mrrig.loop import memory

        memory.set_environment()  # before numpy loads OpenBLAS: what the locked loop needs
    try:
        module = importlib.import_module(module_name)
        if module_name == "mrrig.cli.client":
            return int(module.main([args.command, *argv]) or 0)
        return int(module.main(argv) or 0)
    except KeyboardInterrupt as exc:
        from mrrig.interruption import what

        logging.getLogger("mrrig").warning("interrupted (%s)", what(exc))
        return 130
    except BrokenPipeError:
        return _quiet_broken_pipe()
    except Exception as exc:  # noqa: BLE001 - the CLI's one-line error contract
        if debug or not _is_ordinary(exc):
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2


def _quiet_broken_pipe() -> int:
    """The reader went away (`| head`): no traceback, and no second one when Python flushes
    stdout at exit. 141 is what a shell reports for a process ended by SIGPIPE."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return 141


def _is_ordinary(exc: BaseException) -> bool:
    """User-facing errors: mrrig's own (`MrrigError`) and the builtins of bad input (ValueError,
    OSError, LookupError) that reach here from libraries."""
    return isinstance(exc, MrrigError | ValueError | OSError | LookupError)
