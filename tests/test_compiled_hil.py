"""The hybrid loop's frame compiled (mrrig/loop/compiled_hil.py) equals the Python `HybridStep`
it replaces, to 1e-12, frame by frame over whole runs of every law and both substructures, on a
synthetic rig (the stroke 2.5 frames behind the setpoints, the damper's force on the model's
stroke velocity, both with noise); and the daemon runs it on the compiled path only.
Pure numerics and an in-process daemon; a few seconds."""

from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np
import pytest

from mrrig.hil.scenario import load_scenario
from mrrig.hil.stepper import HybridStep
from mrrig.loop import compiled_hil
from mrrig.loop.compiled_hil import CompiledHybridStep
from tests.conftest import REPO

TOL = 1e-12
pytestmark = pytest.mark.skipif(not compiled_hil.AVAILABLE, reason="numba is not installed")


def _close(a, b, unit: float = 1.0) -> bool:
    """Equal to 1e-12 in `unit`s: absolute for values up to one unit, relative above. Forces
    are compared in kN: a tyre load is k_t (1.9e5 N/m) times a difference of displacements, so
    a state that differs by 1e-17 m (the rounding of the exact step's sums, numpy's or the
    kernel's) moves it by 2e-12 N."""
    a, b = np.asarray(a, dtype=float) / unit, np.asarray(b, dtype=float) / unit
    both_nan = np.isnan(a) & np.isnan(b)
    return bool(np.all(both_nan | (np.abs(a - b) <= TOL * np.maximum(1.0, np.abs(a)))))


def _scenario(path: str, law: str, method: str, on_off: bool | None = None):
    s = load_scenario(REPO / path, law=law)
    c = dataclasses.replace(s.compensation, method=method)
    laws = s.laws if on_off is None else dataclasses.replace(s.laws, clipped_on_off=on_off)
    return dataclasses.replace(s, duration_s=3.0, compensation=c, laws=laws)


def _outputs(run: HybridStep) -> list[float]:
    """The model's outputs of the frame, forces in kN."""
    sub = run.substructure
    if hasattr(sub, "tyre_load_n"):
        return [sub.body_acceleration_m_s2, sub.tyre_load_n / 1e3]
    return [*sub.drifts_m, *sub.accelerations_m_s2]


CASES = [
    ("configs/hil/quarter-car.toml", law, None, method)
    for law in ("skyhook", "groundhook", "hybrid", "clipped-optimal", "passive-hard")
    for method in ("model", "none")
] + [
    ("configs/hil/quarter-car.toml", "clipped-optimal", True, "model"),
    ("configs/hil/building.toml", "clipped-optimal", True, "model"),
    ("configs/hil/building.toml", "clipped-optimal", False, "model"),
    ("configs/hil/building.toml", "clipped-optimal", False, "none"),
    ("configs/hil/building.toml", "passive-soft", None, "model"),
]


@pytest.mark.parametrize(("path", "law", "on_off", "method"), CASES)
def test_the_compiled_hybrid_step_equals_the_python_one_frame_by_frame(
    path: str, law: str, on_off: bool | None, method: str
) -> None:
    """Both runs get the same measured force and stroke each frame (the Python run's rig);
    the demand (force or current), the model's target and its velocity, the setpoint and its
    feedforward, the delay estimate, the model's state and outputs agree to 1e-12 on every
    frame. Not vacuous: the delay estimate leaves its initial value (3 frames beyond the
    loop's own) for the rig's (1.5 beyond it), the lead takes fractions of a frame, and the
    law's demand changes."""
    scenario = _scenario(path, law, method, on_off)
    python, compiled = HybridStep(scenario), compiled_hil.hybrid_step(scenario)
    assert type(compiled) is CompiledHybridStep
    rng = np.random.default_rng(7)
    sent = deque([0.0, 0.0], maxlen=2)
    force = stroke = 0.0
    delays, demands = set(), set()
    for k in range(scenario.steps):
        a, b = python.step(force, stroke), compiled.step(force, stroke)
        assert (a.demand.force_n is None) == (b.demand.force_n is None), k
        if a.demand.current_a is None:
            da = a.demand.force_n
            assert _close(da, b.demand.force_n, unit=1e3), (k, da, b.demand.force_n)
        else:
            da = a.demand.current_a
            assert da == b.demand.current_a, k
        got = [b.target_m, b.target_velocity_m_s, b.setpoint_m, b.setpoint_velocity_m_s]
        want = [a.target_m, a.target_velocity_m_s, a.setpoint_m, a.setpoint_velocity_m_s]
        assert _close(want + [a.delay_s], got + [b.delay_s]), (k, want, got)
        assert _close(python.substructure.x, compiled.substructure.x), k
        assert _close(_outputs(python), _outputs(compiled)), k
        assert python.substructure.k == compiled.substructure.k == k + 1
        assert _close(python.compensator.delay_s, compiled.compensator.delay_s)
        delays.add(round(a.delay_s, 9))
        demands.add(da)
        # the rig: between the setpoints sent two and three frames before (2.5 frames behind),
        # the damper's force on the model's stroke velocity
        stroke = 0.5 * (sent[0] + sent[1]) + 1e-6 * rng.standard_normal()
        sent.append(a.setpoint_m)
        force = 1500.0 * a.target_velocity_m_s + 20.0 * rng.standard_normal()
    assert python.done and compiled.done
    if law.startswith("passive"):
        assert len(demands) == 1
    elif on_off:
        assert demands == {0.0, scenario.damper.i_max_a}
    else:
        assert len(demands) > 100
    if method == "model":
        assert len(delays) > 10, delays  # moved, in fractions of a frame
        # 2.5 frames: 1 the loop's, 1.5 led (a whole frame and the table's 50 %)
        assert abs(python.compensator.delay_s - 0.003) < 0.0005


def test_the_daemon_runs_the_compiled_step_only_on_the_compiled_path(tmp_path) -> None:
    """`loop.numerics = "compiled"`: the daemon's hybrid loop builds `CompiledHybridStep`s;
    "python": the `HybridStep` of mrrig.hil; a compensation the kernel has not (polynomial)
    stays on the Python path."""
    from mrrig.config import load_config
    from mrrig.loop.daemon import daemon_limits, load_profile
    from mrrig.loop.hil_loop import HilLoop
    from tests.conftest import rig_config

    hil = {"scenario": str(REPO / "configs/hil/quarter-car.toml"), "duration_s": 1.0}
    config = rig_config(tmp_path, "unused", None, hil=hil)
    poly = _scenario("configs/hil/quarter-car.toml", "skyhook", "polynomial")
    for numerics, kind in (("compiled", CompiledHybridStep), ("python", HybridStep)):
        cfg = load_config(config, {"loop": {"numerics": numerics}})
        profile = load_profile(
            cfg.can.dbc, cfg.can.signals, cfg.loop.period_s, cfg.source, daemon_limits(cfg)
        )
        loop = HilLoop(cfg, profile, profile.packer(), lambda _waveform, _amplitude: None)
        assert type(loop.build_run()) is kind
        assert type(loop.build_run(poly)) is HybridStep
