"""On-line adaptation of network inversion's model force (mrrig/loop/adaptation.py): off, it is
the controller without it, bit for bit; it learns only while armed and without a fault; a
load-cell spike moves it by no more than its bound; its state reaches the recording; the
model file is never written."""

from __future__ import annotations

import hashlib
import math
import time

import numpy as np
import pytest

from damper.plant import BoucWenParams
from mrrig.loop.adaptation import AdaptationSettings, GainOffsetRLS
from mrrig.loop.controllers import ControlInput, NetworkInversion
from mrrig.loop.mlp import MLP
from mrrig.loop.samples import RigState
from mrrig.offline.simulation import closed_loop
from tests.conftest import rig_config
from tests.rig_harness import ScriptedRig
from tests.test_inversion import I_MAX, random_model

DT_S = 1e-3
LAG_TAU_S = 1.0 / 190.0


def _lagged_model():
    model = random_model(np.random.default_rng(41), monotone=True)
    model.meta.update(current_input="lagged", lag_tau_s=LAG_TAU_S)
    return model


def _motion(n: int, seed: int = 0):
    t = np.arange(n) * DT_S
    rng = np.random.default_rng(seed)
    x = 0.01 * np.sin(2 * np.pi * 2 * t)
    xd = 0.01 * 2 * np.pi * 2 * np.cos(2 * np.pi * 2 * t)
    xdd = -((2 * np.pi * 2) ** 2) * x
    f_meas = 400 * np.sin(2 * np.pi * 2 * t + 0.3) + rng.normal(0, 2.0, n)
    f_des = 380 * np.sin(2 * np.pi * 2 * t + 0.2)
    return x, xd, xdd, f_meas, f_des


def _commands(ctrl: NetworkInversion, n: int, learn: bool) -> list[float]:
    x, xd, xdd, f_meas, f_des = (a.tolist() for a in _motion(n))
    ctrl.reset(1)
    out = []
    for k in range(n - 1):
        out.append(ctrl.command_one(x[k], xd[k], xdd[k], f_meas[k], f_des[k], f_des[k + 1]))
        if learn:
            ctrl.after_send()
    return out


def test_the_float_path_one_step_ahead_is_the_batch_controller():
    """The daemon's float path (`command_one`, one step ahead with the feedback) against the
    batch `command` that `mrrig bench paper` runs: the same commands, to rounding (the float
    path sums the network's force in another order)."""
    model = _lagged_model()
    n = 400
    x, xd, xdd, f_meas, f_des = _motion(n)
    one = NetworkInversion(I_MAX, model, feedback_tau_s=0.004, dt_s=DT_S, ahead=True)
    batch = NetworkInversion(I_MAX, model, feedback_tau_s=0.004, dt_s=DT_S, ahead=True)
    batch.reset(1)
    want = [
        float(
            batch.command(
                ControlInput(
                    *(np.array([a[k]]) for a in (x, xd, xdd, f_meas, f_des)),
                    f_des_next=np.array([f_des[k + 1]]),
                )
            )[0]
        )
        for k in range(n - 1)
    ]
    np.testing.assert_allclose(_commands(one, n, learn=False), want, rtol=0, atol=1e-12)


def test_adaptation_frozen_at_the_model_is_the_controller_without_it_bit_for_bit():
    model = _lagged_model()
    plain = NetworkInversion(I_MAX, model, feedback_tau_s=0.0, dt_s=DT_S, ahead=True)
    adaptive = NetworkInversion(
        I_MAX, model, feedback_tau_s=0.0, dt_s=DT_S, ahead=True, adaptation=AdaptationSettings()
    )
    adaptive.adapt.frozen = True
    assert _commands(adaptive, 300, learn=True) == _commands(plain, 300, learn=False)
    assert adaptive.adapt.updates == 0
    # learning, it departs from the model
    adaptive.adapt.frozen = False
    assert _commands(adaptive, 300, learn=True) != _commands(plain, 300, learn=False)
    assert adaptive.adapt.updates > 0


def test_in_the_papers_loop_adaptation_off_gives_the_same_tracking_as_before():
    """closed_loop calls after_send; without adaptation the commands are those of the
    controller built the way `mrrig bench paper` always built it."""
    model = _lagged_model()
    params = BoucWenParams.preset("paper-volt")
    x, xd, xdd, _, f_des = _motion(300)
    runs = [
        closed_loop(
            NetworkInversion(12.0, model, feedback_tau_s=0.0, dt_s=DT_S, ahead=True, **kw),
            params,
            DT_S,
            x,
            xd,
            xdd,
            f_des,
        ).command
        for kw in ({}, {"adaptation": None})
    ]
    np.testing.assert_array_equal(runs[0], runs[1])


