"""The compiled frame numerics (mrrig/loop/compiled.py) equal the Python path they replace, to
1e-12: over the frames of a recorded run through the daemon, and part by part where the
daemon's run does not reach (the root branch of the solve, lost frames, fast strokes)."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from damper.plant import BoucWenDamper, BoucWenParams
from firmware_sim.config import load_config as load_sim_config
from firmware_sim.firmware import Firmware
from mrrig.config import load_config
from mrrig.loop import compiled
from mrrig.loop.daemon import Daemon
from mrrig.loop.estimation import RealtimeKalman
from mrrig.loop.inversion import ScalarInverter
from mrrig.loop.mlp import MLP
from mrrig.pycan import can
from mrrig.rigio.canbus.profile import contract_profile
from tests.conftest import REPO
from tests.lockstep_rig import lockstep_config

TOL = 1e-12
COLUMNS = ("x_est", "xd", "xdd", "f_des", "f_model", "i_cmd", "state", "outside")


def _close(a, b) -> bool:
    """Equal to 1e-12: absolute for values up to 1 (m, A), relative above (N)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    both_nan = np.isnan(a) & np.isnan(b)
    return bool(np.all(both_nan | (np.abs(a - b) <= TOL * np.maximum(1.0, np.abs(a)))))


def _daemon(config, numerics: str) -> Daemon:
    return Daemon(load_config(config, {"loop": {"numerics": numerics}}), keep_batches=True)


def _record(config, seconds: float) -> list[tuple[float, can.Message]]:
    """The frames firmware_sim sends while it and the Python path's daemon run in lockstep."""
    daemon = _daemon(config, "python")
    channel = f"compiled-record-{time.time_ns()}"
    daemon.bus = can.Bus(interface="virtual", channel=channel)
    rig_end = can.Bus(interface="virtual", channel=channel)
    fw = Firmware(
        dataclasses.replace(load_sim_config(REPO / "configs/sim.toml"), seed=3),
        contract_profile(),
        (),
    )
    fw.actuator.command("sine", 0.015, 3.0)
    daemon.controller.reset(1)
    daemon._arm_pending = True
    frames = []
    base = time.perf_counter()
    try:
        for k in range(round(seconds / fw.period_s)):
            t_sim = k * fw.period_s
            for frame in fw.tick(t_sim):
                fw.sent(frame, t_sim)
                msg = can.Message(
                    arbitration_id=frame.frame_id,
                    is_extended_id=frame.is_extended,
                    dlc=len(frame.data),
                    data=frame.data,
                    timestamp=time.time(),
                )
                frames.append((t_sim, msg))
                daemon.t0 = base
                daemon.on_frame(msg, base + t_sim)
                while (answer := rig_end.recv(0)) is not None:
                    fw.on_frame(
                        answer.arbitration_id, bytes(answer.data), t_sim, answer.is_extended_id
                    )
    finally:
        daemon.bus.shutdown()
        rig_end.shutdown()
    return frames


def _replay(config, numerics: str, frames) -> tuple[Daemon, np.ndarray]:
    """The recorded frames, with the same receive times, through a daemon of `numerics`."""
    daemon = _daemon(config, numerics)
    channel = f"compiled-replay-{time.time_ns()}"
    daemon.bus = can.Bus(interface="virtual", channel=channel)
    daemon.controller.reset(1)
    daemon._arm_pending = True
    base = time.perf_counter()
    daemon.t0 = base
    try:
        for t_sim, msg in frames:
            daemon.on_frame(msg, base + t_sim)
        daemon._flush_samples()
    finally:
        daemon.bus.shutdown()
    return daemon, np.concatenate(daemon.batches.handed_over())


def test_the_compiled_path_equals_the_python_path_over_a_recorded_run(tmp_path, sim_model):
    config = lockstep_config(
        tmp_path,
        model=sim_model,
    )
    frames = _record(config, 3.0)
    python, p = _replay(config, "python", frames)
    fast, c = _replay(config, "compiled", frames)
    assert type(fast.kf) is compiled.CompiledKalman
    assert type(fast.controller._scalar) is compiled.CompiledScalarInverter
    assert type(fast.reference._damper) is compiled.CompiledBoucWenDamper
    assert type(python.controller._scalar) is ScalarInverter
    armed = p["state"] == 1
    assert armed.sum() > 1000 and python.controller.solved_ahead()[0] > 1000
    for col in COLUMNS:
        assert _close(p[col], c[col]), (col, np.nanmax(np.abs(p[col] - c[col])))
    assert fast.controller.solved_ahead() == python.controller.solved_ahead()
    assert fast.counters == python.counters


