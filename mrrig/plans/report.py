"""A plan run's reports: JUnit XML (one testcase per step, the numbers as properties) and one
self-contained HTML file (the identity, the table of steps, a force plot per step)."""

from __future__ import annotations

import base64
import getpass
import hashlib
import html
import io
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from mrrig.plans.criteria import criteria_rows
from mrrig.plans.hil_step import hil_criteria_rows
from mrrig.plans.runner import StepResult, overall
from mrrig.safe_text import one_line, plot_literal

# a JUnit message: the reasons of a step, more than a name (safe_text.MAX_CHARS)
_MAX_MESSAGE_CHARS = 4096


@dataclass(frozen=True)
class Identity:
    plan: Path
    plan_sha256: str
    rig: str
    mrrig_version: str
    started_utc: str
    operator: str

    @classmethod
    def of(cls, plan: Path, rig: str, version: str, started_utc: str) -> Identity:
        digest = hashlib.sha256(plan.read_bytes()).hexdigest()
        try:
            operator = getpass.getuser()
        except (OSError, KeyError):
            operator = "unknown"
        return cls(plan, digest, rig, version, started_utc, operator)


def _number(value: float) -> str:
    return "nan" if math.isnan(value) else f"{value:.6g}"


def write_junit(path: Path, plan_name: str, ident: Identity, results: list[StepResult]) -> None:
    """One testsuite (in <testsuites>) named after the plan; a failed step is a <failure>, an
    aborted one an <error>, a skipped one <skipped>, each with the reason as its message. Every
    text is one printable line (`safe_text.one_line`): a control character in a step's name or
    a fault's reason made the XML ill-formed."""
    plan_name = one_line(plan_name)
    root = ET.Element("testsuites", name=plan_name)
    suite = ET.SubElement(
        root,
        "testsuite",
        name=plan_name,
        tests=str(len(results)),
        failures=str(sum(r.verdict == "failed" for r in results)),
        errors=str(sum(r.verdict == "aborted" for r in results)),
        skipped=str(sum(r.verdict == "skipped" for r in results)),
        time=f"{sum(r.wall_s for r in results):.3f}",
        timestamp=ident.started_utc,
    )
    props = ET.SubElement(suite, "properties")
    for name, value in (
        ("plan", str(ident.plan)),
        ("plan_sha256", ident.plan_sha256),
        ("rig", ident.rig),
        ("mrrig_version", ident.mrrig_version),
        ("operator", ident.operator),
    ):
        ET.SubElement(props, "property", name=name, value=one_line(value, _MAX_MESSAGE_CHARS))
    for r in results:
        case = ET.SubElement(
            suite,
            "testcase",
            classname=plan_name,
            name=one_line(r.step.name),
            time=f"{r.wall_s:.3f}",
        )
        cprops = ET.SubElement(case, "properties")
        values = {
            "verdict": r.verdict,
            "controller": r.controller or "",
            "faults": ",".join(r.faults),
        }
        if r.predicted is not None:
            values["against_motion_before"] = r.predicted.text()
        if r.numbers is not None:
            n = r.numbers
            values |= {
                "samples": str(n.samples),
                "et": _number(n.et),
                "peak_current_a": _number(n.peak_current_a),
                "latency_p99_us": _number(n.latency_p99_us),
                "temperature_max_degc": _number(n.temperature_max_degc),
                "against_motion_share": _number(n.opposed_share),
            }
        if r.hil is not None:  # a hil step's run: per output its RMS and the reference's
            values["hil_law"] = r.hil.law
            for name, (hil, ref) in r.hil.rms.items():
                values[f"hil_rms_{name}"] = _number(hil)
                values[f"reference_rms_{name}"] = _number(ref)
        for name, value in values.items():
            ET.SubElement(cprops, "property", name=name, value=one_line(value, _MAX_MESSAGE_CHARS))
        message = one_line("; ".join(r.reasons), _MAX_MESSAGE_CHARS)
        tag = {"failed": "failure", "aborted": "error", "skipped": "skipped"}.get(r.verdict)
        if tag is not None:
            ET.SubElement(case, tag, message=message).text = message
    tree = ET.ElementTree(root)
    ET.indent(tree)
    tree.write(path, encoding="utf-8", xml_declaration=True)


def _shown(value: float, fmt: str) -> str:
    """A number of the record: `n/a` where undefined, else to the figures that mean something."""
    return "n/a" if math.isnan(value) else format(value, fmt)


