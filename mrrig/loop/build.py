"""The controller and the force reference a daemon config names, built and checked before the
loop runs (and again by the control thread for `set_controller` / `set_profile`): a model that
does not fit the rig stops here with one line."""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import replace
from pathlib import Path

from mrrig.config import DaemonConfig, ReferenceSection
from mrrig.loop import reference as ref
from mrrig.loop.controllers import (
    CONTROLLERS,
    FORWARD_INPUTS,
    Controller,
    ControllerSettings,
    make_controller,
)
from mrrig.loop.estimation import RealtimeKalman
from mrrig.loop.inversion import DEFAULT_CONTINUITY
from mrrig.loop.mlp import MLP, ModelError
from mrrig.loop.model_fit import RigUnits, check_cost, check_period, check_units
from mrrig.loop.model_plausibility import self_check
from mrrig.loop.twin_model import TwinModel, load_forward_model
from mrrig.rigio.canbus.codec import Codec
from mrrig.typed_config import ConfigError

log = logging.getLogger(__name__)


@functools.cache
def rig_units() -> RigUnits:
    """The units a model's signals must have: the DBC's (`model_fit.check_units`), which the
    config's limits share (loop.x_range_m, loop.i_max_a, loop.f_range_n)."""
    codec = Codec()
    dbc = codec.dbc_path.name

    def where(message: str, signal: str, config: str) -> tuple[str, str]:
        return codec.unit(message, signal), f"{message}.{signal} in {dbc}, {config}"

    x, x_where = where("RigSensors", "Displacement", "loop.x_range_m")
    command = where("DamperCommand", "CurrentSetpoint", "loop.i_max_a")
    return {
        "x": (x, x_where),
        "xd": (f"{x}/s", f"the rate of {x_where}"),
        "xdd": (f"{x}/s^2", f"the rate of rate of {x_where}"),
        "current": command,
        "v": command,  # the RNN's previous commands
        "command": command,
        "f_des": where("DamperCommand", "DesiredForce", "loop.f_range_n"),
        "force": where("RigSensors", "Force", "loop.f_range_n"),
    }


def build_controller(cfg: DaemonConfig, section=None, model: MLP | None = None) -> Controller:
    """The configured controller, from the registry (`controllers.make_controller`); a model
    that does not fit stops here with one line: units other than the rig's, or a controller
    whose work per frame is over the loop's budget (measured here, off the loop:
    `model_fit`). `model`: the section's model, already read (the control plane reads it
    under limits)."""
    c = section or cfg.controller
    i_max, dt = cfg.loop.i_max_a, cfg.loop.period_s
    if c.name == "constant" and not 0 <= c.current_a <= i_max:
        raise ConfigError(f"{cfg.source}: controller.current_a: outside [0, {i_max}] A")
    if model is None and CONTROLLERS[c.name].needs_model:
        model = load_model(c.model, cfg.source)
    if model is not None:
        check_units(model, c.model, rig_units())
        check_period(model, c.model, dt)
    if c.on_current_a is not None and c.on_current_a > i_max:
        raise ConfigError(f"{cfg.source}: controller.on_current_a: above loop.i_max_a {i_max} A")
    settings = ControllerSettings(
        i_max, dt_s=dt, model=model, current_a=c.current_a, gain=c.gain, b=c.b,
        on_current_a=c.on_current_a,
    )  # fmt: skip
    if c.name == "network_inversion":
        continuity = c.continuity
        if continuity is None:
            continuity = model_continuity(model, c.model)
            log.info("%s: continuity %g, the model's own", c.model, continuity)
        ahead = c.ahead
        if ahead and len(model.input_names) > len(FORWARD_INPUTS):
            log.warning(
                "%s: a model with history inputs: network inversion solves for the present "
                "instant (the one-step-ahead solve takes a model of x, xd, xdd, current)",
                c.model,
            )
            ahead = False
        if ahead and model.meta.get("current_input", "commanded") != "lagged":
            log.warning(
                "%s: a model of the commanded current (no current_input = 'lagged', no "
                "lag_tau_s): network inversion solves one step ahead without inverting the "
                "coil's lag; for that, train on the lagged current "
                "(mrrig train --current-input lagged)",
                c.model,
            )
        settings = replace(
            settings,
            method=c.method,
            feedback_tau_s=c.feedback_tau_s if c.feedback else None,
            continuity=continuity,
            ahead=ahead,
            adaptation=cfg.adaptation.settings(),
        )
    try:
        controller, spare = (make_controller(c.name, settings) for _ in range(2))
    except ValueError as exc:
        raise ModelError(f"{c.model}: controller {c.name}: {exc}") from None
    check_cost(
        spare,
        c.model if model is not None else f"controller {c.name}",
        dt,
        cfg.loop.work_budget_us * 1e-6,
    )
    if model is not None:  # a short closed loop on the model's own envelope (the spare's)
        x_half = 0.5 * (cfg.loop.x_range_m[1] - cfg.loop.x_range_m[0])
        checked = self_check(spare, model, c.model, dt, i_max, x_half)
        log.info("%s: self-check passed in %.0f ms", c.model, checked.seconds * 1e3)
    if cfg.loop.numerics == "compiled":
        from mrrig.loop import compiled  # numba (LLVM) imported only for the compiled path

        return compiled.compile_controller(controller)
    return controller


