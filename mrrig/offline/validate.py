"""`mrrig validate MODEL [MODEL...]`: force tracking on the rig by network inversion of each model.

The daemon runs with the rig config's force reference (bouc_wen or sine, ...) and actuator
motion; for each model: arm, wait `--settle` s, keep `--duration` s of samples, disarm, and
print the report (Et, tracking error, current, latency, faults). Models after the first are
switched in with the daemon's `set_model` control request while disarmed, without a restart.
With two models or more, the models' numbers are then printed side by side (`table`): Et and
its ratio to the best, tracking error, current, latency, faults.
A window whose faults are all transport faults (a stall past the sensor timeout or the
firmware's watchdog) is tried again, up to `--attempts` in all; the report keeps the faults of
the windows it discarded.
"""

from __future__ import annotations

import argparse
import datetime as dt
import logging
import math
import sys
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from mrrig import json_text
from mrrig.cli_args import HelpFormatter, int_at_least, non_negative, output_file, positive
from mrrig.config import load_config
from mrrig.loop.build import build_controller
from mrrig.loop.safety import TRANSPORT_FAULTS
from mrrig.loop.samples import RigState
from mrrig.loop.summary import format_summary, summarize
from mrrig.offline.characterize import (
    EXIT_INTERRUPTED,
    FLUSH_MARGIN_S,
    RETRY_PAUSE_S,
    register_tool_run,
)
from mrrig.rigio.rig_session import (
    Interrupted,
    RigError,
    RigSession,
    rig_overrides,
    stop_on_signals,
)
from mrrig.typed_config import ConfigError

log = logging.getLogger(__name__)


def _track(
    session: RigSession, settle_s: float, duration_s: float, stop: threading.Event
) -> tuple[dict[str, Any], bool]:
    """One force-tracking window with the daemon's current controller: its summary, and
    whether its faults (if any) are all transport faults."""
    session.request(cmd="disarm")
    session.take(np.inf, np.inf)  # drop what came before
    # a transport fault of the window before is acknowledged (the daemon logs which) to try
    # again: the tool's documented choice, explicit
    session.request(cmd="reset")
    session.request(cmd="arm")
    t_start = session.now() + settle_s
    t_end = t_start + duration_s
    try:
        session.wait_until(t_end + FLUSH_MARGIN_S, stop, fail_on_fault=False)
        session.wait_samples(t_end, stop)
    finally:
        session.request(cmd="disarm")
    s, events = session.take(t_start, t_end)
    summary = summarize(s, events)  # events since arming: a fault while settling counts too
    transport_only = all(e.get("fault") in TRANSPORT_FAULTS for e in events if e["kind"] == "fault")
    armed = s["state"] == RigState.ARMED
    i_meas = s["i_meas"][armed]
    summary["i_meas_a"] = {
        "mean": float(i_meas.mean()) if i_meas.size else float("nan"),
        "max": float(i_meas.max()) if i_meas.size else float("nan"),
    }
    return summary, transport_only


def track_with_attempts(
    session: RigSession,
    settle_s: float,
    duration_s: float,
    attempts: int,
    stop: threading.Event,
) -> dict[str, Any]:
    """A force-tracking window, tried again while its faults are all transport faults, up to
    `attempts` windows; the kept summary has `attempts` and the discarded windows' faults."""
    discarded: list[dict] = []
    for attempt in range(1, attempts + 1):
        summary, transport_only = _track(session, settle_s, duration_s, stop)
        if not summary["faults"] or not transport_only or attempt == attempts:
            break
        log.warning(
            "attempt %d of %d: a transport fault (%s): trying the window again",
            attempt,
            attempts,
            summary["faults"][0]["reason"],
        )
        discarded += summary["faults"]
        session.wait_until(session.now() + RETRY_PAUSE_S, stop, fail_on_fault=False)
    return {**summary, "attempts": attempt, "discarded_faults": discarded}


def format_report(r: dict[str, Any]) -> str:
    skip = ("model", "setup", "i_meas_a", "attempts", "discarded_faults")
    core = {k: v for k, v in r.items() if k not in skip}
    i_meas = r["i_meas_a"]
    lines = [
        f"model         {r['model']}",
        f"setup         {r['setup']}",
        format_summary(core),
        f"i_meas        mean {i_meas['mean']:.4g} A, max {i_meas['max']:.4g} A (armed)",
    ]
    if r["discarded_faults"]:
        lines.append(f"attempts      {r['attempts']}; the windows discarded for a transport fault:")
        lines += [f"  {f['reason']}" for f in r["discarded_faults"]]
    return "\n".join(lines)