def _plot_png(r: StepResult) -> str:
    """The step's measured and desired force against time, as base64 PNG (the desired line
    dashed over the measured one, so that neither hides the other)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 4), dpi=100)
    ax = fig.add_subplot()
    s = r.samples
    if s.size:
        t = s["t"] - s["t"][0]
        ax.plot(t, s["f_meas"], label="f_meas measured", lw=1.2, color="tab:blue")
        ax.plot(t, s["f_des"], label="f_des desired", lw=1.2, color="tab:red", ls="--")
        ax.legend(loc="upper right")
        ax.grid(alpha=0.3)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("force (N)")
    ax.set_title(plot_literal(f"{r.step.name}: {r.verdict}"))
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _criteria_table(r: StepResult) -> str:
    """The step's criteria: each limit, the value measured, met or not."""
    e = html.escape
    rows = criteria_rows(r.step.criteria, r.numbers, r.faults) if r.verdict != "skipped" else []
    rows += hil_criteria_rows(r.step.criteria, r.hil)
    if not rows:
        return ""
    body = "".join(
        f"<tr class='{'passed' if met == 'met' else 'failed'}'><td>{e(what)}</td>"
        f"<td>{e(limit)}</td><td>{e(value)}</td><td>{e(met)}</td></tr>"
        for what, limit, value, met in rows
    )
    return (
        "<table class='criteria'><tr><th>criterion</th><th>limit</th><th>measured</th>"
        f"<th>result</th></tr>{body}</table>"
    )


def write_html(path: Path, plan_name: str, ident: Identity, results: list[StepResult]) -> None:
    e = html.escape
    controllers = ", ".join(sorted({r.controller for r in results if r.controller})) or "-"

    def each(key: str) -> str:  # the rig's identity as in force over the steps
        return ", ".join(sorted({str(r.identity[key]) for r in results if r.identity.get(key)}))

    rig_operator = each("operator")
    ident_rows = [
        ("plan", f"{ident.plan} (sha256 {ident.plan_sha256})"),
        ("rig", ident.rig),
        ("specimen", each("specimen") or "not set"),
        ("controller", controllers),
        ("mrrig version", ident.mrrig_version),
        ("started (UTC)", ident.started_utc),
        (
            "operator",
            f"{rig_operator} (the rig's run; the plan run by {ident.operator})"
            if rig_operator and rig_operator != ident.operator
            else ident.operator,
        ),
        ("daemon run", each("run_id") or "-"),
        ("verdict", overall(results)),
    ]
    rows = []
    for i, r in enumerate(results, start=1):
        n = r.numbers
        cells = (
            [
                _shown(n.et, ".4f"),
                _shown(n.peak_current_a, ".3f"),
                _shown(n.latency_p99_us, ".0f"),
                _shown(n.temperature_max_degc, ".1f"),
                _shown(n.opposed_share, ".1%"),
            ]
            if n
            else ["-"] * 5
        )
        before = r.predicted.text() if r.predicted else "-"
        sha = r.identity.get("model_sha256")
        model = f"{r.identity.get('model_path')} ({sha[:12]})" if sha else "-"
        rows.append(
            f"<tr class='{r.verdict}'><td>{i}</td><td>{e(r.step.name)}</td><td>{r.verdict}</td>"
            + "".join(f"<td>{c}</td>" for c in cells)
            + f"<td>{e(before)}</td><td>{e(', '.join(r.faults) or '-')}</td>"
            + f"<td>{e(model)}</td><td>{e('; '.join(r.reasons))}</td></tr>"
        )
    plots = [
        f"<h3>{i}. {e(r.step.name)}: {r.verdict}</h3>"
        + _criteria_table(r)
        + f"<img alt='force of step {i}' src='data:image/png;base64,{_plot_png(r)}'>"
        for i, r in enumerate(results, start=1)
    ]
    page = f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>mrrig test: {e(plan_name)}</title>
<style>body{{font-family:sans-serif}} td,th{{border:1px solid #ccc;padding:2px 6px}}
table{{border-collapse:collapse}} .passed{{background:#dfd}}
.failed,.aborted{{background:#fdd}}</style>
</head><body><h1>mrrig test: {e(plan_name)}: {overall(results)}</h1>
<table>{"".join(f"<tr><th>{e(k)}</th><td>{e(v)}</td></tr>" for k, v in ident_rows)}</table>
<h2>Steps</h2><table><tr><th>#</th><th>step</th><th>verdict</th><th>Et</th><th>peak current (A)</th>
<th>latency p99 (us)</th><th>temperature max (degC)</th><th>force against the motion (share)</th>
<th>force against the motion, before arming</th><th>faults</th><th>model (sha256)</th>
<th>reason</th></tr>
{"".join(rows)}</table>
<h2>Criteria and force per step</h2>
{"".join(plots)}
</body></html>
"""
    path.write_text(page, encoding="utf-8")
