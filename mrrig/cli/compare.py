"""`mrrig compare --sim | --rig NAME`: the paper's controllers (Heaviside, continuous state,
the supervised inverse MLP, the RNN, network inversion) on the lab's own damper in one
command, the passive extremes (0 A, full current) beside them, and their Et side by side.

It writes a test plan (one step per controller on the same stroke and desired force; `--plan-out`,
default recordings/compare-<UTC>.toml), runs it as `mrrig test` does (each step a run of the
catalog; `--junit`, `--html`), and prints the table: Et, its ratio to the best controller's and
to the better passive extreme's, peak current, latency. Network inversion runs the daemon's own
forward model; `--supervised-model` and `--rnn-model` add those two with their inverse models.

Exit codes: 0 every step ran without a fault (whatever its Et); 1 a step faulted or was
aborted; 2 the comparison could not run (a bad option, no rig).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
from pathlib import Path

from mrrig.cli.test import add_run_arguments, run_on, simulated_rig
from mrrig.cli_args import HelpFormatter, output_file
from mrrig.compare import (
    DEFAULT_ACTUATOR,
    PAPER_ORDER,
    CompareError,
    Comparison,
    plan_text,
    rows,
    table,
)


def main(argv: list[str] | None = None) -> int:
    from mrrig.cli.main import version
    from mrrig.config import load_config
    from mrrig.plans.plan import load_plan

    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig compare", description=__doc__
    )
    ap.add_argument("--rig", help="a live rig's name (or --sim)")
    ap.add_argument(
        "--controllers",
        default="heaviside,continuous_state,network_inversion",
        help=f"comma-separated, of {', '.join(PAPER_ORDER)}",
    )
    ap.add_argument("--gain", type=float, help="continuous_state's G (A/N, eq. 39)")
    ap.add_argument("--b", type=float, help="continuous_state's B (eq. 39)")
    ap.add_argument("--on-current", type=float, help="heaviside's current when on (A)")
    ap.add_argument("--supervised-model", type=Path, help="the supervised inverse MLP's model")
    ap.add_argument("--rnn-model", type=Path, help="the RNN's model")
    ap.add_argument("--duration", type=float, default=10.0, help="each step's length (s)")
    ap.add_argument("--settle", type=float, default=2.0, help="each step's settling (s)")
    ap.add_argument(
        "--amplitude-m", type=float, default=DEFAULT_ACTUATOR["amplitude_m"], help="sine stroke"
    )
    ap.add_argument(
        "--frequency-hz", type=float, default=DEFAULT_ACTUATOR["frequency_hz"], help="its rate"
    )
    ap.add_argument("--no-passive", action="store_true", help="leave out the passive extremes")
    ap.add_argument("--plan-out", type=output_file, help="where the plan is written")
    add_run_arguments(ap)
    args = ap.parse_args(argv)
    if args.sim == (args.rig is not None):
        ap.error("give --sim or --rig NAME")

    names = [n.strip() for n in args.controllers.split(",") if n.strip()]
    settings: dict[str, dict] = {}
    if args.gain is not None or args.b is not None:
        settings["continuous_state"] = {
            k: v for k, v in (("gain", args.gain), ("b", args.b)) if v is not None
        }
    if args.on_current is not None:
        settings["heaviside"] = {"on_current_a": args.on_current}
    for name, model in (("supervised", args.supervised_model), ("rnn", args.rnn_model)):
        if model is not None:
            settings[name] = {"model": str(model.resolve())}
            if name not in names:
                names.append(name)
    comparison = Comparison(
        controllers=names,
        settings=settings,
        actuator={
            **DEFAULT_ACTUATOR,
            "amplitude_m": args.amplitude_m,
            "frequency_hz": args.frequency_hz,
        },  # fmt: skip
        duration_s=args.duration,
        settle_s=args.settle,
        i_max_a=load_config(args.config).loop.i_max_a,
        passive=not args.no_passive,
    )
    try:
        text = plan_text(comparison, rig=args.rig)
    except CompareError as exc:
        ap.error(str(exc))
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    out = args.plan_out or Path("recordings") / f"compare-{stamp}.toml"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(f"plan: {out} (run it again: mrrig test {out} ...)", flush=True)
    plan = load_plan(out)
    with contextlib.ExitStack() as stack:
        if args.sim:
            rig_name, args.zenoh_config = stack.enter_context(
                simulated_rig(args.config, args.sim_config, args.zenoh_config)
            )
        else:
            rig_name = args.rig
        code, results = run_on(plan, rig_name, args, version())
    print(f"\nthe controllers side by side on rig {rig_name}:")
    print(table(rows(results)))
    return code
