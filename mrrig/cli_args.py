"""argparse types for the numeric and output-file flags: a bad value stops the command at
parsing with a one-line error naming the flag (`argument --epochs: must be >= 1, got -3`),
before anything starts or trains, so a long run does not end in an error about its report."""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Every option's default in its help (`(default: 2.0)`), unless the help already says it
    or there is none to say (a flag, an unset optional value); descriptions keep their lines."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if "default" in text or action.default in (None, False, argparse.SUPPRESS, []):
            return text
        return super()._get_help_string(action)


def add_bus_options(ap: argparse.ArgumentParser, what: str = "bus.") -> None:
    """python-can's names for the bus (`-i/--interface`, `-c/--channel`, as in can.logger);
    `--bus-interface`/`--bus-channel` stay as aliases."""
    ap.add_argument(
        "-i",
        "--interface",
        "--bus-interface",
        dest="bus_interface",
        metavar="INTERFACE",
        help=f"python-can interface: socketcan, remote, virtual, ... (overrides {what}interface)",
    )
    ap.add_argument(
        "-c",
        "--channel",
        "--bus-channel",
        dest="bus_channel",
        metavar="CHANNEL",
        help=f"python-can channel: can0, ws://127.0.0.1:54701/, ... (overrides {what}channel)",
    )


def int_at_least(low: int) -> Callable[[str], int]:
    """An integer >= `low` (a seed >= 0, an epoch limit >= 1)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    return parse


def output_file(text: str) -> Path:
    """A file to write at the end (a report, a model, a figure): its folder is made now, and a
    path that cannot be written stops the command before its work, not after it."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder, not a file")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise argparse.ArgumentTypeError(
            f"cannot make the folder {path.parent}: {exc.strerror}"
        ) from None
    if not os.access(path if path.exists() else path.parent, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text}: not writable")
    return path


def port(text: str) -> int:
    """A TCP port, 1 to 65535."""
    value = int_at_least(1)(text)
    if value > 65535:
        raise argparse.ArgumentTypeError(f"must be <= 65535, got {value}")
    return value


def finite(text: str) -> float:
    """Any finite number (an offset, an amplitude)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text}")
    return value


def positive(text: str) -> float:
    """A finite number > 0 (a duration, a rate, a time constant)."""
    value = finite(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def non_negative(text: str) -> float:
    """A finite number >= 0 (a settling time, a noise level)."""
    value = finite(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


SEED = int_at_least(0)
COUNT = int_at_least(1)


def controllers_epilog() -> str:
    """The controllers by name (a `controller.name`, a `set_controller` request's `name`), each
    with its docstring's first line and whether it needs a model file: for `--help`."""
    from mrrig.loop.controllers import CONTROLLERS

    width = max(map(len, CONTROLLERS))
    lines = [
        f"  {name:<{width}}  {(cls.__doc__ or '').strip().splitlines()[0]}"
        + ("  [needs a model file]" if cls.needs_model else "")
        for name, cls in CONTROLLERS.items()
    ]
    return "controllers (controller.name):\n" + "\n".join(lines)
