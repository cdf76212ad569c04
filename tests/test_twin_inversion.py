"""Issue 36, item 3: the Bouc-Wen twin (a plant file, `mrrig identify`) is a forward model the
daemon inverts (mrrig/loop/twin_model.py, network inversion with a plant file as its model).

The twin's state is carried frame to frame as the plant integrates it, the command solved
exactly for a reachable force and clamped to the rig's range for an unreachable one, a twin in
volts refused on a rig in amperes unless mapped (`mrrig identify --map-model`), and the
daemon, inverting the twin that firmware_sim runs, tracks its force
(tests/test_twin_inversion_tracking.py, a process module)."""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from damper.plant import BoucWenDamper, BoucWenParams
from damper.plant_file import Plant, load_plant, save_plant
from mrrig.config import load_config
from mrrig.loop.adaptation import AdaptationSettings
from mrrig.loop.build import build_controller
from mrrig.loop.controllers import ControllerSettings, make_controller
from mrrig.loop.mlp import ModelError
from mrrig.loop.model_fit import COST_BUDGET_S, frame_cost_s
from mrrig.loop.state_inversion import TwinInversion
from mrrig.loop.twin_model import SUBSTEP_S, TwinModel, TwinTracker, load_forward_model
from tests.conftest import REPO, rig_config
from tests.rig_harness import ScriptedRig

DT_S = 0.002
I_MAX_A = 2.0
PLANT = Plant(BoucWenParams.preset("paper-volt"), offset_n=12.5, command_unit="A")


def _motion(n: int, amp_m: float = 0.006, freq_hz: float = 2.0):
    t = np.arange(n) * DT_S
    w = 2 * np.pi * freq_hz
    return amp_m * np.sin(w * t), amp_m * w * np.cos(w * t), -amp_m * w * w * np.sin(w * t)


def _tracker_at(frame: int, command_a: float) -> tuple[TwinTracker, np.ndarray, np.ndarray]:
    """A twin advanced `frame` frames on a sine motion, `command_a` held throughout."""
    x, xd, _ = _motion(frame + 2)
    twin = TwinTracker(TwinModel(PLANT), DT_S, I_MAX_A)
    for k in range(frame + 1):
        twin.advance(float(x[k]), float(xd[k]))
        twin.command = command_a
    return twin, x, xd


def _plant_force_next(twin: TwinTracker, x1: float, xd1: float, command_a: float) -> float:
    """The plant's own force one period on from the twin's state, `command_a` held."""
    plant = BoucWenDamper(PLANT.params, SUBSTEP_S)
    plant.reset(twin.x, twin.xd)
    plant.set_state(twin.damper.state, twin.x, twin.xd)
    return plant.step(x1, xd1, command_a, DT_S) + PLANT.offset_n


@pytest.mark.parametrize("frame", [40, 120, 130])  # moving out, near the reversal, moving back
def test_the_twin_inversion_hits_a_reachable_force(frame):
    twin, x, xd = _tracker_at(frame, 1.1)
    x1, xd1 = float(x[frame + 1]), float(xd[frame + 1])
    # the force the command held so far gives: its own command, to rounding
    target = _plant_force_next(twin, x1, xd1, 1.1)
    assert twin.solve(target, x1, xd1) == pytest.approx(1.1, abs=1e-9)
    # another reachable force: the plant, sent the solved command, gives it to within 0.5 N
    twin.command = 1.1
    target = _plant_force_next(twin, x1, xd1, 0.4)
    command = twin.solve(target, x1, xd1)
    assert 0.0 < command < I_MAX_A
    assert _plant_force_next(twin, x1, xd1, command) == pytest.approx(target, abs=0.5)
    assert abs(target - _plant_force_next(twin, x1, xd1, 1.1)) > 50.0  # a different force


def test_the_twin_inversion_clamps_an_unreachable_force_to_the_rigs_range():
    twin, x, xd = _tracker_at(40, 1.1)
    x1, xd1 = float(x[41]), float(xd[41])
    assert xd1 > 0.0  # the force rises with the command
    top = _plant_force_next(twin, x1, xd1, I_MAX_A)
    assert twin.solve(top + 500.0, x1, xd1) == I_MAX_A
    twin.command = 1.1
    assert twin.solve(_plant_force_next(twin, x1, xd1, 0.0) - 500.0, x1, xd1) == 0.0
    twin.command = 1.1
    assert twin.solve(math.inf, x1, xd1) == I_MAX_A