@pytest.mark.parametrize("continuity", [0.0, 0.3])
def test_the_compiled_solve_equals_the_python_one_on_both_branches(continuity):
    rng = np.random.default_rng(7)
    H = 30
    model = MLP(
        input_names=["x", "xd", "xdd", "current"],
        input_units=["m", "m/s", "m/s^2", "A"],
        output_name="force",
        output_unit="N",
        in_mean=np.array([0.0, 0.0, 0.0, 1.0]),
        in_std=np.array([0.01, 0.3, 10.0, 0.6]),
        out_mean=100.0,
        out_std=800.0,
        W1=rng.normal(0.0, 1.0, (H, 4)),
        b1=rng.normal(0.0, 0.5, H),
        W2=rng.normal(0.0, 0.4, H),
        b2=0.1,
    )
    py = ScalarInverter(model, 2.0, continuity=continuity)
    cc = compiled.CompiledScalarInverter(model, 2.0, continuity=continuity)
    i_prev = 0.5
    for _ in range(400):
        feat = rng.normal(0.0, 1.0, 3) * np.array([0.01, 0.3, 10.0])
        f_des = float(rng.normal(100.0, 1500.0))
        # solve ahead on a nearby sample, as the daemon does, then on the sample itself
        near = feat * (1.0 + rng.normal(0.0, 1e-3, 3))
        py.prepare(near, f_des, i_prev)
        cc.prepare(near, f_des, i_prev)
        a, b = py.solve(feat, f_des, i_prev), cc.solve(feat, f_des, i_prev)
        assert abs(a - b) <= TOL, (a, b)
        assert _close(py.force(feat, a), cc.force(feat, a))
        i_prev = a
    assert (py.ahead_used, py.ahead_missed) == (cc.ahead_used, cc.ahead_missed)
    assert py.ahead_used > 100
    assert np.isnan(cc.solve(feat, float("nan"), i_prev))


def test_the_compiled_kalman_and_damper_equal_the_python_ones_through_gaps_and_fast_strokes():
    py, cc = RealtimeKalman(0.002), compiled.CompiledKalman(0.002)
    rng = np.random.default_rng(1)
    for k in range(2000):
        x = 0.01 * np.sin(0.03 * k) + rng.normal(0.0, 2e-5)
        z = None if k % 97 in (5, 6) else x  # lost frames: the prediction kept
        assert np.allclose(py.update(z), cc.update(z), rtol=TOL, atol=0.0)
        assert py.prior == cc.prior and py.gain == cc.gain
    params = BoucWenParams.preset("rig-current")
    pd, cd = BoucWenDamper(params, 2.5e-4), compiled.CompiledBoucWenDamper(params, 2.5e-4)
    for d in (pd, cd):
        d.reset(0.0, 0.0, 0.8)
    for k in range(1, 600):
        # every 50th step a stroke faster than the sub-steps are stable for (more of them)
        speed = 3.0 if k % 50 == 0 else 0.3
        x, xd = 0.01 * np.sin(0.05 * k), speed * np.cos(0.05 * k)
        dt = 0.002 * (1 + (k % 41 == 0))  # and a lost frame's two periods
        assert _close(pd.step(x, xd, 0.8, dt), cd.step(x, xd, 0.8, dt))
    assert np.allclose(pd.state, cd.state, rtol=TOL, atol=0.0)


def test_the_frame_path_writes_its_row_in_the_sample_dtypes_order():
    from mrrig.loop.frame_path import NO_HIL, ROW_FIELDS
    from mrrig.loop.samples import SAMPLE_DTYPE

    assert ROW_FIELDS == SAMPLE_DTYPE.names
    assert len(NO_HIL) == sum(name.startswith("hil_") for name in SAMPLE_DTYPE.names)


def test_the_frames_model_force_on_the_float_path_equals_the_arrays(sim_model):
    from mrrig.loop.controllers import ConstantCurrent, ControlInput, NetworkInversion

    model = MLP.load(sim_model)
    for ctrl in (
        NetworkInversion(2.0, model),
        NetworkInversion(2.0, model, feedback_tau_s=0.0),
    ):
        ctrl.reset(1)
        for x, xd, xdd, i in ((0.01, 0.2, 3.0, 0.7), (-0.004, -0.5, -20.0, 1.9)):
            s = ControlInput(*(np.array([v]) for v in (x, xd, xdd, 100.0, 200.0)))
            arrays = float(ctrl.model_force(s, np.array([i]))[0])
            assert _close(arrays, ctrl.model_force_one(x, xd, xdd, 100.0, 200.0, i))
    assert np.isnan(ConstantCurrent(2.0, 1.0).model_force_one(0.0, 0.0, 0.0, 0.0, 0.0, 1.0))


def test_an_unknown_numerics_is_one_line_naming_the_setting():
    from mrrig.typed_config import ConfigError

    with pytest.raises(ConfigError, match=r"loop\.numerics: one of compiled, python, got 'fast'"):
        load_config(REPO / "configs/rig.toml", {"loop": {"numerics": "fast"}})