def test_a_10_kn_load_cell_spike_moves_the_parameters_by_no_more_than_the_bound():
    s = AdaptationSettings()
    rng = np.random.default_rng(3)
    for limit in (s.residual_limit_n, 1e9):  # with the plausibility check, and without it
        rls = GainOffsetRLS(AdaptationSettings(residual_limit_n=limit), DT_S)
        for _ in range(500):  # a damper 10 % weaker than its model
            f_net = rng.uniform(-800, 800)
            rls.update(np.array([f_net]), np.array([0.9 * f_net + rng.normal(0, 2)]))
        before = rls.theta.copy()
        skipped = rls.skipped
        f_net = 300.0
        rls.update(np.array([f_net]), np.array([0.9 * f_net + 10000.0]))
        d_gain, d_offset = np.abs(rls.theta[0] - before[0])
        assert d_gain <= s.max_gain_step + 1e-12  # (theta + step) - theta, rounded
        assert d_offset * 1000.0 <= s.max_offset_step_n + 1e-9
        if limit == s.residual_limit_n:
            assert rls.skipped == skipped + 1 and d_gain == 0 and d_offset == 0
        else:
            assert d_gain > 0  # it was used, and clipped to the bound
    # the gain learnt from the plausible frames
    assert 0.85 < rls.gain[0] < 0.95


def test_a_spike_through_the_controller_is_bounded_too():
    model = _lagged_model()
    s = AdaptationSettings(residual_limit_n=5000.0)  # the random model's force spans 4 kN
    ctrl = NetworkInversion(I_MAX, model, feedback_tau_s=0.0, dt_s=DT_S, ahead=True, adaptation=s)
    x, xd, xdd, _, f_des = _motion(200)
    # a damper 10 % weaker than the model at 0.5 A: plausible residuals but for the spike
    f_meas = 0.9 * model.predict(np.column_stack([x, xd, xdd, np.full(200, 0.5)]))
    x, xd, xdd, f_meas, f_des = (a.tolist() for a in (x, xd, xdd, f_meas, f_des))
    ctrl.reset(1)
    for k in range(199):
        spike = 10000.0 if k == 150 else 0.0
        before = ctrl.adapt.theta.copy()
        ctrl.command_one(x[k], xd[k], xdd[k], f_meas[k] + spike, f_des[k], f_des[k + 1])
        ctrl.after_send()
        step = np.abs(ctrl.adapt.theta - before)[0]
        assert step[0] <= s.max_gain_step + 1e-12
        assert step[1] * 1000.0 <= s.max_offset_step_n + 1e-9
        if k == 150:
            assert ctrl.adapt.skipped == 1 and not step.any()
    assert ctrl.adapt.updates == 197  # not the first instant, not the spike


def test_settings_out_of_range_are_refused():
    for bad in (
        {"gain_range": (1.1, 2.0)},
        {"offset_range_n": (10.0, 20.0)},
        {"memory_s": 0.0},
        {"max_gain_step": -1.0},
    ):
        with pytest.raises(ValueError):
            GainOffsetRLS(AdaptationSettings(**bad), DT_S)


# ------------------------------------------------------------------------- in the daemon
def _adaptive_config(tmp_path, model, **loop):
    def config(channel: str):
        return rig_config(
            tmp_path,
            channel,
            model,
            bus={"interface": "virtual"},
            # a sensor timeout of 1 s: the test thread plays the firmware, slowly when loaded
            loop={"realtime": False, "timeout_periods": 500, **loop},
            adaptation={"enabled": True},
            reference={"kind": "sine", "offset_n": 0.0, "amplitude_n": 300.0, "freq_hz": 2.0},
            actuator={"waveform": "stop", "amplitude_m": 0.0, "frequency_hz": 0.0},
        )

    return config


def _frames(rig: ScriptedRig, n: int, k0: int = 0, **flags) -> None:
    for k in range(k0, k0 + n):
        t = k * 0.002
        rig.exchange(
            x=0.01 * math.sin(2 * math.pi * 2 * t),
            force=300.0 * math.sin(2 * math.pi * 2 * t + 0.3),
            **flags,
        )


def _armed(rig: ScriptedRig) -> int:
    time.sleep(0.1)  # the last frame's work after its command (the test saw the command)
    batches = rig.daemon.batches.handed_over()
    return int(sum((b["state"] == RigState.ARMED).sum() for b in batches))


