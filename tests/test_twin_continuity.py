"""A twin forward model on the simulated rig's paper cases (issue 43, item 4): the continuity
of its solve (the pull toward the present lagged current that network inversion's exact solve
has), and its state following the rig's motion while disarmed, kept over an arm."""

from __future__ import annotations

import numpy as np

from damper.plant import BoucWenDamper, BoucWenParams
from damper.plant_file import Plant, save_plant
from mrrig.loop.controllers import ControllerSettings, make_controller
from mrrig.loop.twin_model import SUBSTEP_S, TwinModel
from tests.conftest import rig_config
from tests.lockstep_rig import run_lockstep

DT_S = 0.002
I_MAX_A = 2.0
PARAMS = BoucWenParams.preset("rig-current")  # the simulator's damper


def _commands(continuity: float, seconds: float = 2.0) -> np.ndarray:
    """The twin inversion's commands for a reference damper's force (the same damper at a
    constant 0.75 A) on a 1 Hz, 1 cm sine whose estimate carries noise (the Kalman filter's
    on the load cell's and the encoder's: 20 um, 2 mm/s): the ideal command is 0.75 A."""
    ctl = make_controller(
        "network_inversion",
        ControllerSettings(
            i_max=I_MAX_A,
            model=TwinModel(Plant(PARAMS, 0.0, "A")),
            continuity=continuity,
            feedback_tau_s=None,
        ),
    )
    ctl.reset(1)
    reference = BoucWenDamper(PARAMS, SUBSTEP_S)
    rng = np.random.default_rng(0)
    w = 2 * np.pi
    out = []
    for k in range(round(seconds / DT_S)):
        t = k * DT_S
        x, xd = 0.01 * np.sin(w * t), 0.01 * w * np.cos(w * t)
        x1, xd1 = 0.01 * np.sin(w * (t + DT_S)), 0.01 * w * np.cos(w * (t + DT_S))
        if k == 0:
            reference.reset(x, xd, 0.75)
        f_next = reference.step(x1, xd1, 0.75, DT_S)
        xe, xde = x + rng.normal(0, 2e-5), xd + rng.normal(0, 2e-3)
        out.append(ctl.command_one(xe, xde, 0.0, 0.0, f_next, f_next))
    return np.array(out[250:])  # after the coil's and the hysteresis' start


def test_the_twins_continuity_pulls_its_solve_toward_the_present_current():
    """The root alone turns the estimate's noise into the command (where the force hardly
    depends on the current, at the stroke's ends, through eq. 36's inverted lag 3.2 times):
    on the simulated rig's paper cases the twin's command jumped 0.10-0.13 A a frame against
    the case's own 0.007, Et 1.5-1.7 times the floor (lockstep). mu 0.01 holds it nearer."""
    root, pulled = _commands(0.0), _commands(0.01)
    step_root = np.sqrt(np.mean(np.diff(root) ** 2))
    step_pulled = np.sqrt(np.mean(np.diff(pulled) ** 2))
    assert step_pulled < 0.5 * step_root, (step_root, step_pulled)
    off_root = np.sqrt(np.mean((root - 0.75) ** 2))
    off_pulled = np.sqrt(np.mean((pulled - 0.75) ** 2))
    assert off_pulled < off_root, (off_root, off_pulled)


def test_a_twin_follows_the_motion_while_disarmed_and_arms_on_that_state(tmp_path):
    """Disarmed, the daemon moves the twin on with each frame's estimate and the coil off
    (the rig's SAFE answers); an arm (a new run: `reset`) keeps that state. A twin started at
    rest where it was armed (y = x) asked for k0 (x - y) more, decaying over (c0 + c1) / k0."""
    plant = tmp_path / "sim-twin.json"
    save_plant(Plant(PARAMS, 0.0, "A"), plant)
    config = rig_config(
        tmp_path,
        "unused",
        None,
        bus={"interface": "virtual"},
        loop={"realtime": False, "arm_on_start": False, "max_frame_age_s": 1.0},
        controller={"name": "network_inversion", "model": str(plant), "continuity": 0.0},
    )
    run = run_lockstep(config, ("SINE", 0.01, 1.0), seconds=2.0, preroll_s=0.002)
    assert (run.samples["i_cmd"] == 0).all(), "disarmed throughout"
    ctl = run.daemon.controller
    twin = ctl.lanes[0]
    assert twin.started, "moved with the frames while disarmed"
    assert twin.x == run.samples["x_est"][-1]
    z, y, u = twin.damper.state
    assert u == 0.0 and twin.command == 0.0, "the coil off"
    assert abs(twin.x - y) > 1e-3, "y where the motion put it, not at x"
    ctl.reset(1)  # an arm
    assert ctl.lanes[0] is twin and twin.damper.state == (z, y, u)


def test_the_simulated_rigs_twin_config_runs_the_simulators_own_damper():
    """configs/rig-twin.toml (the paper plan's daemon on the simulated rig) inverts the
    simulator's damper itself: its plant file is firmware_sim's preset, in amperes."""
    from mrrig.config import load_config
    from mrrig.loop.twin_model import load_forward_model
    from tests.conftest import REPO

    cfg = load_config(REPO / "configs/rig-twin.toml")
    model = load_forward_model(REPO / cfg.controller.model)
    assert isinstance(model, TwinModel)
    assert model.plant.params == PARAMS
    assert (model.plant.offset_n, model.plant.command_unit) == (0.0, "A")
