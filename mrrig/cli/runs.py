"""`mrrig runs`: the run catalog (mrrig.catalog) on the command line.

    mrrig runs [--rig R] [--specimen S] [--campaign C] [--since 7d] [--plan P]
               [--controller C] [--where "et < 0.01"] [--all | --characterization]
               [--limit N] [--json]
    mrrig runs show ID [--json]       everything about a run; is its recording still unchanged?
    mrrig runs compare A B [--plot F] two runs' numbers side by side, and one figure of both
    mrrig runs sync --from URL --to URL
    mrrig runs register REC...        the run a recording carries, where the catalog lacks it

The catalog: --catalog URL, else $MRRIG_CATALOG, else recordings/catalog.sqlite (a path is an
SQLite file; postgresql://user@host/db a lab's server). An ID may be the first 4+ digits.
The list leaves out characterization runs (`mrrig characterize`'s constant currents: their Et
means nothing) unless --all, --characterization or `--plan characterize` asks for them.
`show` exits 1 where the run's recording is missing or no longer what was registered; the
list exits 1 where no run matches (one line on stderr). Runs journalled while their catalog
could not take them (locked, corrupt, unreachable: `REC.rrd.journal`) are registered first.
Built on the Python API (`mrrig.api`): the same functions a notebook calls.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mrrig import api
from mrrig.api.catalog import ENV_CATALOG
from mrrig.catalog import CHARACTERIZATION_PLAN, DEFAULT_PATH, NUMERIC_COLUMNS, RunRecord
from mrrig.catalog.store import catalog_url
from mrrig.cli_args import HelpFormatter, int_at_least

ACTIONS = ("show", "compare", "sync", "register")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in ACTIONS:
        actions = {"show": _show, "compare": _compare, "sync": _sync, "register": _register}
        return actions[argv[0]](argv[1:])
    return _list(argv)


def _parser(prog: str, description: str | None) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(formatter_class=HelpFormatter, prog=prog, description=description)
    ap.add_argument(
        "--catalog",
        default=api.default_catalog(),
        help=f"the catalog: an SQLite file or a postgresql:// URL (default: ${ENV_CATALOG},"
        f" else {DEFAULT_PATH})",
    )
    return ap


def _list(argv: list[str]) -> int:
    ap = _parser("mrrig runs", __doc__)
    ap.add_argument("--rig", help="only this rig's runs")
    ap.add_argument("--specimen", help="only runs of this specimen (the damper's serial number)")
    ap.add_argument(
        "--campaign", help="only the runs of this campaign (`mrrig test --campaign`, a matrix)"
    )
    ap.add_argument("--plan", help="only the steps of this plan")
    ap.add_argument("--controller", help="only runs with this controller")
    ap.add_argument("--since", help="runs started since: a span (90s, 30m, 12h, 7d, 2w) or a date")
    ap.add_argument(
        "--where",
        help="a condition on the numbers: COLUMN < <= > >= == != NUMBER, and, or, not, ( );"
        " columns: " + ", ".join(NUMERIC_COLUMNS),
    )
    shown = ap.add_mutually_exclusive_group()
    shown.add_argument(
        "--all", action="store_true", help="the characterization runs too (left out by default)"
    )
    shown.add_argument(
        "--characterization", action="store_true", help="only the characterization runs"
    )
    ap.add_argument("--limit", type=int_at_least(1), help="only the newest N of them")
    ap.add_argument("--json", action="store_true", help="print the runs as one JSON list")
    ap.add_argument(
        "--recordings",
        type=Path,
        help="name the .rrd files in this folder that have no run in the catalog (default: an"
        " SQLite catalog's own folder)",
    )
    args = ap.parse_args(argv)
    _replay(args.catalog, args.recordings)
    found = api.run_records(
        args.catalog,
        rig=args.rig,
        specimen=args.specimen,
        plan=args.plan,
        controller=args.controller,
        campaign=args.campaign,
        characterization=_characterization(args),
        since=args.since,
        where=args.where,
        limit=args.limit,
    )
    if args.json:
        from mrrig import json_text  # numpy: not for the table

        sys.stdout.write(json_text.dumps([r.to_json() for r in found], indent=1) + "\n")
    elif found:
        sys.stdout.write(_table(found))
    _note_unlisted(args.catalog, args.recordings)
    if not found:
        print(f"no run in {_name(args.catalog)} {_matching(args)}", file=sys.stderr)
        return 1
    return 0


def _characterization(args: argparse.Namespace) -> bool | None:
    """Which runs the list shows as to characterization: only those, all, or (by default)
    all but those."""
    if args.characterization:
        return True
    if args.all or args.plan == CHARACTERIZATION_PLAN:
        return None
    return False


_FILTERS = ("rig", "specimen", "campaign", "plan", "controller", "since", "where")


def _matching(args: argparse.Namespace) -> str:
    """What the list asked for, as its options: `matches --rig nosuch`, else `at all`."""
    given = [f"--{k} {getattr(args, k)!r}" for k in _FILTERS if getattr(args, k) is not None]
    if args.characterization:
        given.append("--characterization")
    if given:
        return f"matches {' '.join(given)}"
    if _characterization(args) is False and api.run_records(
        args.catalog, characterization=True, limit=1
    ):
        return "but characterization runs (--all lists them too)"
    return "at all: the catalog is empty"


def _name(catalog: str) -> str:
    """The catalog as a person names it: an SQLite file's path, a server's URL (no password)."""
    url = catalog_url(catalog)
    if url.get_backend_name() == "sqlite":
        return f"the catalog {url.database}"
    return f"the catalog {url.render_as_string(hide_password=True)}"


def _replay(catalog: str, folder: Path | None) -> None:
    """Register the runs journalled because their catalog could not take them."""
    done, kept = api.replay_journals(catalog, folder)
    if done:
        print(f"note: {done} journalled run{'s' if done != 1 else ''} registered", file=sys.stderr)
    if kept:
        print(
            f"note: {kept} run{'s' if kept != 1 else ''} still journalled: their catalog cannot"
            " take them yet (see the log)",
            file=sys.stderr,
        )


# model: the first 12 digits of the sha256 of the model in force when the run started
_COLUMNS = (
    "run", "started (UTC)", "rig", "specimen", "plan/step", "controller", "model", "Et", "faults"
)  # fmt: skip


def _table(found: list[RunRecord]) -> str:
    rows = [
        (
            str(r.run_id)[:8],
            r.started_utc.isoformat(" ", "seconds")[:19],
            r.rig,
            r.specimen or "-",
            "/".join(x for x in (r.plan, r.step) if x) or "-",
            r.controller or "-",
            (r.model_sha256 or "-")[:12],
            "-" if r.et is None else f"{r.et:.4f}",
            str(r.faults_count),
            r.verdict or "-",
        )
        for r in found
    ]
    head = (*_COLUMNS, "verdict")
    widths = [max(len(head[k]), *(len(row[k]) for row in rows)) for k in range(len(head))]
    lines = [
        "  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip()
        for row in [head, *rows]
    ]
    lines.append(f"{len(rows)} run{'s' if len(rows) != 1 else ''}")
    return "\n".join(lines) + "\n"


def _note_unlisted(catalog: str, folder: Path | None) -> None:
    folder, unlisted = api.unregistered_recordings(catalog, folder)
    if unlisted:
        shown = ", ".join(unlisted[:10]) + (", ..." if len(unlisted) > 10 else "")
        print(
            f"note: {len(unlisted)} recording{'s' if len(unlisted) != 1 else ''} in {folder}"
            f" ha{'ve' if len(unlisted) != 1 else 's'} no run in the catalog: {shown}",
            file=sys.stderr,
        )


def _show(argv: list[str]) -> int:
    ap = _parser(
        "mrrig runs show",
        "Everything the catalog knows about one run, and whether its"
        " recording is still there and unchanged (exit 1 if not).",
    )
    ap.add_argument("run_id", metavar="ID", help="the run id, or its first 4+ digits")
    ap.add_argument("--json", action="store_true", help="print it as one JSON object")
    args = ap.parse_args(argv)
    run = api.get_run(args.run_id, args.catalog)
    check = api.check_recording(run)
    if args.json:
        from mrrig import json_text

        print(json_text.dumps(run.to_json() | {"recording_check": check}, indent=1))
    else:
        fields = run.to_json()
        width = max(len(k) for k in fields)
        for key, value in fields.items():
            text = value if isinstance(value, str) else json.dumps(value)
            print(f"{key.ljust(width)}  {text}")
        print(f"{'recording'.ljust(width)}  {check}")
    return 0 if check in ("unchanged", "no recording registered") else 1


_COMPARED = (
    "run_id",
    "rig",
    "host",
    "specimen",
    "operator",
    "campaign",
    "plan",
    "step",
    "started_utc",
    "controller",
    "controller_params",
    "model_path",
    "model_sha256",
    "config_sha256",
    "dbc_sha256",
    "mrrig_version",
    "verdict",
)


def _compare(argv: list[str]) -> int:
    ap = _parser(
        "mrrig runs compare",
        "Two runs' identities and numbers side by side (B - A for the numbers; * where they"
        " differ), and one figure of both from their recordings (through mrrig review's"
        " plotting: force, tracking error, current, force-velocity).",
    )
    ap.add_argument("a", metavar="A", help="a run id, or its first 4+ digits")
    ap.add_argument("b", metavar="B", help="another")
    figure = ap.add_mutually_exclusive_group()
    figure.add_argument(
        "--plot", type=Path, help="the figure's PNG (default: compare-<A>-<B>.png, here)"
    )
    figure.add_argument("--no-plot", action="store_true", help="the numbers only")
    args = ap.parse_args(argv)
    runs = [api.get_run(x, args.catalog) for x in (args.a, args.b)]
    a, b = (r.to_json() for r in runs)
    rows = [("", "A", "B", "B - A")]
    for key in (*_COMPARED, *NUMERIC_COLUMNS):
        va, vb = a.get(key), b.get(key)
        diff = ""
        if key in NUMERIC_COLUMNS and va is not None and vb is not None:
            diff = f"{vb - va:+.6g}"
        mark = "*" if va != vb else " "
        rows.append((f"{mark} {key}", _cell(va), _cell(vb), diff))
    widths = [max(len(row[k]) for row in rows) for k in range(4)]
    for row in rows:
        print("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip())
    if args.no_plot:
        return 0
    png = args.plot or Path(f"compare-{a['run_id'][:8]}-{b['run_id'][:8]}.png")
    print(f"figure: {api.compare_figure(runs[0], runs[1], png)}")
    return 0


def _cell(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, str):
        return value
    return json.dumps(value)


def _sync(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=HelpFormatter,
        prog="mrrig runs sync",
        description="Copy a rig's local runs to the lab's catalog: each run once, by run id;"
        " an interrupted sync is completed by the next one.",
    )
    ap.add_argument("--from", dest="src", required=True, help="the catalog to copy from")
    ap.add_argument("--to", dest="dst", required=True, help="the catalog to copy to")
    ap.add_argument(
        "--batch", type=int_at_least(1), default=500, help="runs to a transaction at the target"
    )
    args = ap.parse_args(argv)
    report = api.sync_runs(args.src, args.dst, batch_rows=args.batch)
    src, dst = (catalog_url(x).render_as_string(hide_password=True) for x in (args.src, args.dst))
    print(
        f"sync: {report.copied} copied, {report.updated} updated, {report.unchanged} already"
        f" there ({src} -> {dst})"
    )
    return 0


def _register(argv: list[str]) -> int:
    ap = _parser(
        "mrrig runs register",
        "Register the run each recording carries (its identity and summary; a recording"
        " without a summary is a run that crashed or was killed: verdict crashed), where the"
        " catalog does not have it yet: a run whose registration was lost.",
    )
    ap.add_argument("recordings", metavar="REC", nargs="+", type=Path, help="a daemon's .rrd")
    args = ap.parse_args(argv)
    for path in args.recordings:
        record, added = api.register_recording(path, args.catalog)
        what = f"registered (verdict {record.verdict})" if added else "already there"
        print(f"{path}: run {str(record.run_id)[:8]} {what} in {_name(args.catalog)}")
    return 0
