"""`mrrig hil`: a real-time hybrid simulation scenario (the HIL specification; configs/hil/*.toml).

    mrrig hil SCENARIO --reference            the scenario all-numerically: the simulator's own
                                              damper model (Bouc-Wen) in place of the rig, the
                                              law's force through that model's inverse
    mrrig hil SCENARIO --reference --table    every law on the scenario's road (quarter car):
                                              RMS body acceleration, suspension travel and tyre
                                              load, and their % change against passive-soft and
                                              passive-hard
    mrrig hil SCENARIO --reference --stroke-limit-mm 40
                                              exit 2 (one line) if the reference's stroke goes
                                              past the rig's (or its force past --force-limit-n)
    mrrig hil SCENARIO --sim [--compensation none]
                                              on the simulated rig (bridge, firmware_sim, a
                                              daemon running the scenario): J1-J3, the
                                              response errors against the reference (with the
                                              daemon's controller path: its --config's
                                              controller, current clamp and slew limit), figures
    mrrig hil SCENARIO --rig NAME             the same on a rig whose daemon runs [hil]
    mrrig hil STROKE.csv --sim [--law passive-hard]
                                              displacement playback: the actuator plays a
                                              recorded stroke (t_s, x_m[, v_m_s]) resampled to
                                              the loop, refused in one line before anything
                                              moves where it passes the actuator's stroke,
                                              velocity or acceleration (naming the first frame);
                                              the damper at 0 A (or damper.i_max_a); J1-J3 and
                                              the force against the reference

The reference is what a HIL run of the same scenario should give: its stroke and force envelope
say whether the scenario fits the rig before anything moves.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shutil
import tempfile
from pathlib import Path

from mrrig.api.hil import daemon_command, measured_apart
from mrrig.cli_args import HelpFormatter, positive
from mrrig.errors import MrrigError
from mrrig.hil.laws import LAWS
from mrrig.hil.measured_stalls import counted
from mrrig.hil.metrics import AFTER_STALL_S, StallApart, WindowsApart, too_fast
from mrrig.hil.playback import ActuatorLimits, infeasibility
from mrrig.hil.reference import (
    SIM_PLANT_PRESET,
    DaemonCommand,
    envelope_problem,
    law_table,
    percent_change,
    run_reference,
)
from mrrig.hil.scenario import Scenario, load_scenario

log = logging.getLogger(__name__)


def _title(path: Path, s: Scenario, law: str, command: DaemonCommand | None = None) -> str:
    if s.kind == "quarter-car":
        what = f"quarter car, class {s.road.iso_class} road at {s.road.speed_m_s:g} m/s"
    elif s.kind == "playback":
        what = f"playback of the stroke {s.playback.file}"
    else:
        what = (
            f"{len(s.building.masses_kg)}-storey building, Kanai-Tajimi ground motion "
            f"(PGA {s.ground.pga_m_s2:g} m/s^2)"
        )
    return (
        f"{path}: {what}, {law}, {s.duration_s:g} s ({s.steps} frames of {s.period_s * 1e3:g} ms); "
        f"reference: firmware_sim's Bouc-Wen damper ({SIM_PLANT_PRESET}, 0-{s.damper.i_max_a:g} A)"
        + (", its exact inverse" if command is None else f", the daemon's {command.name}")
    )


def _summary(fig: dict[str, float], s: Scenario) -> list[str]:
    lines = []
    if s.kind == "quarter-car":
        for label, key, scale, unit in (
            ("body acceleration", "body_acceleration_m_s2", 1.0, "m/s^2"),
            ("suspension travel", "suspension_travel_m", 1e3, "mm"),
            ("dynamic tyre load", "tyre_load_n", 1.0, "N"),
        ):
            lines.append(
                f"{label:<18} RMS {fig['rms_' + key] * scale:9.4g} {unit:<6}"
                f"  peak {fig['peak_' + key] * scale:9.4g} {unit}"
            )
    elif s.kind == "playback":
        lines.append(
            f"{'damper force':<18} RMS {fig['rms_force_n']:9.4g} {'N':<6}"
            f"  peak {fig['peak_force_n']:9.4g} N"
        )
    else:
        for j in range(1, len(s.building.masses_kg) + 1):
            lines.append(
                f"storey {j}  drift RMS {fig[f'rms_drift_m_{j}'] * 1e3:7.4g} mm"
                f"  peak {fig[f'peak_drift_m_{j}'] * 1e3:7.4g} mm"
                f"   acceleration RMS {fig[f'rms_acceleration_m_s2_{j}']:7.4g} m/s^2"
                f"  peak {fig[f'peak_acceleration_m_s2_{j}']:7.4g} m/s^2"
            )
    lines.append(
        f"envelope           |stroke| <= {fig['max_abs_stroke_m'] * 1e3:.4g} mm, "
        f"|force| <= {fig['max_abs_force_n']:.4g} N; the damper took {fig['dissipated_j']:.4g} J"
    )
    return lines


def _table(scenario: Scenario) -> list[str]:
    rows = law_table(scenario)
    by_name = {r.law: r for r in rows}
    soft, hard = by_name["passive-soft"], by_name["passive-hard"]
    head = (
        f"{'law':<16} {'acc RMS m/s^2':>13} {'travel RMS mm':>13} {'tyre RMS N':>10}"
        f" {'|s| max mm':>10}"
        f"   % vs passive-soft (acc travel tyre)   % vs passive-hard (acc travel tyre)"
    )
    lines = [head]
    for r in rows:
        values = (r.rms_body_acceleration_m_s2, r.rms_suspension_travel_m, r.rms_tyre_load_n)
        vs = []
        for passive in (soft, hard):
            against = (
                passive.rms_body_acceleration_m_s2,
                passive.rms_suspension_travel_m,
                passive.rms_tyre_load_n,
            )
            pct = [percent_change(v, a) for v, a in zip(values, against, strict=True)]
            vs.append(" ".join(f"{p:+7.1f}" for p in pct))
        lines.append(
            f"{r.law:<16} {values[0]:13.4f} {values[1] * 1e3:13.3f} {values[2]:10.1f}"
            f" {r.max_abs_stroke_m * 1e3:10.1f}"
            f"   {vs[0]:<35}   {vs[1]}"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="mrrig hil", description=__doc__, formatter_class=HelpFormatter
    )
    ap.add_argument(
        "scenario",
        type=Path,
        help="scenario file (configs/hil/*.toml), or a stroke CSV to play (t_s, x_m[, v_m_s])",
    )
    where = ap.add_mutually_exclusive_group(required=True)
    where.add_argument(
        "--reference",
        action="store_true",
        help="run the scenario all-numerically (the simulator's damper model for the rig)",
    )
    where.add_argument(
        "--sim",
        action="store_true",
        help="on the simulated rig (bridge, firmware_sim, a daemon running the scenario)",
    )
    where.add_argument(
        "--rig", help="on this live rig, whose daemon runs the scenario ([hil] scenario)"
    )
    ap.add_argument(
        "--compensation",
        choices=("none", "polynomial", "adaptive", "model"),
        help="--sim: this delay compensation in place of the scenario's",
    )
    ap.add_argument(
        "--config", type=Path, default=Path("configs/rig.toml"), help="--sim: the daemon's config"
    )
    ap.add_argument(
        "--tries",
        type=int,
        default=3,
        metavar="N",
        help="--sim/--rig: runs in all where a run ends by a transport fault (a stall)",
    )
    ap.add_argument(
        "--sim-config", type=Path, default=Path("configs/sim.toml"), help="--sim: the simulator's"
    )
    ap.add_argument(
        "--zenoh-config",
        type=Path,
        help="--rig: the Zenoh client config (default configs/zenoh-client.json5); --sim: the"
        " client's, the daemon then on its config's (default: both on a free 127.0.0.1 port)",
    )
    ap.add_argument("--law", choices=LAWS, help="this law in place of the scenario's")
    ap.add_argument("--duration", type=positive, metavar="S", help="seconds, for the file's")
    ap.add_argument(
        "--table", action="store_true", help="every law on the scenario (quarter car), %% change"
    )
    ap.add_argument(
        "--stroke-limit-mm",
        type=positive,
        metavar="MM",
        help="exit 2 if the reference's stroke goes past it (firmware_sim's actuator: 40)",
    )
    ap.add_argument(
        "--force-limit-n",
        type=positive,
        default=6000.0,
        metavar="N",
        help="with --stroke-limit-mm: the force the rig's load cell takes",
    )
    args = ap.parse_args(argv)
    scenario = load_scenario(args.scenario, law=args.law)
    if args.duration is not None:
        scenario = dataclasses.replace(scenario, duration_s=args.duration)
        try:
            scenario.check()  # a playback's record is this long
        except ValueError as exc:
            raise MrrigError(f"--duration: {args.scenario}: {exc}") from None
    if args.table:
        if scenario.kind != "quarter-car":
            ap.error("--table: the law table is the quarter car's (skyhook, groundhook, ...)")
        print(_title(args.scenario, scenario, "every law"))
        print("\n".join(_table(scenario)))
        return 0
    if args.compensation is not None and not args.sim:
        ap.error("--compensation: only with --sim (a live rig's daemon keeps its own [hil])")
    if args.table and not args.reference:
        ap.error("--table: only with --reference")
    if args.sim and scenario.kind == "playback":  # before anything starts: the simulator's
        why = infeasibility(
            scenario.played_stroke(), _sim_limits(args), str(scenario.playback.file)
        )
        if why is not None:
            raise MrrigError(why)
    # --sim: the daemon's own controller path, so that the run and its reference differ only
    # by the rig; a live rig's daemon config is elsewhere: the exact inverse
    command = daemon_command(args.config) if args.sim else None
    run = run_reference(scenario, command=command)
    if args.sim or args.rig:
        return _live(args, scenario, run, command)
    figures = run.figures()
    print(_title(args.scenario, scenario, scenario.law))
    print("\n".join(_summary(figures, scenario)))
    if args.stroke_limit_mm is not None:
        problem = envelope_problem(figures, args.stroke_limit_mm * 1e-3, args.force_limit_n)
        if problem is not None:
            raise MrrigError(f"{args.scenario}: {problem}: it does not fit the rig")
    return 0


def _stall_line(s: StallApart) -> str:
    """J2 and J3 apart from the frames a measured stall of the loop explains."""
    return (
        f"  apart from {s.excluded} frames within {AFTER_STALL_S * 1e3:g} ms after one of "
        f"{s.stalls} measured stalls (a frame answered or delivered late): "
        f"J2 {s.j2_pct:.2f} %   J3 {s.j3_pct:.2f} %; the largest error at {s.peak_t_s:.2f} s, "
        + ("after a stall" if s.peak_after_stall else "no stall before it")
    )


def _read_measured(work: Path, into: dict[str, dict]) -> None:
    """The stopped simulator's stats and daemon's summary (`work`), where both were written."""
    try:
        into["sim_stats"] = json.loads((work / "sim.json").read_text())
        into["daemon_summary"] = json.loads((work / "daemon.json").read_text())
    except (OSError, ValueError) as exc:
        log.warning("the run's measured stalls are not known (%s): no J3 apart from them", exc)
        into.clear()


def _measured_line(s: WindowsApart, windows: list) -> str:
    """J2 and J3 apart from the stalls the actuator, the simulator and the kernel measured."""
    where = f"inside {s.peak_window}" if s.peak_window else "no measured stall there"
    return (
        f"  apart from {s.excluded} frames in or within {AFTER_STALL_S * 1e3:g} ms after "
        f"{len(s.windows)} measured stall windows ({counted(windows)}): J2 {s.j2_pct:.2f} %   "
        f"J3 {s.j3_pct:.2f} % (at {s.kept_peak_t_s:.2f} s); the largest error at "
        f"{s.peak_t_s:.2f} s, {where}"
    )


def _too_fast_line(args: argparse.Namespace, scenario: Scenario, reference) -> str | None:
    """Where the reference's stroke asks more speed than the simulated actuator has."""
    limit = _sim_limits(args).velocity_m_s
    fast = too_fast(reference.stroke_m, scenario.period_s, limit)
    if fast is None:
        return None
    return (
        f"  the reference's stroke asks up to {fast.peak_m_s:.2f} m/s (at {fast.peak_t_s:.2f} s; "
        f"{fast.frames} frames past the actuator's {limit:g} m/s): the piston falls behind "
        "there, whatever the compensation"
    )