def test_the_twin_state_carried_across_frames_matches_the_plants_own_integration():
    """The controller's twin, advanced each frame on the motion with the commands it sent,
    is the plant integrated (as firmware_sim does) with those commands held."""
    n = 400
    x, xd, xdd = _motion(n + 1, amp_m=0.01, freq_hz=3.0)
    f_des = 600.0 * np.sin(2 * np.pi * 1.5 * np.arange(n + 1) * DT_S) + 300.0
    ctrl = TwinInversion(I_MAX_A, TwinModel(PLANT), DT_S, feedback_tau_s=0.0, ahead=True)
    plant = BoucWenDamper(PLANT.params, SUBSTEP_S)
    f_meas = plant.reset(float(x[0]), float(xd[0]), 0.0) + PLANT.offset_n
    commands, worst = [], 0.0
    for k in range(n):
        if k:
            f_meas = plant.step(float(x[k]), float(xd[k]), commands[-1], DT_S) + PLANT.offset_n
        commands.append(
            ctrl.command_one(x[k], xd[k], xdd[k], f_meas, f_des[k], float(f_des[k + 1]))
        )
        twin_state, plant_state = ctrl.lanes[0].damper.state, plant.state
        worst = max(worst, *(abs(a - b) for a, b in zip(twin_state, plant_state, strict=True)))
    assert worst <= 1e-12
    assert len(set(np.round(commands, 6))) > 100  # the commands varied: a real test of the hold


def test_the_daemon_inverts_a_twin_in_amperes_and_refuses_one_in_volts(tmp_path):
    amps = tmp_path / "twin-a.json"
    save_plant(PLANT, amps)
    ctrl = build_controller(load_config(rig_config(tmp_path, "ws://127.0.0.1:1/", amps)))
    assert isinstance(ctrl, TwinInversion) and ctrl.name == "network_inversion"
    assert ctrl.ahead and ctrl.feedback_tau_s == 0.0  # configs/rig.toml's, as for a network
    cost_s, _ = frame_cost_s(ctrl, DT_S)
    print(f"twin inversion: work per frame {cost_s * 1e6:.0f} us (median)")
    assert cost_s <= COST_BUDGET_S
    volts = tmp_path / "twin-v.json"
    save_plant(replace(PLANT, command_unit="V"), volts)
    with pytest.raises(ModelError, match=r"twin-v.json: input_units\[2\] \(current\): expected A"):
        build_controller(load_config(rig_config(tmp_path, "ws://127.0.0.1:1/", volts)))
    mapped = tmp_path / "twin-mapped.json"
    subprocess.run(
        [sys.executable, "-m", "mrrig", "identify", "--map-model", str(volts)]
        + ["--command-per-a", "2", "--out", str(mapped)],
        cwd=REPO,
        check=True,
        capture_output=True,
    )
    back = load_plant(mapped)
    assert back.command_unit == "A" and back.params.alpha_b == 2 * PLANT.params.alpha_b
    assert isinstance(
        build_controller(load_config(rig_config(tmp_path, "ws://127.0.0.1:1/", mapped))),
        TwinInversion,
    )


def test_a_twin_takes_the_exact_solve_without_adaptation(tmp_path):
    path = tmp_path / "twin.json"
    save_plant(PLANT, path)
    model = load_forward_model(path)
    assert isinstance(model, TwinModel) and model.plant == PLANT
    with pytest.raises(ValueError, match="method 'flow': a twin forward model is solved exactly"):
        make_controller(
            "network_inversion", ControllerSettings(I_MAX_A, model=model, method="flow")
        )
    with pytest.raises(ValueError, match="adaptation: not with a twin forward model"):
        make_controller(
            "network_inversion",
            ControllerSettings(I_MAX_A, model=model, adaptation=AdaptationSettings()),
        )


def test_set_model_takes_a_twin_in_amperes_and_refuses_one_in_volts_with_one_line(tmp_path):
    """The control plane's `set_model` (the daemon's loop on a virtual bus) reads a plant file
    as it reads a network; the twin then answers frames."""
    (tmp_path / "models").mkdir()
    # the test plays the firmware and sends no frame while the daemon prepares a model (the
    # twin's self-check, issue 40: about 0.2 s of CPU): a sensor timeout longer than that
    overrides = {
        "control": {"model_dirs": [str(tmp_path / "models")]},
        "loop": {"timeout_periods": 500},
    }
    start, volts = tmp_path / "models" / "start.json", tmp_path / "models" / "volts.json"
    save_plant(PLANT, start)
    save_plant(replace(PLANT, command_unit="V"), volts)
    other = tmp_path / "models" / "other.json"
    save_plant(replace(PLANT, offset_n=-40.0), other)
    overrides["controller"] = {"model": str(start), "name": "network_inversion"}
    with ScriptedRig(tmp_path, overrides=overrides) as rig:
        assert isinstance(rig.daemon.controller, TwinInversion)
        rig.exchange()  # armed on start: disarmed to change the model
        assert rig.request({"cmd": "disarm"})["ok"]
        reply = rig.request({"cmd": "set_model", "path": str(volts)})
        assert reply == {
            "ok": False,
            "error": f"{volts}: input_units[2] (current): expected A (DamperCommand"
            ".CurrentSetpoint in mrrig.dbc, loop.i_max_a), found 'V'",
        }
        reply = rig.request({"cmd": "set_model", "path": str(other)})
        assert reply["ok"] and reply["settings"]["model"] == str(other), reply
        twin = rig.daemon.controller
        assert isinstance(twin, TwinInversion) and twin.lanes[0].offset_n == -40.0
        assert rig.request({"cmd": "arm"})["ok"]
        for _ in range(3):
            cmd = rig.exchange()
        assert cmd["Mode"] == 1 and 0.0 <= cmd["CurrentSetpoint"] <= I_MAX_A  # ACTIVE
