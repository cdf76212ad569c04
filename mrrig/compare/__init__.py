"""`mrrig compare`: the paper's controllers (its Table 6) on a lab's own damper in one command.

A comparison is a test plan made here, one step per controller on the same stroke and the
same desired force, run as any plan (`mrrig.plans`: each step a run of the catalog, the JUnit
and HTML reports), then the controllers' numbers side by side. The plan is written out first
so that the comparison can be run again, or edited, as `mrrig test PLAN`.

The passive extremes (the damper off at 0 A and fully on) frame the table: a controller no
better than one of them is not worth its name. Network inversion takes the daemon's own
forward model (the lab's, trained by `mrrig train`); the supervised inverse MLP and the RNN
need their own inverse models and run only where they are given.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# the paper's controllers in its Table 6 order, and the passive extremes
PASSIVE_OFF = "passive off (0 A)"
PASSIVE_ON = "passive on"
PAPER_ORDER = ("heaviside", "continuous_state", "supervised", "rnn", "network_inversion")
NEEDS_OWN_MODEL = ("supervised", "rnn")

DEFAULT_ACTUATOR = {"waveform": "sine", "amplitude_m": 0.01, "frequency_hz": 1.0}
# a desired force a damper can give: the Bouc-Wen reference damper on the measured motion
DEFAULT_REFERENCE = {
    "kind": "bouc_wen",
    "preset": "rig-current",
    "current_a": 0.8,
    "current_amp_a": 0.5,
    "current_freq_hz": 0.5,
}


class CompareError(ValueError):
    """A comparison that cannot be made; one line naming what was wrong."""


@dataclass(frozen=True)
class Comparison:
    """What to compare: the controllers (registry names, `PAPER_ORDER`), their settings
    (gains: `continuous_state` `gain`/`b`, `heaviside` `on_current_a`; `supervised`/`rnn`
    `model`), the stroke and the desired force (a plan step's `actuator` and `reference`
    tables), each step's length and settling time, and the rig's full current."""

    controllers: Sequence[str] = ("heaviside", "continuous_state", "network_inversion")
    settings: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    actuator: Mapping[str, Any] = field(default_factory=lambda: dict(DEFAULT_ACTUATOR))
    reference: Mapping[str, Any] = field(default_factory=lambda: dict(DEFAULT_REFERENCE))
    duration_s: float = 10.0
    settle_s: float = 2.0
    i_max_a: float = 2.0
    passive: bool = True

    def check(self) -> None:
        unknown = [c for c in self.controllers if c not in PAPER_ORDER]
        if unknown:
            raise CompareError(
                f"controller {unknown[0]!r}: not one of the paper's ({', '.join(PAPER_ORDER)})"
            )
        for name in NEEDS_OWN_MODEL:
            if name in self.controllers and not self.settings.get(name, {}).get("model"):
                raise CompareError(
                    f"controller {name}: needs its own inverse model (--{name}-model FILE)"
                )
        if not (math.isfinite(self.duration_s) and 0 < self.duration_s <= 3600):
            raise CompareError(f"duration: {self.duration_s!r} s must be in (0, 3600]")
        if not (math.isfinite(self.i_max_a) and self.i_max_a > 0):
            raise CompareError(f"i_max_a: {self.i_max_a!r} A must be positive")


def steps(c: Comparison) -> list[tuple[str, dict[str, Any]]]:
    """The plan's steps as (step name, controller table), passive extremes first."""
    out: list[tuple[str, dict[str, Any]]] = []
    if c.passive:
        out += [
            (PASSIVE_OFF, {"name": "constant", "current_a": 0.0}),
            (f"{PASSIVE_ON} ({c.i_max_a:g} A)", {"name": "constant", "current_a": c.i_max_a}),
        ]
    for name in sorted(c.controllers, key=PAPER_ORDER.index):
        out.append((name, {"name": name, **dict(c.settings.get(name, {}))}))
    return out


def plan_text(c: Comparison, plan_name: str = "compare", rig: str | None = None) -> str:
    """The comparison as a plan file (TOML), `mrrig test` can run it again as it is."""
    c.check()
    lines = [
        "# written by `mrrig compare`: one step per controller on the same stroke and force",
        "[plan]",
        f"name = {_toml(plan_name)}",
        *([f"rig = {_toml(rig)}"] if rig else []),
        'description = "the paper\'s controllers side by side (Table 6)"',
    ]
    for name, controller in steps(c):
        lines += [
            "",
            "[[step]]",
            f"name = {_toml(name)}",
            f"duration_s = {c.duration_s:g}",
            f"settle_s = {c.settle_s:g}",
            f"actuator = {_inline(c.actuator)}",
            f"controller = {_inline(controller)}",
            f"reference = {_inline(c.reference)}",
            'criteria = { faults = "transport" }',
        ]
    return "\n".join(lines) + "\n"


def _toml(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(float(v)) if isinstance(v, float) else str(v)
    text = str(v)
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _inline(table: Mapping[str, Any]) -> str:
    return "{ " + ", ".join(f"{k} = {_toml(v)}" for k, v in table.items()) + " }"


@dataclass(frozen=True)
class Row:
    step: str
    controller: str
    settings: str
    et: float
    peak_current_a: float
    latency_p99_us: float
    verdict: str


def rows(results: Sequence[Any]) -> list[Row]:
    """The plan's step results (`mrrig.plans.runner.StepResult`) as the comparison's rows."""
    out = []
    for r in results:
        c = r.step.controller
        settings = _settings(c) if c is not None else ""
        n = r.numbers
        nan = math.nan
        out.append(
            Row(
                r.step.name,
                c.name if c is not None else "-",
                settings or "-",
                n.et if n else nan,
                n.peak_current_a if n else nan,
                n.latency_p99_us if n else nan,
                r.verdict,
            )
        )
    return out


def _settings(c: Any) -> str:
    """The settings that make the controller what it is, as in force (defaults included)."""
    if c.name == "constant":
        return f"{c.current_a:g} A"
    if c.name == "continuous_state":
        return f"G {c.gain:g} A/N, B {c.b:g}"
    if c.name == "heaviside":
        return f"on {c.on_current_a:g} A" if c.on_current_a is not None else "on at i_max"
    model = Path(str(c.model)).name if c.model is not None else "-"
    return "the daemon's model" if model.startswith("(") else model


def table(rs: Sequence[Row]) -> str:
    """The controllers' Et side by side, with each one's ratio to the best controller's and
    to the better passive extreme's."""
    passive = [r.et for r in rs if r.controller == "constant" and math.isfinite(r.et)]
    active = [r.et for r in rs if r.controller != "constant" and math.isfinite(r.et)]
    best_passive = min(passive) if passive else math.nan
    best = min(active) if active else math.nan
    head = (
        f"{'step':<28} {'settings':<28} {'Et':>7} {'/best':>6} {'/passive':>8}"
        f" {'I peak A':>8} {'lat p99 us':>10} verdict"
    )
    lines = [head, "-" * len(head)]
    for r in rs:
        lines.append(
            f"{r.step[:28]:<28} {r.settings[:28]:<28} {_f(r.et, '.4f'):>7}"
            f" {_f(r.et / best, '.2f'):>6} {_f(r.et / best_passive, '.2f'):>8}"
            f" {_f(r.peak_current_a, '.3f'):>8} {_f(r.latency_p99_us, '.0f'):>10} {r.verdict}"
        )
    return "\n".join(lines)


def _f(v: float, fmt: str) -> str:
    return format(v, fmt) if math.isfinite(v) else "-"
