"""The daemon's check of a controller's work per frame (mrrig.loop.model_fit.frame_cost_s)
counts the controller's work, not the time its thread waited: on a loaded machine a
wall-clock measure refused a model of 57 us a frame as 396 us (the walkthrough's set_model)."""

from __future__ import annotations

import threading
import time

import pytest

from mrrig.config import load_config
from mrrig.loop.controllers import ControllerSettings, make_controller
from mrrig.loop.mlp import ModelError
from mrrig.loop.model_fit import COST_BUDGET_S, check_cost, frame_cost_s
from mrrig.typed_config import ConfigError
from tests.conftest import REPO


def test_a_frame_whose_thread_waits_off_the_cpu_is_measured_by_its_work() -> None:
    ctrl = make_controller("constant", ControllerSettings(i_max=2.0, current_a=0.5))
    command_one = ctrl.command_one
    held = threading.Event()

    def preempted(*args):
        # off the CPU for 2 ms, as a thread the scheduler or the GIL holds back is
        held.wait(0.002)
        return command_one(*args)

    ctrl.command_one = preempted
    t0 = time.perf_counter()
    cost_s, frames = frame_cost_s(ctrl, 0.002)
    wall_s = time.perf_counter() - t0
    assert frames >= 3
    assert wall_s >= frames * 0.002  # each frame waited
    assert cost_s < COST_BUDGET_S, f"{cost_s * 1e6:.0f} us"


def test_the_start_up_check_holds_the_controller_to_the_loops_work_budget(tmp_path) -> None:
    """`loop.work_budget_us` (the spec's 300 us by default; CI's emulated VM allows more): a
    controller over it is refused in one line naming the budget; a budget beyond one period is
    a config error naming the field."""
    ctrl = make_controller("constant", ControllerSettings(i_max=2.0, current_a=0.5))
    check_cost(ctrl, "controller constant", 0.002)  # the spec's budget: a constant is within
    with pytest.raises(ModelError, match=r"over the loop's budget of 0 us \(loop.work_budget_us"):
        check_cost(ctrl, "controller constant", 0.002, budget_s=1e-9)
    rig = tmp_path / "rig.toml"
    rig.write_text(
        (REPO / "configs/vcan-vm.toml")
        .read_text()
        .replace("work_budget_us = 2000", "work_budget_us = 2500")
    )
    with pytest.raises(ConfigError, match=r"work_budget_us: must be in \[10, 2000\] us"):
        load_config(rig)
    assert load_config(REPO / "configs/vcan-vm.toml").loop.work_budget_us == 2000
    assert load_config(REPO / "configs/rig.toml").loop.work_budget_us == 300
