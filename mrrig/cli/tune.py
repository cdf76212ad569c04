"""`mrrig tune --rig NAME`: on-rig auto-tuning of network inversion's free parameters (the
exact solve's continuity, the load-cell feedback's time constant) by closed-loop trials.

Each candidate of the grid runs as a short closed-loop trial on a TUNING profile (random
motion, the Bouc-Wen reference damper's force with a moving current: the kind of signal the
model was trained on, never a validation case) through the rig's control plane, as a step of
`mrrig test` does; the smallest measured Et wins (a faulted trial never does: a transport
fault runs the trial once more after a reset). The trial table is printed and kept (JSON and
CSV beside the model, or --out); the chosen continuity is written into the model file's
meta.online_continuity (where the daemon reads it), the feedback time constant into a config
snippet beside it, and both are put in force on the rig. `--sim` starts the simulated rig
first, as `mrrig test --sim` does.

Exit codes: 0 chosen and written; 1 no usable trial, or interrupted (nothing written);
2 the rig or the arguments cannot be used.
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from mrrig.cli.test import add_sim_arguments
from mrrig.cli_args import HelpFormatter
from mrrig.interruption import stops_interrupt
from mrrig.rigio import client


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected numbers separated by commas: {text!r}"
        ) from None


def main(argv: list[str] | None = None) -> int:
    from mrrig.tune.rule import CONTINUITY_CANDIDATES, FEEDBACK_TAU_CANDIDATES_S

    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter, prog="mrrig tune", description=__doc__
    )
    ap.add_argument("--rig", help="the rig's name (with --sim: the simulated rig's)")
    ap.add_argument(
        "--zenoh-config",
        type=Path,
        help=f"Zenoh client config (default: {client.DEFAULT_CONFIG}; with --sim, both the"
        " client's and the daemon's on a free port of 127.0.0.1)",
    )
    ap.add_argument(
        "--model",
        help="the model file to tune (sent with every trial; default: the daemon's own)",
    )
    ap.add_argument(
        "--continuity",
        type=_floats,
        default=list(CONTINUITY_CANDIDATES),
        help="the continuities to try, comma-separated",
    )
    ap.add_argument(
        "--feedback-tau-s",
        type=_floats,
        default=list(FEEDBACK_TAU_CANDIDATES_S),
        help="the feedback time constants to try (s), comma-separated",
    )
    ap.add_argument("--duration", type=float, default=8.0, help="each trial's scored seconds")
    ap.add_argument("--settle", type=float, default=2.0, help="each trial's settling seconds")
    ap.add_argument(
        "--out",
        type=Path,
        help="the trial table's JSON file (a CSV beside it; default: MODEL.tune.json)",
    )
    ap.add_argument(
        "--dry-run",
        action="store_true",
        help="run the trials and print the choice, but write nothing into the model or config",
    )
    add_sim_arguments(ap)
    args = ap.parse_args(argv)
    if not (0 < args.duration <= 600 and 0 <= args.settle <= 60):
        ap.error("--duration: (0, 600] s; --settle: [0, 60] s")

    from mrrig.tune.rule import grid

    candidates = grid(args.continuity, args.feedback_tau_s)  # TuneError: one line, exit 2
    with contextlib.ExitStack() as stack:
        if args.sim:
            from mrrig.cli.test import SimError, simulated_rig

            rig_name, args.zenoh_config = stack.enter_context(
                simulated_rig(args.config, args.sim_config, args.zenoh_config)
            )
            if args.rig and args.rig != rig_name:
                raise SimError(f"--rig {args.rig}: the simulated rig ({args.config}) is {rig_name}")
        elif args.rig:
            rig_name = args.rig
        else:
            ap.error("--rig NAME (or --sim): which rig to tune")
        return _tune(rig_name, candidates, args)


def _tune(rig_name: str, candidates, args: argparse.Namespace) -> int:
    from dataclasses import replace

    from mrrig.api import Rig, default_catalog
    from mrrig.tune import trials as tr

    profile = replace(tr.DEFAULT_PROFILE, duration_s=args.duration, settle_s=args.settle)
    with Rig(rig_name, zenoh_config=args.zenoh_config) as rig:
        rig.status()  # no rig answering: one line, exit 2, before any trial
        model_path = _local_model(rig, args)
        with stops_interrupt():
            result = tr.run_trials(
                rig,
                candidates,
                profile,
                lambda line: print(line, flush=True),
                args.model,
                default_catalog(),
            )
        print(tr.table(result.trials, result.chosen))
        out = args.out or model_path.with_suffix(".tune.json")
        tr.write_trials(result, out, profile, rig_name)
        print(f"trial table: {result.files['trials']} and {result.files['trials_csv']}")
        if result.chosen is None:
            print(f"{result.why}: nothing chosen, nothing written (the rig is disarmed)")
            return 1
        c = result.chosen.candidate
        print(f"chosen: {tr.trial_line(result.chosen)}")
        if args.dry_run:
            print("--dry-run: nothing written")
            return 0
        tr.write_choice(result, model_path, rig_name)
        settings = tr.apply_choice(rig, result)
    print(
        f"wrote continuity {c.continuity:g} into {result.files['model']}"
        " (meta.online_continuity: the daemon takes it where [controller] sets no continuity)"
    )
    print(
        f"wrote [controller] feedback_tau_s {c.feedback_tau_s or 0.0:g} into"
        f" {result.files['config_snippet']} (merge it into the daemon's config)"
    )
    print(
        f"in force on rig {rig_name} now: continuity {settings.get('continuity')},"
        f" feedback {settings.get('feedback')}, feedback_tau_s {settings.get('feedback_tau_s')}"
    )
    return 0


def _local_model(rig, args: argparse.Namespace) -> Path:
    """The model file the choice is written into: --model, else the daemon's own; it must be
    on this machine (a rig PC runs `mrrig tune` beside its daemon) unless --dry-run."""
    from mrrig.tune.rule import TuneError
    from mrrig.tune.trials import daemons_model

    path = Path(daemons_model(rig, args.model))
    if not args.dry_run and not path.is_file():
        raise TuneError(
            f"model {path}: not on this machine, where the choice is written (give --model"
            " with the same file's path here, or --dry-run)"
        )
    return path
