"""Test plans (`mrrig test PLAN.toml`): TOML parsed once into typed, validated steps.

A plan is `[plan]` (name, the rig it is meant for) and an ordered list of `[[step]]`s, each
with what the daemon's control requests take (`actuator`, `controller` = `set_controller`,
`reference` = `set_profile`, `adaptation` = `reset_adaptation` + `freeze_adaptation`), its
duration and settling time, and its `criteria`. A `hil` step (`hil = {scenario, law}`) is one
hybrid-simulation run of a `[hil]` daemon's scenario with that law (`set_hil`), judged against
the all-numerical reference (`mrrig.plans.hil_step`). An error is one line naming the file, the
step (index and name) and the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from mrrig.config import (
    ActuatorSection,
    ControllerSection,
    HilCompensation,
    HilLaw,
    ReferenceSection,
)
from mrrig.loop.controllers import CONTROLLERS
from mrrig.plans.criteria import HIL_CRITERIA, Criteria
from mrrig.safe_text import MAX_CHARS, one_line
from mrrig.typed_config import ConfigError, load_toml, parse

# a plan's size: a 1,000,000-step plan took 2 minutes and 916 MB to read before it found that
# no daemon answered. A day of 90 s steps is under 1000; the file's bytes are bounded before
# it is parsed (a step is a few hundred bytes)
MAX_STEPS = 1000
MAX_PLAN_BYTES = 2_000_000
# what `compare_et` may hold: Et is a normalized error (0: perfect, 1: no better than zero force)
MAX_COMPARE_ET = 100.0

# a model-using controller without `model` keeps the daemon's model (set_controller's rule):
# the plan checks every other field with this stand-in, and sends no model
_DAEMONS_MODEL = "(the daemon's model)"


class PlanError(ConfigError):
    """A plan that cannot run; the message is one line naming file, step and field."""


@dataclass(frozen=True)
class HilStepSection:
    """A `hil` step: one run of the scenario (the daemon's `[hil]` scenario, the same file)
    with this law (and compensation: the scenario's if left out), for the step's duration_s,
    beside the scenario computed all-numerically (the reference)."""

    scenario: Path
    law: HilLaw
    compensation: HilCompensation | None = None


@dataclass(frozen=True)
class Step:
    name: str
    duration_s: float
    settle_s: float = 1.0  # after arming, left out of the criteria
    actuator: ActuatorSection | None = None
    controller: ControllerSection | None = None
    reference: ReferenceSection | None = None
    criteria: Criteria = field(default_factory=Criteria)
    # on-line adaptation of the model's force, on a daemon with [adaptation] enabled: "on"
    # from the model as trained (reset, updating), "off" the model as trained (reset,
    # frozen); absent: as the daemon has it
    adaptation: Literal["on", "off"] | None = None
    # the request fields the plan gave (the daemon keeps the others as they are)
    given: dict[str, tuple[str, ...]] = field(default_factory=dict)
    # figures printed beside the step's Et, by source (e.g. the paper's for the same case)
    compare_et: dict[str, float] = field(default_factory=dict)
    hil: HilStepSection | None = None
    # the step (by name) whose Et this step's is the floor of: e.g. the same case with the
    # `reference_current` controller (the reference damper's own current); the table prints
    # it beside that step's Et, with their ratio
    floor_of: str | None = None

    def check(self) -> None:
        _one_line("name", self.name)
        for source, value in self.compare_et.items():
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"compare_et.{source}: expected a number, got {value!r}")
            if not (math.isfinite(value) and 0 <= value <= MAX_COMPARE_ET):
                raise ValueError(
                    f"compare_et.{source}: {value!r} is not an Et (a finite number in"
                    f" [0, {MAX_COMPARE_ET:g}])"
                )
        if not 0 < self.duration_s <= 24 * 3600:
            raise ValueError("duration_s: must be in (0, 86400] s")
        if not 0 <= self.settle_s <= 600:
            raise ValueError("settle_s: must be in [0, 600] s")

    def requests(self) -> list[dict[str, Any]]:
        """The control requests that set this step up (while disarmed), in order."""
        out = []
        for cmd, section in (
            ("actuator", self.actuator),
            ("set_controller", self.controller),
            ("set_profile", self.reference),
        ):
            if section is None:
                continue
            fields = self.given[cmd]
            req = {k: getattr(section, k) for k in fields}
            out.append(
                {"cmd": cmd, **{k: str(v) if isinstance(v, Path) else v for k, v in req.items()}}
            )
        if self.hil is not None:
            h = self.hil
            run = {"law": h.law, "duration_s": self.duration_s}
            if h.compensation is not None:
                run["compensation"] = h.compensation
            out.append({"cmd": "set_hil", **run})
        if self.adaptation is not None:  # after set_controller, which builds a new one
            frozen = self.adaptation == "off"
            out += [{"cmd": "reset_adaptation"}, {"cmd": "freeze_adaptation", "frozen": frozen}]
        return out


@dataclass(frozen=True)
class Plan:
    name: str
    path: Path
    steps: tuple[Step, ...]
    rig: str | None = None  # the rig it is meant for (--rig overrides)
    description: str = ""

    @property
    def hil_scenario(self) -> Path | None:
        """The scenario of the plan's `hil` steps (one: a daemon runs one), or None."""
        return next((s.hil.scenario for s in self.steps if s.hil is not None), None)


@dataclass(frozen=True)
class _Header:
    name: str
    rig: str | None = None
    description: str = ""

    def check(self) -> None:
        _one_line("name", self.name)
        if self.rig is not None:
            _one_line("rig", self.rig)


def _one_line(field_name: str, text: str) -> None:
    """A name a terminal, a log line, the JUnit report and the catalog show: printable, one
    line, of bounded length (`safe_text.one_line` would change it)."""
    if one_line(text) != text:
        raise ValueError(
            f"{field_name}: {one_line(text, 60)}: one printable line of at most {MAX_CHARS}"
            " characters (no control character, line break or bidi override)"
        )


def load_plan(path: str | Path) -> Plan:
    """Parse and check a plan file; PlanError (one line: file, step, field) when it cannot run."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError:
        size = 0  # load_toml names what is wrong with the file
    if size > MAX_PLAN_BYTES:
        raise PlanError(
            f"{path}: {size} bytes, over the limit of {MAX_PLAN_BYTES} for a plan (at most"
            f" {MAX_STEPS} steps)"
        )
    try:
        table = load_toml(path)
    except ConfigError as exc:
        raise PlanError(str(exc)) from None
    source = str(path)
    unknown = sorted(set(table) - {"plan", "step"})
    if unknown:
        raise PlanError(f"{source}: {unknown[0]}: unknown table (known: plan, step)")
    try:
        header = parse(_Header, table.get("plan", {}), source, "plan")
    except ConfigError as exc:
        raise PlanError(str(exc)) from None
    steps = table.get("step")
    if not isinstance(steps, list) or not steps:
        raise PlanError(f"{source}: step: a plan needs at least one [[step]]")
    if len(steps) > MAX_STEPS:
        raise PlanError(
            f"{source}: step: {len(steps)} steps, over the limit of {MAX_STEPS} (split the plan)"
        )
    parsed = tuple(_step(i, raw, source) for i, raw in enumerate(steps, start=1))
    _check_hil_steps(parsed, source)
    _check_floors(parsed, source)
    return Plan(
        name=header.name,
        path=path,
        steps=parsed,
        rig=header.rig,
        description=header.description,
    )


def _step(index: int, raw: Any, source: str) -> Step:
    name = raw.get("name") if isinstance(raw, dict) else None
    where = f"step {index} ({name})" if isinstance(name, str) else f"step {index}"
    if not isinstance(raw, dict):
        raise PlanError(f"{source}: {where}: expected a table")
    if "given" in raw:  # the plan's own bookkeeping, not a field a plan sets
        raise PlanError(f"{source}: {where}.given: unknown field")
    table = dict(raw)
    given: dict[str, tuple[str, ...]] = {}
    for key, cmd in (
        ("actuator", "actuator"),
        ("controller", "set_controller"),
        ("reference", "set_profile"),
    ):
        sub = table.get(key)
        if isinstance(sub, dict):
            given[cmd] = tuple(sub)
            if key == "controller" and "model" not in sub:
                needs = CONTROLLERS.get(sub.get("name", "network_inversion"))
                if needs is not None and needs.needs_model:
                    table[key] = {**sub, "model": _DAEMONS_MODEL}
    try:
        step = parse(Step, table, source, where)
    except ConfigError as exc:
        raise PlanError(str(exc)) from None
    if step.hil is not None:
        mixed = [key for key in ("actuator", "reference", "settle_s") if key in raw]
        if mixed:
            raise PlanError(
                f"{source}: {where}.{mixed[0]}: a hil step's run sets the actuator (STREAM) and"
                " the force reference (the law's) and starts as it is armed: leave it out"
            )
        step = replace(step, settle_s=0.0)
    else:
        hil_only = [k for k in HIL_CRITERIA if getattr(step.criteria, k) is not None]
        if hil_only:
            raise PlanError(
                f"{source}: {where}.criteria.{hil_only[0]}: a criterion of a hil step (this"
                " step has no `hil`)"
            )
    return replace(step, given=given)


def _check_floors(steps: tuple[Step, ...], source: str) -> None:
    """A step's `floor_of` names one other step of the plan, which is no floor itself."""
    by_name: dict[str, list[Step]] = {}
    for step in steps:
        by_name.setdefault(step.name, []).append(step)
    for index, step in enumerate(steps, start=1):
        name = step.floor_of
        if name is None:
            continue
        where = f"{source}: step {index} ({step.name}).floor_of: {name!r}"
        named = by_name.get(name, [])
        if len(named) != 1 or named[0] is step:
            what = "no other step" if not named or named[0] is step else "several steps"
            raise PlanError(f"{where}: {what} of the plan has this name")
        if named[0].floor_of is not None:
            raise PlanError(f"{where}: that step is itself a floor (of {named[0].floor_of!r})")


def _check_hil_steps(steps: tuple[Step, ...], source: str) -> None:
    """A plan's hil steps run one scenario (a daemon runs one), which loads with each law."""
    from mrrig.hil.scenario import load_scenario

    first: Path | None = None
    for index, step in enumerate(steps, start=1):
        if step.hil is None:
            continue
        where = f"{source}: step {index} ({step.name}).hil"
        if first is None:
            first = step.hil.scenario
        elif step.hil.scenario != first:
            raise PlanError(
                f"{where}.scenario: {step.hil.scenario}: the plan's hil steps run on one daemon's"
                f" scenario: every one names {first}"
            )
        if not step.hil.scenario.is_file():
            raise PlanError(f"{where}.scenario: {step.hil.scenario}: no such file")
        try:
            scenario = load_scenario(step.hil.scenario, law=step.hil.law)
        except ConfigError as exc:
            raise PlanError(f"{where}: {exc}") from None
        if not scenario.period_s <= step.duration_s <= 3600.0:
            raise PlanError(
                f"{source}: step {index} ({step.name}).duration_s: {step.duration_s:g} s, not a"
                f" scenario's run ([{scenario.period_s:g}, 3600] s)"
            )
        try:  # a playback's step within its record
            replace(scenario, duration_s=step.duration_s).check()
        except ValueError as exc:
            raise PlanError(f"{source}: step {index} ({step.name}).{exc}") from None
