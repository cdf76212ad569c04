"""`mrrig review`'s figure and its one-file HTML report, for a test engineer's record.

The figure: forces (desired, measured, model) and the tracking error f_meas - f_des over
time, armed time shaded, each fault marked and labelled with its reason; the damper current;
the force-velocity and force-displacement loops; the latency histogram. Its title names the
file, the controller and Et. A window of more frames than the axes have pixels is drawn as
its per-pixel min-max band with the mean, so a long run is not a solid block of ink; `--from`
and `--to` zoom in. The HTML report embeds the figure (base64 PNG), the summary table, the
faults and, when given, the bus log's check: one file to attach to a test record.
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mrrig.loop.samples import RigState
from mrrig.offline.review import Recording
from mrrig.safe_text import one_line, plot_literal

_MAX_POINTS = 4000  # per line: about twice the pixels of a panel's width at 100 dpi


def window(rec: Recording, t_from: float | None, t_to: float | None) -> Recording:
    """The samples and events with sensor time in [t_from, t_to] (None: no bound)."""
    lo = -np.inf if t_from is None else t_from
    hi = np.inf if t_to is None else t_to
    if lo >= hi:
        raise ValueError(f"--from {t_from:g} must be before --to {t_to:g}")
    s = rec.samples
    keep = (s["t"] >= lo) & (s["t"] <= hi)
    if s.size and not keep.any():
        raise ValueError(
            f"{rec.path}: no frame between {lo:g} and {hi:g} s (the recording has"
            f" {s['t'][0]:.3f} to {s['t'][-1]:.3f} s)"
        )
    events = [e for e in rec.events if e.get("t") is not None and lo <= e["t"] <= hi]
    return Recording(rec.path, s[keep], events, rec.summary)


def _line(ax, t: np.ndarray, y: np.ndarray, **kw) -> None:
    """y(t) as a line, or as its min-max band per bin and the bin means when it has more
    points than the panel can show."""
    if t.size <= _MAX_POINTS:
        ax.plot(t, y, lw=0.8, **kw)
        return
    bins = np.linspace(t[0], t[-1], _MAX_POINTS // 2 + 1)
    idx = np.clip(np.searchsorted(bins, t, side="right") - 1, 0, bins.size - 2)
    counts = np.bincount(idx, minlength=bins.size - 1)
    ok = counts > 0
    finite = np.where(np.isfinite(y), y, np.nan)
    lo = np.full(bins.size - 1, np.nan)
    hi = np.full(bins.size - 1, np.nan)
    np.fmin.at(lo, idx, finite)
    np.fmax.at(hi, idx, finite)
    mean = np.bincount(idx, weights=np.nan_to_num(finite), minlength=bins.size - 1)
    mid = 0.5 * (bins[:-1] + bins[1:])
    (line,) = ax.plot(mid[ok], mean[ok] / counts[ok], lw=0.8, **kw)
    ax.fill_between(mid[ok], lo[ok], hi[ok], color=line.get_color(), alpha=0.25, lw=0)


def _armed_spans(s: np.ndarray) -> list[tuple[float, float]]:
    armed = (s["state"] == RigState.ARMED).astype(np.int8)
    if not armed.size:
        return []
    edges = np.flatnonzero(np.diff(np.concatenate(([0], armed, [0]))))
    t = s["t"]
    return [(float(t[a]), float(t[b - 1])) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _faults(rec: Recording) -> list[tuple[float, str]]:
    return [
        (float(e["t"]), str(e.get("reason") or e.get("text")))
        for e in rec.events
        if e.get("kind") == "fault" and e.get("t") is not None
    ]


def title(rec: Recording, metrics: Mapping[str, Any]) -> str:
    summary = rec.summary or {}
    et = metrics.get("et")
    et_text = f"Et {et:.4f}" if isinstance(et, float) and np.isfinite(et) else "Et n/a"
    controller = summary.get("controller", "controller not recorded")
    return (
        f"{rec.path.name}: {controller}, {et_text} ({metrics.get('armed_frames', 0)} armed frames)"
    )


def plot(rec: Recording, metrics: Mapping[str, Any], out_png: str | Path | io.BytesIO) -> None:
    """The review figure as a PNG (a path or a buffer)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = rec.samples
    t = s["t"]
    fig = plt.figure(figsize=(13, 11), layout="constrained")
    grid = fig.add_gridspec(4, 3, height_ratios=[3, 2, 2, 3])
    ax_f = fig.add_subplot(grid[0, :])
    ax_e = fig.add_subplot(grid[1, :], sharex=ax_f)
    ax_i = fig.add_subplot(grid[2, :], sharex=ax_f)
    ax_fv, ax_fx, ax_lat = (fig.add_subplot(grid[3, k]) for k in range(3))
    # measured first: the desired and commanded lines are drawn over its band
    _line(ax_f, t, s["f_meas"], label="f_meas measured (load cell)", color="tab:blue")
    _line(ax_f, t, s["f_des"], label="f_des desired (reference)", color="tab:red")
    _line(ax_f, t, s["f_model"], label="f_model network model", color="tab:green", ls="--")
    _line(ax_e, t, s["f_meas"] - s["f_des"], label="f_meas - f_des", color="tab:purple")
    ax_e.axhline(0.0, color="0.5", lw=0.5)
    _line(ax_i, t, s["i_meas"], label="i_meas measured (coil driver)", color="tab:blue")
    _line(ax_i, t, s["i_cmd"], label="i_cmd commanded", color="tab:red")
    spans = _armed_spans(s)
    for ax in (ax_f, ax_e, ax_i):
        for k, (a, b) in enumerate(spans):
            ax.axvspan(a, b, color="gold", alpha=0.15, lw=0, label="armed" if k == 0 else None)
    for k, (tf, reason) in enumerate(_faults(rec)):
        for ax in (ax_f, ax_e, ax_i):
            ax.axvline(tf, color="red", lw=0.8, alpha=0.7)
        # stagger the labels so that faults close together stay readable
        ax_f.annotate(
            plot_literal(reason),
            (tf, 1.0 - 0.08 * (k % 4)),
            xycoords=("data", "axes fraction"),
            fontsize=8,
            color="red",
            ha="left",
            va="top",
            rotation=0,
            bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "red", "alpha": 0.8},
        )
    ax_f.set(ylabel="force (N)", title="Force tracking")
    ax_e.set(ylabel="error (N)", title="Tracking error")
    ax_i.set(xlabel="sensor time (s)", ylabel="current (A)", title="Damper current")
    for ax in (ax_f, ax_e, ax_i):
        # outside the axes, so that no legend covers a trace
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)
    armed = s["state"] == RigState.ARMED
    for ax, xfield, xlabel, name in (
        (ax_fv, "xd", "velocity (m/s)", "Force-velocity"),
        (ax_fx, "x", "displacement (m)", "Force-displacement"),
    ):
        ax.plot(s[xfield][~armed], s["f_meas"][~armed], ".", ms=1, color="0.7", label="not armed")
        ax.plot(s[xfield][armed], s["f_meas"][armed], ".", ms=1, label="armed")
        ax.set(xlabel=xlabel, ylabel="measured force (N)", title=name)
        ax.legend(loc="lower right", markerscale=8, fontsize=8)
    lat = s["latency_us"][np.isfinite(s["latency_us"])]
    ax_lat.hist(lat, bins=100, log=True)
    if lat.size:
        p99 = float(np.percentile(lat, 99))
        ax_lat.axvline(p99, color="red", lw=0.8, label=f"p99 {p99:.0f} us")
        ax_lat.legend(loc="upper right", fontsize=8)
    ax_lat.set(xlabel="cycle latency (us)", ylabel="frames", title="Latency receive -> send")
    fig.suptitle(plot_literal(title(rec, metrics)))
    fig.savefig(out_png, dpi=100, format="png")
    plt.close(fig)