def _sim_limits(args: argparse.Namespace) -> ActuatorLimits:
    """What the simulated rig's actuator plays: the tighter of the daemon config's `[hil]`
    limits and the simulator's stroke and servo flow limit (its config's `[actuator]`,
    read as TOML: the rig service never imports the simulator; firmware_sim's defaults)."""
    from mrrig.config import load_config
    from mrrig.loop.hil_loop import playback_limits
    from mrrig.typed_config import load_toml

    rig = playback_limits(load_config(args.config).hil)
    actuator = load_toml(args.sim_config).get("actuator", {})
    stroke = float(actuator.get("stroke_m", 0.04))
    velocity = float(actuator.get("servo", {}).get("velocity_limit_m_s", 1.0))
    return ActuatorLimits(
        min(rig.stroke_m, stroke), min(rig.velocity_m_s, velocity), rig.acceleration_m_s2
    )


def _live(
    args: argparse.Namespace, scenario: Scenario, reference, command: DaemonCommand | None
) -> int:
    """The scenario on the simulated or a live rig, judged against `reference`."""
    import contextlib

    from mrrig.api.hil import run_on_rig
    from mrrig.cli.test import simulated_rig

    problem = envelope_problem(reference.figures(), 0.04, args.force_limit_n)
    if problem is not None:  # the simulator's stroke; a live rig's daemon checks its own
        raise MrrigError(f"{args.scenario}: {problem}: it does not fit the rig")
    where = "the simulated rig" if args.sim else f"rig {args.rig}"
    print(_title(args.scenario, scenario, scenario.law, command) + f"; on {where}", flush=True)
    measured: dict[str, dict] = {}  # the simulator's stats and the daemon's summary, once stopped
    with contextlib.ExitStack() as stack:
        rig_name = args.rig
        if args.sim:
            work = Path(tempfile.mkdtemp(prefix="mrrig-hil-"))
            stack.callback(shutil.rmtree, work, True)  # last: after the files are read
            stack.callback(_read_measured, work, measured)  # once the processes stopped
            daemon_args = ["--hil", str(args.scenario), "--hil-duration", repr(scenario.duration_s)]
            daemon_args += ["--hil-law", scenario.law, "--summary-json", str(work / "daemon.json")]
            if args.compensation is not None:
                daemon_args += ["--hil-compensation", args.compensation]
            # its stats, not --measure-echo: its own frames echoed would load the bridge
            sim_args = ("--stats", str(work / "sim.json"))
            rig_name, args.zenoh_config = stack.enter_context(
                simulated_rig(
                    args.config,
                    args.sim_config,
                    args.zenoh_config,
                    daemon_args=tuple(daemon_args),
                    sim_args=sim_args,
                )  # fmt: skip
            )
        elif args.zenoh_config is None:
            from mrrig.rigio.client import DEFAULT_CONFIG

            args.zenoh_config = DEFAULT_CONFIG
        result = run_on_rig(
            rig_name, scenario, reference, args.zenoh_config, lambda s: print(s, flush=True),
            tries=args.tries,
        )  # fmt: skip
    end = result.end
    h = end["hil"]
    t = result.tracking
    print(
        f"run: {h['k']} model frames, {h['setpoints_sent']} setpoints sent; "
        f"{result.frames} frames in the telemetry ({result.missing} missing), "
        f"compensation {h['compensation']}, delay estimate {result.delay_s * 1e3:.2f} ms; "
        f"ended: {h['ended'] or '-'}"
    )
    for why in result.retried:
        print(f"run again after a transport fault: {why}")
    if t is not None:
        print(f"J1 {t.j1_ms:.2f} ms   J2 {t.j2_pct:.2f} %   J3 {t.j3_pct:.2f} %")
        print(_stall_line(result.apart))
        if len(measured) == 2 and result.samples is not None:
            try:
                apart = measured_apart(result.samples, **measured, period_s=scenario.period_s)
                print(_measured_line(*apart))
            except ValueError as exc:  # every frame in a window
                print(f"  apart from the measured stall windows: {exc}")
        if args.sim and (fast := _too_fast_line(args, scenario, reference)) is not None:
            print(fast)
    for name, e in result.errors.items():
        hil_rms, ref_rms = result.figures[name]
        print(
            f"{name:<24} RMS {hil_rms:9.4g} (reference {ref_rms:9.4g}): RMS error "
            f"{e.rms_of_rms_pct:+.2f} %, sample-wise {e.rms_pct:.2f} % RMS, {e.peak_pct:.2f} % peak"
        )
    fault = end.get("fault")
    print(
        f"rig: {end['state']}, fault {fault or 'none'}"
        + (f" ({end.get('fault_reason')})" if fault else "")
        + f"; sensor frames {end['sensor_frames_valid']}, commands {end['commands_sent']}"
    )
    return 1 if fault else 0
