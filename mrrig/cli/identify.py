"""`mrrig identify DATA...`: a twin of a measured damper, the modified Bouc-Wen model (eqs
30-36, the command's first-order filter, a force offset) fitted to DATA by least squares.

DATA are CSVs whose headers name field and unit (`t_s`, `x_cm`, `xd_cm_s`, `command_v`,
`force_n`), tidy characterization CSVs or daemon recordings (.rrd); bad stretches are
excluded as `mrrig train` does. The fit starts from the paper's parameters (`--from paper`,
Table 3) or a plant file's (`--from FILE`) and from `--starts` - 1 more drawn around it
(seeded; each screened a few evaluations, the best fitted on), each parameter within a
physical range (mrrig/offline/identify/fit.py BOUNDS; eta held where the command is held per
run). Et is printed per test, and the estimate: on `--holdout FILES` (tests the fit never
saw), else on each test's segments it did not fit (the test cut into 8 segments dealt by
character, amplitude, frequency and command level, into 4 groups; the group most unlike the
rest left out of the fit with guard bands either side; optimistic next to another test). A run
that starts moving is scored after a 0.2 s warm-up, the twin run from rest before it. Writes
the plant file that `firmware_sim` runs (`[plant] file = ...`): the fitted set whose estimate
is printed.

`mrrig identify --map-model MODEL --command-per-a K --out OUT` instead takes a forward model
trained on such data with its command in V, a network or a twin (a plant file), to the rig's
amperes (v = K i, the twin's `[plant] command_per_a`), so that the daemon, which commands
amperes, can invert it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from damper.plant_file import PARAM_NAMES, save_plant
from mrrig.cli_args import COUNT, HelpFormatter, output_file, positive
from mrrig.loop.greybox import GreyBoxModel
from mrrig.loop.twin_model import TwinModel, load_forward_model
from mrrig.offline.identify.command_map import model_in_amperes, plant_in_amperes
from mrrig.offline.identify.fit import STARTS
from mrrig.offline.identify.identify import identify


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="mrrig identify", description=__doc__, formatter_class=HelpFormatter
    )
    ap.add_argument("data", nargs="*", type=Path, help="measured tests to fit (CSV, .rrd)")
    ap.add_argument(
        "--out", type=output_file, default="models/plant.json", help="plant file to write"
    )
    ap.add_argument(
        "--from",
        dest="start",
        default="paper",
        metavar="paper|FILE",
        help="start parameters: the paper's Table 3 or a plant file (default %(default)s)",
    )
    ap.add_argument(
        "--holdout", nargs="+", type=Path, default=[], metavar="FILE", help="tests kept out"
    )
    ap.add_argument(
        "--starts",
        type=COUNT,
        default=STARTS,
        help="the fit's starts: --from's and more drawn around it (default %(default)s)",
    )
    ap.add_argument("--seed", type=int, default=0, help="the drawn starts' seed (default 0)")
    ap.add_argument(
        "--max-evaluations",
        type=COUNT,
        default=60,
        help="least-squares evaluations from the best start, at most",
    )
    ap.add_argument("--report", type=output_file, help="also write the report as JSON")
    ap.add_argument(
        "--map-model", type=Path, metavar="MODEL", help="map MODEL's command from V to A instead"
    )
    ap.add_argument(
        "--command-per-a",
        type=positive,
        default=1.0,
        help="with --map-model: V of the command per A of the rig (default %(default)s)",
    )
    return ap


def _fmt(value: float | None) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.4f}"


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    if args.map_model is not None:
        if args.data:
            ap.error("--map-model takes no DATA")
        source = str(args.map_model)
        model = load_forward_model(args.map_model)
        if isinstance(model, GreyBoxModel):  # its network's inputs include the command in V
            ap.error(
                f"--map-model {source}: a grey-box model (a twin and a network on its "
                "residual, whose inputs include the command) cannot be mapped: train it on "
                "the command in A"
            )
        if isinstance(model, TwinModel):
            save_plant(plant_in_amperes(model.plant, args.command_per_a, source), args.out)
        else:
            model_in_amperes(model, args.command_per_a, source).save(args.out)
        print(f"wrote {args.out}: {args.map_model}'s command in A ({args.command_per_a:g} V per A)")
        return 0
    if not args.data:
        ap.error("DATA: at least one file")
    progress = lambda line: print(line, flush=True)  # noqa: E731 - the CLI's progress lines
    t0 = time.monotonic()
    plant, report = identify(
        args.data,
        args.holdout,
        args.start,
        args.max_evaluations,
        progress,
        starts=args.starts,
        seed=args.seed,
    )
    print(
        f"fitted in {report['seconds']:.0f} s, {report['evaluations']} evaluations "
        f"({report['status']}): Et on the fitted rows {_fmt(report['et_start_fitted_rows'])}"
        f" -> {_fmt(report['et_fitted_rows_objective'])}"
    )
    if report["start_ets_fitted_rows"]:
        print(
            f"starts: {report['starts']} ({args.start} and {report['starts'] - 1} drawn around it,"
            f" seed {report['seed']}), Et on the fitted rows after screening: "
            + " ".join(_fmt(e) for e in report["start_ets_fitted_rows"])
            + f"; fitted on from start {report['chosen_start']}"
        )
    if report["at_bounds"]:
        print(f"at a physical bound (fit.BOUNDS): {', '.join(report['at_bounds'])}")
    print(
        "Et per test (the twin run open loop from the measured motion and command; a run that"
        f" starts moving scored after a {report['warmup_s']:g} s warm-up):"
    )
    for t in report["tests"]:
        if "et_holdout_test" in t:
            print(f"  {t['file']}: held-out test {_fmt(t['et_holdout_test'])}")
            continue
        line = f"  {t['file']}: fitted rows {_fmt(t['et_fitted_rows'])}"
        if "et_segments_not_fitted" in t:
            line += f", segments not fitted ({t['held_out']}) {_fmt(t['et_segments_not_fitted'])}"
        print(line)
    est = report["estimate"]
    print(f"estimate on the {est['on']}: Et {_fmt(est['et'])} ({est['method']})")
    p = plant.params
    print(
        "parameters: "
        + ", ".join(f"{k} {getattr(p, k):.5g}" for k in PARAM_NAMES)
        + f", offset_n {plant.offset_n:.5g}, command in {plant.command_unit}"
    )
    save_plant(plant, args.out)
    print(
        f'wrote {args.out} (firmware_sim: [plant] file = "{args.out}"); identify took'
        f" {time.monotonic() - t0:.0f} s"
    )
    if args.report:
        args.report.write_text(json.dumps(plant.identified, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
