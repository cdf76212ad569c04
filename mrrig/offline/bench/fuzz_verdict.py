"""`mrrig bench fuzz`'s verdict: the counts that fail a run, the motion beyond the limits in
force at arming, and the printed report (mrrig/offline/bench/fuzz.py runs the campaign)."""

from __future__ import annotations

from typing import Any

from mrrig.offline.bench import fuzz_faulty_bus, fuzz_observer

# The armed motion's tolerances: the firmware's ramp (0.5 s) moves at most 0.16 mm and
# 0.08 Hz a period; a change the daemon sends just before the SAFE command that ends a
# stretch (a disarm and an actuator request taken between the same two frames) shows for up
# to 3 periods
MOTION_TOL_M = 0.0005
FREQUENCY_TOL_HZ = 0.25


def motion_beyond_limits(armed_motion: list[dict], step_m: float) -> list[dict]:
    """The stretches of ACTIVE commands (the simulator's `armed_motion`) whose motion went
    beyond the limits in force when the rig was armed: an amplitude more than `step_m`
    (`control.armed_amplitude_step_m`) above the one in force at arming, or a frequency above
    that one (the daemon takes no frequency change while armed)."""
    return [
        m
        for m in armed_motion
        if m["amplitude_max_m"] > m["amplitude_at_start_m"] + step_m + MOTION_TOL_M
        or m["frequency_max_hz"] > m["frequency_at_start_hz"] + FREQUENCY_TOL_HZ
    ]


def failures(result: dict[str, Any], i_max_a: float) -> list[str]:
    """The counts of `result` that are not 0, by name."""
    names = [
        "crashes", "commands_above_limit", "desired_force_out_of_range", "motion_beyond_limits",
        "active_applied_to_stale", "active_applied_to_invalid", "active_answers_invalid",
        "requests_unanswered",
    ]  # fmt: skip
    out = [n for n in names if result[n]]
    out += [n for n in ("armed_without_lease", "faulty_bus_not_aborted") if result.get(n)]
    out += [n for n in ("runs_missing_from_catalog",) if result.get(n)]
    if result["max_commanded_current_a"] > i_max_a + 1e-4:
        out.append("max_commanded_current_a")
    if "observer_misuse" in result:
        out += fuzz_observer.failures(result["observer_misuse"])
    return out


def report(r: dict) -> str:
    lat = r["answer_latency_p99_us"]
    signals = ", ".join(f"{s['signal']} {s['outcome']}" for s in r["signals"])
    age = r["applied_active_age_us_max"]
    return "\n".join(
        [
            f"bench fuzz: {r['minutes']:g} min against a live rig (bridge, firmware_sim, daemon)",
            f"  frames fuzzed {r['frames_fuzzed']}, requests {r['requests']} "
            f"(burst {r['burst']['requests']}), commands seen {r['commands']}, "
            f"re-arms {r['rearms']}, daemon starts {r['daemon_starts']}",
            f"  request sequences {r['sequences']}",
            f"  signals: {signals}",
            f"  crashes {len(r['crashes'])} {r['crashes']}",
            f"  commands above the limit {r['commands_above_limit']} "
            f"(max commanded {r['max_commanded_current_a']:.4f} A), "
            f"desired force outside loop.f_range_n {r['desired_force_out_of_range']}",
            f"  motion beyond the limits in force at arming {r['motion_beyond_limits']} "
            f"(of {r['armed_stretches']} armed stretches) {r['motion_beyond']}",
            f"  ACTIVE commands the firmware applied to stale frames "
            f"{r['active_applied_to_stale']}, to invalid frames "
            f"{r['active_applied_to_invalid']} (frame age when applied: max "
            f"{'n/a' if age is None else f'{age:.0f} us'}); late commands it dropped "
            f"{r['late_commands_dropped']}; ACTIVE answers that reached the bus over the age "
            f"limit {r['active_answers_stale_at_bus']}, to no genuine frame "
            f"{r['active_answers_invalid']}",
            f"  control requests unanswered {r['requests_unanswered']}",
            f"  clients killed while armed {r['clients_killed']} (never armed"
            f" {r['clients_never_armed']}): armed without a live lease beyond its timeout"
            f" {r['armed_without_lease']}, left ARMED after a kill max"
            f" {_seconds(r['left_armed_after_kill_s_max'])}",
            f"  a client's step on a faulty bus (the simulator held up {fuzz_faulty_bus.STALL_S:g}"
            f" s every {fuzz_faulty_bus.STALL_EVERY_S:g} s) {r['faulty_bus_episodes']} times"
            f" (never armed {r['faulty_bus_never_armed']}, {r['faulty_bus_stalls']} stalls):"
            f" aborted 'faulty bus' {r['faulty_bus_aborted']}, not aborted"
            f" {r['faulty_bus_not_aborted']} {r['faulty_bus_not_aborted_how']}",
            f"  runs missing from the catalog {len(r['runs_missing_from_catalog'])} of"
            f" {r['recordings']} recordings {r['runs_missing_from_catalog'][:5]}",
            f"  answer latency p99 as the firmware sees it: quiet {lat['quiet']:.0f} us, "
            f"burst {lat['burst']:.0f} us, ratio {lat['ratio']:.2f} (target <= 1.5)",
            f"  daemon: {r['daemon']}",
            f"  faults: {dict(r['faults'])}",
        ]
    )


def _seconds(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f} s"
