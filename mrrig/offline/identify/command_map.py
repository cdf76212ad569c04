"""A forward model of a command in volts taken to the rig's amperes: the lab's mapping of the
rig's current setpoint to the measured damper's driver input, v = command_per_a * i (the same
`[plant] command_per_a` the twin runs with). The network is unchanged; its command input's
normalisation takes i instead of v: (v - mean) / std = (i - mean / k) / (std / k).

What the mapping does not change: the data's own sample period (a model with history inputs
counts samples of its data, and the daemon refuses one at another rate: train without
history, or on data at the rig's rate), and the range the model was trained on (the envelope's
command range, i_max, current_range_a are mapped with it).
"""

from __future__ import annotations

import copy
from dataclasses import replace

from damper.plant_file import Plant
from mrrig.loop.mlp import MLP, ModelError

COMMAND_COLUMN = 3  # the forward network's inputs: x, xd, xdd, command, then history


def model_in_amperes(model: MLP, command_per_a: float, source: str = "model") -> MLP:
    """A copy of a forward model of a command in V whose command is in A (v = k i)."""
    if not command_per_a > 0.0:
        raise ValueError(f"command_per_a: must be > 0, got {command_per_a}")
    unit = model.meta.get("command_unit", "A")
    if unit != "V":
        raise ModelError(f"{source}: meta.command_unit: expected V to map to A, found {unit!r}")
    if any(n.startswith("current_") for n in model.input_names):
        raise ModelError(f"{source}: input_names: past commands are not mapped (train without)")
    out = copy.deepcopy(model)
    k = command_per_a
    out.in_mean[COMMAND_COLUMN] /= k
    out.in_std[COMMAND_COLUMN] /= k
    out.input_units[COMMAND_COLUMN] = "A"
    meta = out.meta
    meta["command_unit"] = "A"
    meta["command_map"] = {"from": "V", "command_per_a": k}
    for key in ("i_max_a",):
        if isinstance(meta.get(key), int | float):
            meta[key] = meta[key] / k
    if isinstance(meta.get("current_range_a"), list):
        meta["current_range_a"] = [v / k for v in meta["current_range_a"]]
    env = meta.get("envelope")
    if isinstance(env, dict) and isinstance(env.get("lo"), list) and len(env["lo"]) > 3:
        env["lo"][3] /= k
        env["hi"][3] /= k
    return out


def plant_in_amperes(plant: Plant, command_per_a: float, source: str = "plant") -> Plant:
    """A copy of a twin of a command in V whose command is in A (v = k i)."""
    if not command_per_a > 0.0:
        raise ValueError(f"command_per_a: must be > 0, got {command_per_a}")
    if plant.command_unit != "V":
        raise ModelError(
            f"{source}: command_unit: expected V to map to A, found {plant.command_unit!r}"
        )
    k = command_per_a
    p = plant.params
    params = replace(p, c0b=p.c0b * k, c1b=p.c1b * k, alpha_b=p.alpha_b * k)  # eqs 33-35
    identified = {**plant.identified, "command_map": {"from": "V", "command_per_a": k}}
    return replace(plant, params=params, command_unit="A", identified=identified)