def model_continuity(model: MLP, path: Path | None) -> float:
    """The continuity `mrrig train` chose for the model on its training rows (the on-line
    inversion's smallest current RMSE there: `training.choose_continuity`); for a model
    without one, `DEFAULT_CONTINUITY` (the root)."""
    mu = model.meta.get("online_continuity", DEFAULT_CONTINUITY)
    if isinstance(mu, bool) or not isinstance(mu, int | float) or not 0 <= mu < math.inf:
        raise ModelError(f"{path}: meta.online_continuity: expected a number >= 0, got {mu!r}")
    return float(mu)


def load_model(path: Path | None, source: str) -> MLP | TwinModel:
    if path is None:
        raise ModelError(f"{source}: controller.model: no model file given")
    if not Path(path).is_file():
        raise ModelError(
            f"{source}: controller.model: {path} not found (train one: mrrig train ...)"
        )
    return load_forward_model(path)  # a network, or a twin (a plant file)


def kalman(period_s: float, q: float, r0: float, numerics: str) -> RealtimeKalman:
    """The daemon's estimate, compiled with `numerics="compiled"` (`mrrig.loop.compiled`)."""
    if numerics == "compiled":
        from mrrig.loop import compiled  # numba (LLVM) imported only for the compiled path

        return compiled.kalman(period_s, q, r0, True)
    return RealtimeKalman(period_s, q=q, r0=r0)


def build_reference(
    r: ReferenceSection, dt_s: float, numerics: str = "python"
) -> ref.ForceReference:
    """The reference a section names; a reference damper stepped in compiled code with
    `numerics="compiled"` (`mrrig.loop.compiled`)."""
    reference = _reference(r, dt_s)
    if numerics == "compiled":
        from mrrig.loop import compiled  # numba (LLVM) imported only for the compiled path

        return compiled.compile_reference(reference)
    return reference


def _reference(r: ReferenceSection, dt_s: float) -> ref.ForceReference:
    if r.kind == "constant":
        return ref.Constant(r.offset_n)
    if r.kind == "sine":
        return ref.Sine(r.offset_n, r.amplitude_n, r.freq_hz)
    if r.kind == "noise":
        return ref.Noise(r.offset_n, r.amplitude_n, r.freq_hz, r.seed, dt_s)
    if r.kind == "csv":
        return ref.CsvSeries(r.path)
    if r.kind == "bouc_wen":
        return ref.BoucWenReference(r.preset, r.current_a, r.current_amp_a, r.current_freq_hz, dt_s)
    if r.kind == "paper_case":
        return ref.PaperCase(r.case, r.current_scale, r.preset, dt_s)
    return ref.External(r.timeout_s)