def _rows(d: Mapping[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    rows: list[tuple[str, str]] = []
    for k, v in d.items():
        if k == "faults":
            continue
        if isinstance(v, Mapping):
            rows += _rows(v, f"{prefix}{k}.")
        elif isinstance(v, float):
            rows.append((prefix + k, f"{v:.6g}"))
        elif not isinstance(v, list):
            rows.append((prefix + k, str(v)))
    return rows


# the run's identity as the record's header: (label, identity key)
IDENTITY_ROWS = (
    ("run id", "run_id"),
    ("rig", "rig"),
    ("specimen", "specimen"),
    ("operator", "operator"),
    ("started (UTC)", "started_utc"),
    ("controller", "controller"),
    ("model", "model_path"),
    ("model sha256", "model_sha256"),
    ("config sha256", "config_sha256"),
    ("DBC sha256", "dbc_sha256"),
    ("mrrig", "mrrig_version"),
)
# the numbers a reader looks for first: (label, path in the summary, unit, format)
KEY_NUMBERS = (
    ("Et (eqs 41-43)", ("et",), "", ".4f"),
    ("Et where answered", ("et_answered",), "", ".4f"),
    ("duration", ("duration_s",), "s", ".1f"),
    ("armed frames", ("armed_frames",), "", "d"),
    ("peak commanded current", ("i_cmd_a", "max"), "A", ".3f"),
    ("latency p50", ("latency_us", "p50"), "us", ".0f"),
    ("latency p99", ("latency_us", "p99"), "us", ".0f"),
    ("tracking error p95", ("tracking_error_n", "p95"), "N", ".1f"),
    ("force against the motion", ("force_against_motion", "share"), "", ".1%"),
)


def _get(d: Mapping[str, Any], path: tuple[str, ...]) -> Any:
    for k in path:
        d = d.get(k) if isinstance(d, Mapping) else None  # type: ignore[assignment]
    return d


def _number(v: Any, fmt: str) -> str:
    if isinstance(v, bool) or not isinstance(v, int | float):
        return "n/a"
    if isinstance(v, float) and not np.isfinite(v):
        return "n/a"
    return format(int(v) if fmt == "d" else v, fmt)


def verdict(rec: Recording, metrics: Mapping[str, Any]) -> str:
    """The run's verdict as the catalog gives it (`mrrig.catalog.finished.verdict_of`), with
    the number of faults."""
    from mrrig.catalog.finished import verdict_of

    n = len(metrics.get("faults", []))
    return f"{verdict_of(rec.summary)}, {n} fault{'s' if n != 1 else ''}"


def _png(draw, *args: Any) -> str:
    buf = io.BytesIO()
    draw(*args, buf)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _marks(rec: Recording) -> list[tuple[float, str]]:
    """The plan's step boundaries and other marks in the recording (`mark` requests)."""
    return [
        (float(e["t"]), str(e.get("text")))
        for e in rec.events
        if e.get("kind") == "mark" and e.get("t") is not None
    ]


def plot_traces(rec: Recording, out_png: str | Path | io.BytesIO) -> None:
    """Every channel over time, one panel each: displacement, velocity, force, current,
    temperature; armed time shaded, the marks (a plan's step boundaries) as dashed lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = rec.samples
    t = s["t"]
    panels = (
        ("displacement (mm)", (("x", 1e3, "x measured"), ("x_est", 1e3, "x estimated"))),
        ("velocity (m/s)", (("xd", 1.0, "xd estimated"),)),
        ("force (N)", (("f_meas", 1.0, "f_meas measured"), ("f_des", 1.0, "f_des desired"))),
        ("current (A)", (("i_cmd", 1.0, "i_cmd commanded"), ("i_meas", 1.0, "i_meas measured"))),
        ("temperature (degC)", (("temp_degc", 1.0, "damper"),)),
    )
    fig, axes = plt.subplots(len(panels), 1, figsize=(13, 13), sharex=True, layout="constrained")
    spans = _armed_spans(s)
    marks = _marks(rec)
    for ax, (ylabel, lines) in zip(axes, panels, strict=True):
        for field, scale, label in lines:
            if np.isfinite(s[field]).any():
                _line(ax, t, s[field] * scale, label=label)
        for a, b in spans:
            ax.axvspan(a, b, color="gold", alpha=0.15, lw=0)
        for tm, _ in marks:
            ax.axvline(tm, color="0.3", lw=0.8, ls="--")
        ax.set_ylabel(ylabel)
        if ax.lines:
            ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=9, frameon=False)
    axes[-1].set_xlabel("sensor time (s); shaded: armed; dashed: a mark (a plan step's start/end)")
    fig.suptitle(plot_literal(f"{rec.path.name}: every channel over time"))
    fig.savefig(out_png, dpi=100, format="png")
    plt.close(fig)


def plot_cycles(cs: Sequence[Any], out_png: str | Path | io.BytesIO) -> None:
    """Per cycle, coloured by test condition: peak force against peak velocity (extension and
    compression), and the energy dissipated per cycle over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_fv, ax_e) = plt.subplots(1, 2, figsize=(13, 5.5), layout="constrained")
    conditions = list(dict.fromkeys(c.condition() for c in cs))
    for k, cond in enumerate(conditions):
        g = [c for c in cs if c.condition() == cond]
        label = f"{cond[0] * 1e3:g} mm, {cond[1]:g} Hz, {cond[2]:g} A"
        v = [c.v_max_m_s for c in g] + [c.v_min_m_s for c in g]
        f = [c.f_max_n for c in g] + [c.f_min_n for c in g]
        ax_fv.plot(v, f, "o", ms=4, color=f"C{k % 10}", label=label)
        ax_e.plot([c.t_start_s for c in g], [c.energy_j for c in g], "o", ms=4, color=f"C{k % 10}")
    ax_fv.axhline(0.0, color="0.5", lw=0.5)
    ax_fv.axvline(0.0, color="0.5", lw=0.5)
    ax_fv.set(xlabel="peak velocity (m/s)", ylabel="peak force (N)",
              title="Peak force against peak velocity, per cycle")  # fmt: skip
    ax_e.set(xlabel="cycle start (s)", ylabel="energy dissipated (J)", title="Energy per cycle")
    if conditions:
        ax_fv.legend(fontsize=8, title="amplitude, frequency, current")
    fig.savefig(out_png, dpi=100, format="png")
    plt.close(fig)


def _table(head: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    esc = html.escape
    th = "".join(f"<th>{esc(h)}</th>" for h in head)
    body = "".join("<tr>" + "".join(f"<td>{esc(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


def record_parts(rec: Recording, metrics: Mapping[str, Any]) -> list[str]:
    """The test record's sections: identity, verdict and key numbers, the figures (review,
    every channel over time, per cycle), the per-condition table, marks, faults, summary."""
    from mrrig.offline.cycles import by_condition, cycles

    esc = html.escape
    ident = rec.identity or {}
    id_rows = [(label, str(ident.get(key) or "not recorded")) for label, key in IDENTITY_ROWS]
    numbers = [
        (label, f"{_number(_get(metrics, path), fmt)} {unit}".strip())
        for label, path, unit, fmt in KEY_NUMBERS
    ]
    cs = cycles(rec.samples)
    rows = by_condition(cs)
    cond = [
        (f"{r.amplitude_m * 1e3:g}", f"{r.frequency_hz:g}", f"{r.current_a:g}", str(r.cycles),
         f"{r.v_max_m_s:.3f}", f"{r.v_min_m_s:.3f}", f"{r.f_max_n:.1f}", f"{r.f_min_n:.1f}",
         f"{r.energy_j:.2f}")
        for r in rows
    ]  # fmt: skip
    faults = [(f"{f['t']:.3f}", str(f["reason"])) for f in metrics.get("faults", [])]
    parts = [
        f"<h1>{esc(title(rec, metrics))}</h1>",
        f"<p class='verdict'>verdict: <b>{esc(verdict(rec, metrics))}</b></p>",
        "<h2>Identity</h2>",
        _table(("field", "value"), id_rows),
        "<h2>Key numbers</h2>",
        _table(("number", "value"), numbers),
        "<h2>Review</h2>",
        f"<img alt='review figure' src='data:image/png;base64,{_png(plot, rec, metrics)}'>",
        "<h2>Time traces</h2>",
        f"<img alt='time traces' src='data:image/png;base64,{_png(plot_traces, rec)}'>",
        f"<h2>Per cycle ({len(cs)} cycles)</h2>",
    ]
    if cs:
        parts += [
            _table(
                (
                    "amplitude (mm)",
                    "frequency (Hz)",
                    "current (A)",
                    "cycles",
                    "v max (m/s)",
                    "v min (m/s)",
                    "F max (N)",
                    "F min (N)",
                    "energy (J)",
                ),
                cond,
            ),  # fmt: skip
            "<p>medians per test condition; the energy is the loop integral of the measured"
            " force over the displacement (work done on the damper)</p>",
            f"<img alt='per cycle' src='data:image/png;base64,{_png(plot_cycles, cs)}'>",
        ]
    else:
        parts.append("<p>no complete stroke cycle in this recording</p>")
    marks = _marks(rec)
    if marks:
        parts += ["<h2>Marks</h2>", _table(("t (s)", "mark"), [(f"{t:.3f}", m) for t, m in marks])]
    parts += [f"<h2>Faults ({len(faults)})</h2>"]
    if faults:
        parts.append(_table(("t (s)", "reason"), faults))
    return parts


def write_html(
    rec: Recording,
    metrics: Mapping[str, Any],
    out_html: str | Path,
    bus_log_text: str | None = None,
    window_text: str | None = None,
) -> Path:
    """One self-contained HTML file, a test record: identity, verdict, key numbers, the
    figures (base64 PNG), the per-cycle results, marks, faults and every summary number."""
    esc = html.escape
    table = "".join(f"<tr><th>{esc(k)}</th><td>{esc(v)}</td></tr>" for k, v in _rows(metrics))
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>{esc(rec.path.name)}</title>",
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:2px 8px;text-align:left}th{background:#f4f4f4}"
        "img{max-width:100%}.verdict{font-size:1.3em}</style></head><body>",
        *record_parts(rec, metrics),
        f"<p>recording <code>{esc(str(rec.path))}</code>"
        + (f", window {esc(window_text)}" if window_text else "")
        + "</p>",
        "<details><summary>Every summary number</summary>",
        f"<table>{table}</table></details>",
    ]
    if bus_log_text:
        parts += ["<h2>Bus log</h2>", f"<pre>{esc(bus_log_text)}</pre>"]
    parts.append("</body></html>")
    out_html = Path(out_html)
    out_html.write_text("\n".join(parts))
    return out_html


def plot_compare(
    runs: Sequence[tuple[str, np.ndarray, list[dict[str, Any]]]], out_png: str | Path
) -> Path:
    """One figure with several runs (`mrrig runs compare`): per run (label, SAMPLE_DTYPE
    samples, events), its desired and measured force, tracking error and commanded current
    over time from its first armed frame (s), each fault marked, and its armed
    force-velocity loop; the title names each run (its label) with its armed frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(13, 11), layout="constrained")
    grid = fig.add_gridspec(4, 1, height_ratios=[3, 2, 2, 3])
    ax_f, ax_e, ax_i = (fig.add_subplot(grid[k, 0]) for k in range(3))
    ax_e.sharex(ax_f)
    ax_i.sharex(ax_f)
    ax_fv = fig.add_subplot(grid[3, 0])
    titles = []
    for k, (label, s, events) in enumerate(runs):
        color = f"C{k}"
        armed = s["state"] == RigState.ARMED
        t0 = float(s["t"][armed][0]) if armed.any() else float(s["t"][0]) if s.size else 0.0
        t = s["t"] - t0
        shown = plot_literal(label)  # a `$` in a run's label is text, not mathtext
        _line(ax_f, t, s["f_meas"], label=f"{shown}: f_meas measured", color=color)
        _line(ax_f, t, s["f_des"], label=f"{shown}: f_des desired", color=color, ls="--")
        _line(ax_e, t, s["f_meas"] - s["f_des"], label=f"{shown}: f_meas - f_des", color=color)
        _line(ax_i, t, s["i_cmd"], label=f"{shown}: i_cmd commanded", color=color)
        fault_times = [e["t"] - t0 for e in events if e.get("kind") == "fault" and "t" in e]
        for tf in fault_times:
            for ax in (ax_f, ax_e, ax_i):
                ax.axvline(tf, color=color, lw=0.8, ls=":")
        ax_fv.plot(s["xd"][armed], s["f_meas"][armed], ".", ms=1, color=color, label=shown)
        titles.append(f"{one_line(label)}: {int(armed.sum())} armed frames")
    ax_f.set(ylabel="force (N)", title="Force tracking (dotted: a fault)")
    ax_e.set(ylabel="error (N)", title="Tracking error")
    ax_e.axhline(0.0, color="0.5", lw=0.5)
    ax_i.set(xlabel="time from the first armed frame (s)", ylabel="current (A)", title="Current")
    for ax in (ax_f, ax_e, ax_i):
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)
    ax_fv.set(xlabel="velocity (m/s)", ylabel="measured force (N)", title="Force-velocity, armed")
    ax_fv.legend(loc="lower right", markerscale=8, fontsize=8)
    fig.suptitle(plot_literal("; ".join(titles)))
    # the title also as the PNG's own: a figure filed away still says which runs it shows
    fig.savefig(out_png, dpi=100, format="png", metadata={"Title": "; ".join(titles)})
    plt.close(fig)
    return Path(out_png)
