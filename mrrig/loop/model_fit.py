"""Whether a model fits the rig, checked where it is prepared (the daemon's start-up, the
control worker for `set_controller` / `set_model`), off the loop: its units against the rig's
(the DBC's signals, which the config's limits share), the sample period of its history inputs
against the rig's, and its controller's work per frame
against the loop's budget. A model that does not fit is refused with one line.

Pure: the rig's units come in as a table (the daemon reads them from the DBC).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mrrig.loop.controllers import ControlInput, Controller
from mrrig.loop.mlp import MLP, ModelError

# spec/system.md's performance budget: the loop's work per frame (receive -> send) p99 <= 300
# us on this project's 2-core VM. A controller whose typical frame (median) takes more cannot
# meet it: the frame's command, its work ahead and the model force it records, at most this
COST_BUDGET_S = 300e-6
COST_FRAMES = 25  # frames measured, or as many as COST_TIME_S allows (at least 3)
COST_TIME_S = 0.25

# the unit a model's input or output must have: (unit, where the rig says so), per signal
RigUnits = Mapping[str, tuple[str, str]]


def _signal(name: str) -> str:
    """The signal of an input name: `x_3` (x, 3 samples back) and `v_1` (the RNN's previous
    command) are in the units of `x` and `v`."""
    base, sep, k = name.rpartition("_")
    return base if sep and k.isdigit() else name


def check_units(model: MLP, path: Path | str | None, units: RigUnits) -> None:
    """ModelError naming the first field whose unit is not the rig's: an input, the output,
    the command (`meta.command_unit`; a model without one commands a current in A)."""
    found = [
        (f"input_units[{k}] ({name})", _signal(name), unit)
        for k, (name, unit) in enumerate(zip(model.input_names, model.input_units, strict=True))
    ]
    found.append((f"output_unit ({model.output_name})", model.output_name, model.output_unit))
    found.append(("meta.command_unit", "command", model.meta.get("command_unit", "A")))
    for field, signal, unit in found:
        if signal in units and unit != units[signal][0]:
            want, where = units[signal]
            raise ModelError(f"{path}: {field}: expected {want} ({where}), found {unit!r}")


# a model's history taps may sit this far (relative) from the rig's period: they count samples
PERIOD_TOLERANCE = 0.01


def check_period(model: MLP, path: Path | str | None, period_s: float) -> None:
    """ModelError where a model with history inputs (earlier samples: `x_3` is 3 samples back)
    was trained at another sample period than the rig's: its taps would look at other times.
    A model of the present state alone (and the lag's tau, in seconds) fits any rate; one
    that does not record its period (the RNN, trained on the simulator's 500 Hz) is taken."""
    trained = model.meta.get("sample_period_s")
    # a recurrent model's state (mrrig/loop/gru.py) steps once a sample, as taps count them
    recurrent = model.meta.get("kind") == "gru"
    if trained is None or not (recurrent or any(_signal(n) != n for n in model.input_names)):
        return
    if isinstance(trained, bool) or not isinstance(trained, int | float) or not trained > 0:
        raise ModelError(f"{path}: meta.sample_period_s: expected a number > 0, got {trained!r}")
    if abs(trained - period_s) > PERIOD_TOLERANCE * period_s:
        what = "a recurrent state" if recurrent else "history inputs"
        raise ModelError(
            f"{path}: meta.sample_period_s: {what} trained at {trained:.6g} s"
            f" ({1.0 / trained:g} Hz), the rig runs at {period_s:g} s ({1.0 / period_s:g} Hz,"
            " loop.period_s): retrain on data at the rig's rate"
        )


def frame_cost_s(controller: Controller, dt_s: float) -> tuple[float, int]:
    """(median seconds, frames) of the controller's work for one frame of the loop, on a
    sine motion: its command, the on-line learning after it, its work ahead for the next
    frame and the model force. `controller` is a spare one: its state is spent. The work is
    the thread's CPU time: a wait for the CPU or the GIL (a busy machine, the loop's own
    frames) is not the model's cost, and a wall clock refused a 57 us model at 396 us under
    load."""
    controller.reset(1)
    times: list[float] = []
    end = time.perf_counter() + COST_TIME_S
    for k in range(COST_FRAMES):
        if len(times) >= 3 and time.perf_counter() > end:
            break
        w = 2 * np.pi * 2.0 * k * dt_s
        x, xd, xdd = 0.01 * np.sin(w), 0.126 * np.cos(w), -1.58 * np.sin(w)
        f_meas, f_des, f_next = 200.0 + 50 * np.sin(w), 300.0, 300.0
        t0 = time.thread_time()
        i = controller.command_one(x, xd, xdd, f_meas, f_des, f_next)
        controller.after_send()
        controller.prepare_one(x + xd * dt_s, xd + xdd * dt_s, xdd, f_des, f_next)
        s = ControlInput(*(np.array([v]) for v in (x, xd, xdd, f_meas, f_des)))
        controller.model_force(s, np.array([i]))
        times.append(time.thread_time() - t0)
    return statistics.median(times), len(times)


def check_cost(
    controller: Controller,
    path: Path | str | None,
    dt_s: float,
    budget_s: float = COST_BUDGET_S,
) -> None:
    """ModelError with the cost where the controller's work per frame (`frame_cost_s`) is over
    `budget_s` (the spec's by default; `loop.work_budget_us`)."""
    cost, frames = frame_cost_s(controller, dt_s)
    if cost > budget_s:
        model = getattr(controller, "model", None)
        size = f" (hidden {model.hidden})" if isinstance(model, MLP) else ""
        raise ModelError(
            f"{path}: the {controller.name} controller's work per frame with this model{size} "
            f"takes {cost * 1e6:.0f} us (median of {frames} frames), over the loop's budget of "
            f"{budget_s * 1e6:.0f} us (loop.work_budget_us; spec/system.md: work per frame p99 "
            f"<= 300 us): a smaller model, or another method"
        )
