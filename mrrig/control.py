"""Control requests to the daemon (`mrrig/<rig>/control`): validated, then applied.

A request is a JSON object with a `cmd`; the reply is `{"ok": true, ...}` or
`{"ok": false, "error": "..."}`. An invalid request (unknown command, missing or out-of-range
value, wrong state) changes nothing.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mrrig.config import ActuatorSection, reference_from_table
from mrrig.controllers import CONTROLLER_NAMES
from mrrig.errors import MrrigError
from mrrig.samples import RigState
from mrrig.typed_config import ConfigError, parse

if TYPE_CHECKING:
    from mrrig.daemon import Daemon


class RequestError(MrrigError, ValueError):
    """A control request that cannot be carried out; nothing was changed."""


def _arm(d: Daemon, req: dict) -> dict:
    ok, msg, events = d.supervisor.arm(d.now())
    if not ok:
        raise RequestError(msg)
    if events:
        d.controller.reset(1)
        d.reset_reference(d.now(), d.last_x)
    d._emit(events)
    return {"state": d.supervisor.state.name, "message": msg}


def _disarm(d: Daemon, req: dict) -> dict:
    d._emit(d.supervisor.disarm(d.now(), "disarmed by request"))
    return {"state": d.supervisor.state.name}


def _require_not_armed(d: Daemon, what: str) -> None:
    if d.supervisor.state is RigState.ARMED:
        raise RequestError(f"{what} only when not armed (disarm first)")


def _set_controller(d: Daemon, req: dict) -> dict:
    from mrrig.daemon import build_controller

    _require_not_armed(d, "set_controller")
    name = req.get("name")
    if name not in CONTROLLER_NAMES:
        raise RequestError(
            f"name: unknown controller {name!r} (known: {', '.join(CONTROLLER_NAMES)})"
        )
    keys = ("model", "method", "ahead", "feedback", "feedback_tau_s", "continuity", "current_a")
    table = {k: v for k, v in req.items() if k in keys}
    table["name"] = name
    if "model" not in table and d.cfg.controller.model is not None:
        table["model"] = str(d.cfg.controller.model)
    section = _parse_section(type(d.cfg.controller), table, "controller")
    d.controller = _built(lambda: build_controller(d.cfg, section))
    d.controller.reset(1)
    d.reset_reference(d.now(), d.last_x)  # its desired forces ahead, if it wants them
    d.cfg = replace(d.cfg, controller=section)
    d._send_status(force=True)
    return {"controller": d.controller.name}


def _set_model(d: Daemon, req: dict) -> dict:
    path = req.get("path")
    if not isinstance(path, str) or not path:
        raise RequestError("path: a model file path is required")
    if d.cfg.controller.name not in ("network_inversion", "supervised", "rnn"):
        raise RequestError(f"controller {d.cfg.controller.name} uses no model")
    return _set_controller(d, {"name": d.cfg.controller.name, "model": str(Path(path))})


def _set_profile(d: Daemon, req: dict) -> dict:
    from mrrig.daemon import build_reference

    table = {k: v for k, v in req.items() if k not in ("cmd", "id")}
    try:
        section = reference_from_table(table, "request")
    except ConfigError as exc:
        raise RequestError(str(exc).removeprefix("request: ")) from None
    new = _built(lambda: build_reference(section, d.period_s))
    d.reset_reference(d.now(), d.last_x, new)
    d.cfg = replace(d.cfg, reference=section)
    d._send_status(force=True)
    return {"reference": new.kind}


def _actuator(d: Daemon, req: dict) -> dict:
    table = {k: v for k, v in req.items() if k not in ("cmd", "id")}
    section = _parse_section(ActuatorSection, table, "actuator")
    d.actuator = section
    d._send_actuator()
    return {
        "waveform": section.waveform,
        "amplitude_m": section.amplitude_m,
        "frequency_hz": section.frequency_hz,
    }


def _status(d: Daemon, req: dict) -> dict:
    return {"status": d.status()}


def _adaptive(d: Daemon):
    adapt = getattr(d.controller, "adapt", None)
    if adapt is None:
        raise RequestError(
            f"controller {d.controller.name} has no on-line adaptation ([adaptation] enabled)"
        )
    return adapt


def _reset_adaptation(d: Daemon, req: dict) -> dict:
    """Back to the model as trained (gain 1, offset 0); allowed while armed."""
    adapt = _adaptive(d)
    adapt.reset(adapt.theta.shape[0])
    d._emit([d.supervisor.event(d.now(), "adaptation", "adaptation reset by request")])
    return {"adaptation": adapt.state()}


def _freeze_adaptation(d: Daemon, req: dict) -> dict:
    """`frozen`: true stops the updates (the adapted state stays in use), false resumes."""
    frozen = req.get("frozen", True)
    if not isinstance(frozen, bool):
        raise RequestError(f"frozen: expected true or false, got {frozen!r}")
    adapt = _adaptive(d)
    adapt.frozen = frozen
    what = "frozen" if frozen else "resumed"
    d._emit([d.supervisor.event(d.now(), "adaptation", f"adaptation {what} by request")])
    return {"adaptation": adapt.state()}


COMMANDS = {
    "arm": _arm,
    "disarm": _disarm,
    "set_controller": _set_controller,
    "set_model": _set_model,
    "set_profile": _set_profile,
    "actuator": _actuator,
    "status": _status,
    "reset_adaptation": _reset_adaptation,
    "freeze_adaptation": _freeze_adaptation,
}


def _parse_section(cls, table: dict, prefix: str):
    try:
        return parse(cls, table, "request", prefix)
    except ConfigError as exc:
        raise RequestError(str(exc).removeprefix("request: ")) from None


def _built(factory):
    try:
        return factory()
    except (ValueError, OSError) as exc:
        raise RequestError(str(exc)) from None


def handle(d: Daemon, req: Any) -> dict[str, Any]:
    """Apply one request; never raises: errors become `{"ok": false, "error": ...}`."""
    if not isinstance(req, dict):
        return {"ok": False, "error": "request must be a JSON object"}
    cmd = req.get("cmd")
    fn = COMMANDS.get(cmd) if isinstance(cmd, str) else None
    if fn is None:
        return {"ok": False, "error": f"unknown command {cmd!r} (known: {', '.join(COMMANDS)})"}
    for k, v in req.items():
        if isinstance(v, float) and not math.isfinite(v):
            return {"ok": False, "error": f"{k}: non-finite number"}
    try:
        return {"ok": True, **fn(d, req)}
    except RequestError as exc:
        return {"ok": False, "error": str(exc)}
