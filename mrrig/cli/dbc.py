"""`mrrig dbc`: a rig profile (the lab's DBC and `[can.signals]`) as the daemon will use it.

    mrrig dbc check FILE --config CFG   every problem, one line each; exit 2 if any
    mrrig dbc show [FILE] --config CFG  the roles, their messages, IDs, units and periods

FILE is the DBC (default: the config's `[can] dbc`, else the CAN contract's); CFG the daemon
config whose `[can.signals]` and `loop.period_s` go with it. Problems: an unknown unit, an
unmapped role, an ID two messages share, a frame its signals overflow, a period that
disagrees, a scale or offset that cannot be computed with, an actuator message without its
waveform, a signal that cannot carry its limit (the command current up to loop.i_max_a, the
force over loop.f_range_n, the displacement over loop.x_range_m, ...: mrrig/rigio/canbus/
profile.py, profile_limits.py).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mrrig.cli_args import HelpFormatter
from mrrig.config import load_config
from mrrig.rigio.canbus.profile import ROLES, RigProfile, check_profile
from mrrig.rigio.canbus.profile_limits import daemon_limits

USAGE_EXIT = 2


def _profile(args: argparse.Namespace) -> tuple[RigProfile | None, list[str], str]:
    cfg = load_config(args.config)
    dbc = args.file if args.file is not None else cfg.can.dbc
    profile, problems = check_profile(
        dbc, cfg.can.signals, cfg.loop.period_s, str(cfg.source), daemon_limits(cfg)
    )
    return profile, problems, str(dbc or "the CAN contract's mrrig.dbc")


def _show(profile: RigProfile) -> str:
    lines = [f"{'role':<20} {'message.signal':<34} {'ID':>10}  unit -> SI"]
    for name in ROLES:
        m = profile.mapped.get(name)
        if m is None:
            lines.append(f"{name:<20} {'absent':<34}")
            continue
        lay = profile.codec.layout(m.message)
        ident = f"0x{lay.frame_id:08X}" if lay.is_extended else f"0x{lay.frame_id:03X}"
        unit = f"{m.unit or '-'} x {m.factor:g}"
        lines.append(f"{name:<20} {m.message + '.' + m.signal:<34} {ident:>10}  {unit}")
    lines.append("")
    for group, message in (
        ("sensors (answered)", profile.sensor_message),
        ("status", profile.status_message),
        ("command (sent)", profile.command_message),
        ("actuator (sent)", profile.actuator_message),
        ("setpoint (sent)", profile.setpoint_message),
    ):
        if message is None:
            lines.append(f"{group}: none")
            continue
        lay = profile.codec.layout(message)
        period = f"{lay.period_s * 1e3:g} ms" if lay.period_s else "period from the config"
        fmt = ("29-bit" if lay.is_extended else "11-bit") + (", CAN FD" if lay.is_fd else "")
        e2e = f"E2E profile 2 (Data ID {lay.data_id})" if lay.e2e else "no E2E"
        lines.append(f"{group}: {message}, {lay.length} bytes, {fmt}, {period}, {e2e}")
    lines.append(profile.startup_line())
    if (unmapped := profile.unmapped_line()) is not None:
        lines.append(unmapped)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="mrrig dbc", description=__doc__, formatter_class=HelpFormatter
    )
    sub = ap.add_subparsers(dest="action", required=True)
    for action, text in (
        ("check", "every problem of the profile, one line each (exit 2 if any)"),
        ("show", "the mapping as the daemon will use it"),
    ):
        p = sub.add_parser(action, help=text, formatter_class=HelpFormatter)
        p.add_argument("file", type=Path, nargs="?", help="the DBC (default: the config's)")
        p.add_argument("--config", type=Path, required=True, help="daemon config (TOML)")
    args = ap.parse_args(argv)
    profile, problems, dbc = _profile(args)
    for line in problems:
        print(line)
    if profile is None:
        return USAGE_EXIT
    if args.action == "show":
        print(_show(profile))
    else:
        print(f"{dbc}: ok; {profile.startup_line()}")
        if (unmapped := profile.unmapped_line()) is not None:
            print(unmapped)
    return 0