@pytest.mark.process  # the daemon's loop at frame rate (and the sidecar)
def test_adaptation_runs_only_while_armed_and_never_in_a_fault(tmp_path, sim_model):
    cfg = _adaptive_config(tmp_path, sim_model, arm_on_start=False, telemetry_batch=1)
    with ScriptedRig(tmp_path, config=cfg) as rig:
        adapt = rig.daemon.controller.adapt
        _frames(rig, 60)
        assert adapt.updates == adapt.skipped == 0  # IDLE
        assert rig.request({"cmd": "arm"})["ok"]
        _frames(rig, 100, 60)
        armed = _armed(rig)
        learnt = adapt.updates + adapt.skipped
        assert learnt == armed - 1 > 0  # each armed frame but the first (it answers none)
        theta = adapt.theta.copy()
        rig.exchange(SensorFault=1)  # FAULT within this frame: no update from it
        assert rig.daemon.supervisor.state is RigState.FAULT
        _frames(rig, 50, 161)
        assert _armed(rig) == armed
        assert adapt.updates + adapt.skipped == learnt
        np.testing.assert_array_equal(adapt.theta, theta)
        # freeze and reset on request
        assert rig.request({"cmd": "reset"})["ok"]  # the sensor fault acknowledged
        assert rig.request({"cmd": "arm"})["ok"]
        assert rig.request({"cmd": "freeze_adaptation"})["ok"]
        _frames(rig, 30, 211)
        assert adapt.updates + adapt.skipped == learnt
        reply = rig.request({"cmd": "reset_adaptation"})
        assert reply["ok"] and reply["adaptation"]["gain"] == 1.0
        bad = rig.request({"cmd": "freeze_adaptation", "frozen": "yes"})
        assert not bad["ok"] and "frozen" in bad["error"]


@pytest.mark.process  # the daemon's loop at frame rate (and the sidecar)
def test_the_recording_holds_the_adapted_state_and_the_model_file_is_unchanged(tmp_path, sim_model):
    from mrrig.offline.review import read_recording

    digest = hashlib.sha256(sim_model.read_bytes()).hexdigest()
    record = tmp_path / "run.rrd"
    cfg = _adaptive_config(tmp_path, sim_model, arm_on_start=True, arm_settle_s=0.0)
    with ScriptedRig(tmp_path, config=cfg, record_path=record) as rig:
        _frames(rig, 300)
        final = rig.daemon.controller.adaptation_state()
        # the recording is closed before the daemon's thread ends: time for that
        rig.daemon.request_stop("test done")
        rig.thread.join(timeout=60)
    assert final["updates"] > 0 and final["gain"] != 1.0
    summary = rig.daemon.summary
    assert summary["adaptation"]["gain"] == final["gain"]
    s = read_recording(record).samples
    armed = s[s["state"] == RigState.ARMED]
    assert np.isfinite(armed["adapt_gain"]).all()
    assert armed["adapt_gain"][-1] == final["gain"]
    assert armed["adapt_offset_n"][-1] == final["offset_n"]
    assert len(np.unique(armed["adapt_gain"])) > 10  # it moved frame by frame
    assert hashlib.sha256(sim_model.read_bytes()).hexdigest() == digest


@pytest.mark.process  # the daemon's loop at frame rate (and the sidecar)
def test_the_daemon_evaluates_the_reference_once_per_frame_and_passes_the_next_target(
    tmp_path, sim_model
):
    """The one-step-ahead default gets each frame's desired force and the next frame's; the
    reference (a Bouc-Wen damper, stateful) is stepped once per instant, in order, on the
    estimate of that instant once its frame has come."""

    def config(channel: str):
        return rig_config(
            tmp_path,
            channel,
            sim_model,
            bus={"interface": "virtual"},
            loop={
                "realtime": False,
                "timeout_periods": 500,
                "arm_on_start": True,
                "arm_settle_s": 0.0,
            },
            actuator={"waveform": "stop", "amplitude_m": 0.0, "frequency_hz": 0.0},
        )

    with ScriptedRig(tmp_path, config=config) as rig:
        d = rig.daemon
        assert d.controller.wants_next_target and d.reference.kind == "bouc_wen"
        times, targets = [], []
        force, command_one = d.reference.force, d.controller.command_one

        def counted(t, x, xd):
            times.append(t)
            return force(t, x, xd)

        def seen(*a):
            targets.append((a[4], a[5]))
            return command_one(*a)

        d.reference.force, d.controller.command_one = counted, seen
        _frames(rig, 200)
        time.sleep(0.1)
    n = len(targets)
    assert n == 200  # armed from the first frame
    assert all(b > a for a, b in zip(times, times[1:], strict=False))  # each instant once
    assert len(times) == 200  # moved on once a frame, on its estimate (targets: forecasts)
    for (_, nxt), (now, _) in zip(targets, targets[1:], strict=False):
        assert now == nxt


def test_an_old_model_of_the_commanded_current_loads_and_says_what_it_lacks(
    tmp_path, caplog, sim_model
):
    from mrrig.config import load_config
    from mrrig.loop.build import build_controller

    # the trained network without current_input and lag_tau_s, as files were before them (a
    # random network is no model of a damper: the self-check refuses it, issue 40)
    old = MLP.load(sim_model)
    for key in ("current_input", "lag_tau_s"):
        old.meta.pop(key)
    path = tmp_path / "old.json"
    old.save(path)
    cfg = load_config(rig_config(tmp_path, "ws://127.0.0.1:1/", path))
    with caplog.at_level("WARNING", logger="mrrig.loop.build"):
        ctrl = build_controller(cfg)
    assert ctrl.name == "network_inversion" and ctrl.ahead and ctrl.lag_tau_s is None
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "no current_input = 'lagged', no lag_tau_s" in warning
    assert "mrrig train --current-input lagged" in warning