def table(reports: list[dict[str, Any]]) -> str:
    """The models' numbers side by side, one row each in the order run: Et and its ratio to
    the lowest, |f_des - f_meas| p50 and p95 (N), measured current mean (A, armed), commanded
    current max (A), latency p99 (us), windows tried and faults."""
    ets = [r["et"] for r in reports if math.isfinite(r["et"])]
    best = min(ets) if ets else math.nan
    names = [Path(r["model"]).name for r in reports]
    if len(set(names)) < len(names):  # the same name in two folders: the paths tell them apart
        names = [r["model"] for r in reports]
    width = max(len("model"), *map(len, names))
    head = (
        f"{'model':<{width}} {'Et':>7} {'/best':>6} {'err p50 N':>9} {'err p95 N':>9}"
        f" {'i_meas A':>8} {'i_cmd max':>9} {'lat p99 us':>10} {'tries':>5} faults"
    )
    lines = ["models side by side:", head, "-" * len(head)]
    for name, r in zip(names, reports, strict=True):
        err = r["tracking_error_n"]
        lines.append(
            f"{name:<{width}} {_f(r['et'], '.4f'):>7} {_f(r['et'] / best, '.2f'):>6}"
            f" {_f(err['p50'], '.1f'):>9} {_f(err['p95'], '.1f'):>9}"
            f" {_f(r['i_meas_a']['mean'], '.3f'):>8} {_f(r['i_cmd_a']['max'], '.3f'):>9}"
            f" {_f(r['latency_us']['p99'], '.0f'):>10} {r['attempts']:>5} {len(r['faults'])}"
        )
    return "\n".join(lines)


def _f(v: float, fmt: str) -> str:
    return format(v, fmt) if math.isfinite(v) else "-"


def finish(reports: list[dict[str, Any]], json_path: Path | None) -> int:
    """After the last model: the side-by-side table (two models or more), the JSON, and the
    exit status (1 where a model's window faulted)."""
    if len(reports) >= 2:
        print(table(reports), flush=True)
    if json_path:
        json_path.write_text(json_text.dumps({"reports": reports}), encoding="utf-8")
    faulted = [r["model"] for r in reports if r["faults"]]
    if faulted:
        print(f"faults during the validation of: {', '.join(faulted)}", file=sys.stderr)
        return 1
    return 0


def _setup(cfg) -> str:
    r, a, c = cfg.reference, cfg.actuator, cfg.controller
    ref = f"reference {r.kind}"
    if r.kind == "bouc_wen":
        ref += (
            f" ({r.preset}, {r.current_a:g} A + {r.current_amp_a:g} A at {r.current_freq_hz:g} Hz)"
        )
    elif r.kind == "sine":
        ref += f" ({r.offset_n:g} N + {r.amplitude_n:g} N at {r.freq_hz:g} Hz)"
    fb = f", feedback tau {c.feedback_tau_s:g} s" if c.feedback_tau_s is not None else ""
    return (
        f"{ref}; actuator {a.waveform} {a.amplitude_m * 1e3:g} mm {a.frequency_hz:g} Hz; "
        f"inversion {c.method}{fb}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig validate", description=__doc__.splitlines()[0]
    )
    ap.add_argument("model", nargs="+", type=Path, help="forward model file(s) (mrrig train)")
    ap.add_argument(
        "--rig-config", type=Path, default=Path("configs/rig.toml"), help="daemon config (TOML)"
    )
    ap.add_argument("--duration", type=positive, default=10.0, help="kept per model, s")
    ap.add_argument("--settle", type=non_negative, default=1.0, help="after arming, not kept, s")
    ap.add_argument(
        "--attempts",
        type=int_at_least(1),
        default=3,
        help="windows per model while each meets only a transport fault",
    )
    ap.add_argument(
        "-c",
        "--channel",
        "--bus-channel",
        dest="bus_channel",
        help="python-can channel (overrides bus.channel of the rig config)",
    )
    ap.add_argument("--no-telemetry", action="store_true", help="no Zenoh telemetry")
    ap.add_argument("--json", type=output_file, help="write the reports (a list) as JSON")
    args = ap.parse_args(argv)
    overrides = rig_overrides(
        args.bus_channel,
        args.no_telemetry,
        controller={"name": "network_inversion", "model": str(args.model[0])},
        # the models named on this command line are switched in with set_model
        control={"model_dirs": sorted({str(p.parent) for p in args.model})},
    )
    cfg = load_config(args.rig_config, overrides)
    for path in args.model:  # a missing or unfit model stops here, before the rig moves
        build_controller(cfg, replace(cfg.controller, model=path))
    if cfg.actuator.waveform == "stop":
        raise ConfigError(f"{args.rig_config}: actuator.waveform: 'stop': nothing would move")
    reports: list[dict[str, Any]] = []
    with stop_on_signals() as stop:
        try:
            with RigSession(cfg) as session:
                for k, model in enumerate(args.model):
                    if k:
                        session.request(cmd="disarm")
                        session.request(cmd="set_model", path=str(model))
                    started_utc = dt.datetime.now(dt.UTC)
                    r = track_with_attempts(
                        session, args.settle, args.duration, args.attempts, stop
                    )
                    r = {"model": str(model), "setup": _setup(cfg), **r}
                    register_tool_run(
                        cfg,
                        started_utc,
                        plan="validate",
                        step=model.name,
                        controller=cfg.controller.name,
                        model=model,
                        summary=r,
                        verdict="fault" if r["faults"] else "ok",
                    )
                    r["clock_t0_s"] = session.clock_t0_s  # the faults' `t` on CLOCK_MONOTONIC
                    # the loop's own stalls (the kernel's): what explains a discarded fault
                    r["kernel_stalls"] = session.kernel_stalls()
                    reports.append(r)
                    print(format_report(r), flush=True)
        except Interrupted:
            print("interrupted: the rig is SAFE and the actuator stopped", file=sys.stderr)
            return EXIT_INTERRUPTED
        except RigError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
    return finish(reports, args.json)
