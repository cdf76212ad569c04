"""The hybrid loop's safety checks (mrrig/hil/watch.py; spec/hil.md, Safety), pure numerics:
a loop made unstable on purpose is caught before its stroke leaves the envelope, a healthy one
is not; each check names what it saw. The loop is tests/test_hil_loop.py's: HybridStep, the
benchmark's servo behind two frames, firmware_sim's Bouc-Wen damper moved by the actuator."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from damper.plant import BoucWenDamper, BoucWenParams
from mrrig.hil.reference import SIM_PLANT_PRESET, BoucWenInverse
from mrrig.hil.scenario import load_scenario
from mrrig.hil.stepper import HybridStep
from mrrig.hil.substructure import zoh
from mrrig.hil.watch import HilWatch, WatchLimits

ENVELOPE_M = 0.04


def _watched(
    path: str, method: str, duration_s: float, after_s: float = 0.0, lead_s: float | None = None
):
    """(the frame the watch tripped at or None, its reason, the largest |x_m| and |setpoint|
    sent before it, the largest |x_m| the loop reached unwatched, going on `after_s` past the
    trip, frames run). `lead_s`: the compensation's initial delay (what it leads by until
    its estimate is made), in place of the scenario's."""
    scenario = load_scenario(path)
    comp = dataclasses.replace(scenario.compensation, method=method)
    if lead_s is not None:
        comp = dataclasses.replace(comp, initial_delay_s=lead_s)
    scenario = dataclasses.replace(scenario, duration_s=duration_s, compensation=comp)
    dt = scenario.period_s
    loop = HybridStep(scenario)
    sub = loop.substructure
    params = BoucWenParams.preset(SIM_PLANT_PRESET)
    damper = BoucWenDamper(params, scenario.damper.substep_s)
    inverse = BoucWenInverse(params, scenario.damper.i_max_a, dt)
    ad, bd = zoh(np.array([[0.0, 1.0], [-1.0e5, -425.0]]), np.array([[0.0], [1.0e5]]), dt)
    watch = HilWatch(WatchLimits(ENVELOPE_M), dt)
    rng = np.random.default_rng(1)
    actuator, transport, force = np.zeros(2), [0.0, 0.0], damper.reset(0.0)
    tripped, reason, max_xm, max_sent, max_xm_after = None, None, 0.0, 0.0, 0.0
    for k in range(sub.steps):
        x_m = float(actuator[0]) + 2e-6 * rng.standard_normal()
        f_m = force + 2.0 * rng.standard_normal()
        x_c, v_c = sub.stroke_m, sub.stroke_velocity_m_s
        frame = loop.step(f_m, x_m)
        if tripped is None:
            max_xm = max(max_xm, abs(x_m))
            why = watch.check(
                x_c, x_m, f_m, v_c, frame.target_m, frame.setpoint_m,
                frame.setpoint_velocity_m_s, sub.x,
            )  # fmt: skip
            if why is not None:
                tripped, reason = k, why
            else:
                max_sent = max(max_sent, abs(frame.setpoint_m))
        max_xm_after = max(max_xm_after, abs(x_m))
        if tripped is not None and k - tripped > after_s / dt:
            break
        demand = frame.demand
        current = (
            demand.current_a
            if demand.current_a is not None
            else inverse.current_a(
                damper, frame.target_m, frame.target_velocity_m_s, demand.force_n
            )
        )
        # the unwatched loop goes on (the rig's stroke clamps it), to show where it went
        transport.append(min(max(frame.setpoint_m, -ENVELOPE_M), ENVELOPE_M))
        actuator = ad @ actuator + bd[:, 0] * transport.pop(0)
        actuator[0] = min(max(actuator[0], -ENVELOPE_M), ENVELOPE_M)
        force = damper.step(float(actuator[0]), float(actuator[1]), current, dt)
        if not math.isfinite(force):
            break
    return tripped, reason, max_xm, max_sent, max_xm_after, k + 1


def test_the_building_made_unstable_by_polynomial_compensation_is_caught_inside_the_envelope():
    # a large delay injected: the compensation leads by 40 ms where the rig's delay is about
    # 6 ms (before its delay estimate's warm-up, a wrong early estimate did this by chance)
    tripped, reason, max_xm, max_sent, max_xm_after, _ = _watched(
        "configs/hil/building.toml", "polynomial", 2.0, after_s=1.0, lead_s=0.04
    )
    print(f"tripped at frame {tripped}: {reason}; |x_m| <= {max_xm * 1e3:.3f} mm before, "
          f"unwatched {max_xm_after * 1e3:.1f} mm")  # fmt: skip
    assert tripped is not None and "unstable" in reason
    assert max_xm < 0.1 * ENVELOPE_M  # caught long before the envelope
    assert max_xm_after > 10 * max_xm  # unwatched, it diverges
    assert max_sent <= ENVELOPE_M


def test_the_uncompensated_building_injects_energy_and_is_caught():
    tripped, reason, max_xm, *_ = _watched("configs/hil/building.toml", "none", 10.0)
    assert tripped is not None and "energy injected" in reason, reason
    assert max_xm < ENVELOPE_M


@pytest.mark.parametrize("method", ["model", "none"])
def test_the_quarter_car_runs_without_a_trip(method):
    tripped, reason, *_, frames = _watched("configs/hil/quarter-car.toml", method, 5.0)
    assert tripped is None, f"frame {tripped}: {reason}"
    assert frames == 2500


def _check(watch: HilWatch, **kw) -> str | None:
    values = dict(
        commanded_m=0.0, measured_m=0.0, force_n=0.0, stroke_velocity_m_s=0.0, target_m=0.0,
        setpoint_m=0.0, setpoint_velocity_m_s=0.0, state=np.zeros(4),
    )  # fmt: skip
    return watch.check(**(values | kw))


def test_each_check_names_what_it_saw():
    limits = WatchLimits(ENVELOPE_M, tracking_limit_m=0.005, energy_limit_j=0.05)
    assert _check(HilWatch(limits, 0.002)) is None
    assert "not finite" in _check(HilWatch(limits, 0.002), state=np.array([0, math.nan, 0, 0]))
    assert "not finite" in _check(HilWatch(limits, 0.002), setpoint_m=math.inf)
    assert "setpoint 41.00 mm beyond the STREAM envelope +-40 mm" in _check(
        HilWatch(limits, 0.002), setpoint_m=0.041
    )
    assert "model's stroke -40.50 mm beyond" in _check(HilWatch(limits, 0.002), target_m=-0.0405)
    assert "tracking error x_m - x_c 6.00 mm beyond +-5 mm" in _check(
        HilWatch(limits, 0.002), measured_m=0.006
    )
    w = HilWatch(limits, 0.002)
    assert _check(w, setpoint_m=0.001) is None
    assert "moved 7.00 mm in one frame (3.50 m/s, limit 3 m/s)" in _check(w, setpoint_m=0.008)
    # a damper that pushes the model along its motion: 100 N at 0.1 m/s, 0.02 J a frame
    w = HilWatch(limits, 0.002)
    reasons = [_check(w, force_n=-100.0, stroke_velocity_m_s=0.1) for _ in range(5)]
    assert reasons[:2] == [None, None] and "delivered 0.060 J" in reasons[2]
    # and one that dissipates never trips
    w = HilWatch(limits, 0.002)
    assert all(_check(w, force_n=100.0, stroke_velocity_m_s=0.1) is None for _ in range(500))
