"""The HIL numerics of spec/hil.md: the substructures' conventions and integrator, the laws'
semi-active rule, the delay compensators against a servo-hydraulic actuator model, the metrics
J1-J3 and the scenario files' one-line errors. Pure numerics: seconds."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from mrrig.hil.compensation import extrapolation_weights, make_compensator
from mrrig.hil.laws import Demand, Law, LawParams, dissipative
from mrrig.hil.metrics import response_error, tracking, tracking_apart_from_stalls
from mrrig.hil.scenario import load_scenario
from mrrig.hil.substructure import BuildingParams, QuarterCar, QuarterCarParams, ShearBuilding, zoh
from mrrig.typed_config import ConfigError

DT = 0.002
REPO = Path(__file__).resolve().parents[1]


def test_the_quarter_car_steps_exactly_what_its_equations_integrate() -> None:
    """The ZOH step against a tight ODE solution of m_s z_s'' = -k_s s - F, m_u z_u'' = k_s s
    + F - k_t (z_u - z_r), the force and road held over each frame."""
    p = QuarterCarParams()
    road = 0.01 * np.sin(2 * np.pi * 1.5 * np.arange(201) * DT)
    car = QuarterCar(p, road, DT)
    forces = 300.0 * np.cos(2 * np.pi * 3.0 * np.arange(200) * DT)
    x = np.zeros(4)
    for k in range(200):
        car.step(forces[k])

        def rhs(_t, s, f=forces[k], zr=road[k]):
            zs, vs, zu, vu = s
            return [
                vs,
                (-p.k_s_n_per_m * (zs - zu) - f) / p.m_s_kg,
                vu,
                (p.k_s_n_per_m * (zs - zu) + f - p.k_t_n_per_m * (zu - zr)) / p.m_u_kg,
            ]

        x = solve_ivp(rhs, (0, DT), x, rtol=1e-11, atol=1e-14).y[:, -1]
    assert car.x == pytest.approx(x, rel=1e-6, abs=1e-12)


def test_a_damper_force_in_tension_pulls_the_body_down_and_the_wheel_up() -> None:
    car = QuarterCar(QuarterCarParams(), np.zeros(11), DT)
    for _ in range(10):
        car.step(500.0)
    assert car.x[0] < 0.0 < car.x[2]
    assert car.stroke_m < 0.0


def test_the_damper_delivers_minus_f_times_the_stroke_velocity_to_the_masses() -> None:
    """spec/hil.md: the power the damper delivers to the masses is -F s', so a passive damper
    (F = c s', tension in extension) takes sum F s' dt from a free vibration: the model's
    energy falls by that much."""
    p = QuarterCarParams()
    car = QuarterCar(p, np.zeros(1501), DT)

    def energy() -> float:
        zs, vs, zu, vu = car.x
        return 0.5 * (
            p.m_s_kg * vs**2
            + p.m_u_kg * vu**2
            + p.k_s_n_per_m * (zs - zu) ** 2
            + p.k_t_n_per_m * zu**2
        )

    car.x = np.array([0.03, 0.0, 0.0, 0.0])
    e0, taken = energy(), 0.0
    for _ in range(car.steps):
        s0 = car.stroke_m
        force = 1500.0 * car.stroke_velocity_m_s
        car.step(force)
        # the force is held over the frame (the exact step): its work is F times the stroke
        taken += force * (car.stroke_m - s0)
    assert energy() < 0.05 * e0
    assert e0 - energy() == pytest.approx(taken, rel=1e-6)


def test_the_building_is_dyke_s_three_storey_model() -> None:
    """The storey values give Dyke et al. (1996)'s K and C matrices."""
    b = ShearBuilding(BuildingParams(), np.zeros(11), DT)
    k = -b.a[3:, :3] * 98.3
    c = -b.a[3:, 3:] * 98.3
    assert k == pytest.approx(
        1e5 * np.array([[12.0, -6.84, 0], [-6.84, 13.68, -6.84], [0, -6.84, 6.84]])
    )
    assert c == pytest.approx(np.array([[175.0, -50, 0], [-50, 100, -50], [0, -50, 50]]))


def test_a_passive_damper_cannot_push() -> None:
    assert dissipative(100.0, 0.1) == 100.0
    assert dissipative(100.0, -0.1) == 0.0
    assert dissipative(-100.0, -0.1) == -100.0


@pytest.mark.parametrize("name", ["skyhook", "groundhook", "hybrid", "clipped-optimal"])
def test_every_law_asks_only_forces_a_damper_can_give(name: str) -> None:
    from mrrig.hil.road import road_input_m

    car = QuarterCar(QuarterCarParams(), road_input_m("C", 20.0, 4.0, DT, seed=5), DT)
    law = Law(name, LawParams(), car, 2.0)
    asked = 0
    for _ in range(car.steps):
        demand = law.demand(0.0)
        assert demand.current_a is None
        assert demand.force_n * car.stroke_velocity_m_s >= 0.0
        asked += demand.force_n != 0.0
        car.step(1000.0 * car.stroke_velocity_m_s)
    assert asked > car.steps // 10


def test_skyhook_asks_c_sky_times_the_body_velocity_when_the_damper_can_give_it() -> None:
    car = QuarterCar(QuarterCarParams(), np.zeros(3), DT)
    law = Law("skyhook", LawParams(skyhook_c_n_s_per_m=2000.0), car, 2.0)
    car.x = np.array([0.0, 0.3, 0.0, 0.1])  # body up faster than the wheel: extension
    assert law.demand(0.0) == Demand(force_n=600.0)
    car.x = np.array([0.0, 0.3, 0.0, 0.5])  # compression while the body rises: none
    assert law.demand(0.0) == Demand(force_n=0.0)


def test_the_passive_laws_are_currents_and_clipped_optimal_on_off_is_dyke_s() -> None:
    car = QuarterCar(QuarterCarParams(), np.zeros(3), DT)
    assert Law("passive-soft", LawParams(), car, 2.0).demand(5.0) == Demand(current_a=0.0)
    assert Law("passive-hard", LawParams(), car, 2.0).demand(5.0) == Demand(current_a=2.0)
    law = Law("clipped-optimal", LawParams(clipped_on_off=True), car, 2.0)
    car.x = np.array([0.01, 0.2, 0.0, -0.1])
    f_c = law.optimal_force_n()
    assert law.demand(0.5 * f_c) == Demand(current_a=2.0)  # |f| < |f_c|, same sign: more
    assert law.demand(2.0 * f_c) == Demand(current_a=0.0)
    assert law.demand(-f_c) == Demand(current_a=0.0)


def test_a_vehicle_law_on_a_building_is_refused() -> None:
    b = ShearBuilding(BuildingParams(), np.zeros(3), DT)
    with pytest.raises(ValueError, match="needs a quarter car"):
        Law("skyhook", LawParams(), b, 2.0)


def test_the_extrapolation_is_exact_for_a_polynomial_of_its_order() -> None:
    """Horiuchi et al. (1996): a cubic through four samples is continued exactly."""

    def cubic(t):
        return 0.3 - 0.2 * t + 0.05 * t**2 + 0.01 * t**3

    for lead in (0.0, 0.7, 2.5, 4.0):
        w, dw = extrapolation_weights(3, lead)
        x = np.array([cubic(-j) for j in range(4)])
        assert w @ x == pytest.approx(cubic(lead))
        assert dw @ x == pytest.approx(-0.2 + 0.1 * lead + 0.03 * lead**2)


def _servo_actuator_run(target: np.ndarray, method: str, transport_frames: int = 2):
    """The RTHS benchmark's servo-valve / actuator a1 b0 / (s^2 + b1 s + b2) (b1 = 425 1/s,
    b2 = 1.0e5 1/s^2, unit static gain) behind `transport_frames` of transport, 2 um sensor
    noise: the measured stroke of each frame and the compensator's last delay estimate."""
    ad, bd = zoh(np.array([[0.0, 1.0], [-1.0e5, -425.0]]), np.array([[0.0], [1.0e5]]), DT)
    comp = make_compensator(method, 3, DT, 0.006, 0.04)
    noise = np.random.default_rng(1).normal(0.0, 2e-6, target.size)
    x, pipe, measured = np.zeros(2), [0.0] * transport_frames, np.empty(target.size)
    for k in range(target.size):
        measured[k] = x[0] + noise[k]
        setpoint, _velocity = comp.update(target[min(k + 1, target.size - 1)], measured[k])
        pipe.append(setpoint)
        x = ad @ x + bd[:, 0] * pipe.pop(0)
    return measured, comp.delay_s


@pytest.mark.parametrize("method", ["polynomial", "adaptive"])
def test_compensation_meets_the_acceptance_bounds_on_a_servo_actuator(method: str) -> None:
    """issue 41: with compensation J1 <= 0.5 ms, J2 <= 2 %, J3 <= 5 % (after 10 s of
    convergence); without it J1 is several ms (a 2 Hz stroke of 10 mm plus a 9 Hz one)."""
    t = np.arange(0.0, 20.0, DT)
    target = 0.01 * np.sin(2 * np.pi * 2.0 * t) + 0.002 * np.sin(2 * np.pi * 9.0 * t + 1.0)
    half = t.size // 2
    raw, _ = _servo_actuator_run(target, "none")
    uncompensated = tracking(target[half:], raw[half:], DT)
    assert uncompensated.j1_ms > 5.0 and uncompensated.j2_pct > 5.0
    measured, delay_s = _servo_actuator_run(target, method)
    got = tracking(target[half:], measured[half:], DT)
    assert abs(got.j1_ms) <= 0.5 and got.j2_pct <= 2.0 and got.j3_pct <= 5.0, got
    assert 5e-3 < delay_s < 9e-3


def test_j1_j2_j3_of_a_known_delay_and_error() -> None:
    t = np.arange(0.0, 10.0, DT)
    x_c = np.sin(2 * np.pi * 1.0 * t)
    x_m = np.sin(2 * np.pi * 1.0 * (t - 0.005))  # 2.5 samples late
    got = tracking(x_c, x_m, DT)
    assert got.j1_lag_samples in (2, 3)
    assert got.j1_ms == pytest.approx(5.0, abs=0.05)
    assert got.j2_pct == pytest.approx(100 * 2 * np.sin(np.pi * 0.005), rel=1e-3)
    assert tracking(x_c, x_c + 0.01, DT).j3_pct == pytest.approx(1.0)
    e = response_error(1.02 * x_c, x_c)
    assert (e.rms_pct, e.peak_pct, e.rms_of_rms_pct) == pytest.approx((2.0, 2.0, 2.0))


def test_j2_j3_apart_from_stalls_set_aside_only_what_a_measured_stall_explains() -> None:
    """A stall (a frame answered 5 ms late: its setpoint dropped) and, 10 ms later, a 3 mm
    error: set aside; a frame delivered 4 ms after the one before: a stall too; a 1 mm error
    with no stall in the 20 ms before it stays in J3."""
    t = np.arange(0.0, 8.0, DT)
    x_c = 0.02 * np.sin(2 * np.pi * 1.0 * t)
    x_m = x_c.copy()
    latency_us = np.full(t.size, 400.0)
    latency_us[1000] = 5000.0
    x_m[1005] += 0.003  # 10 ms after the stall: 15 % of the 20 mm peak
    t[1500:] += 0.002  # frame 1500 delivered 4 ms after frame 1499
    x_m[1509] -= 0.002  # 18 ms after it: 10 %
    x_m[2000] += 0.001  # no stall: 5 %
    got = tracking_apart_from_stalls(x_c, x_m, t, latency_us, DT)
    assert got.stalls == 2 and got.excluded == 2 * 11
    assert got.j3_pct == pytest.approx(5.0, rel=1e-6)
    assert got.peak_after_stall and got.peak_t_s == pytest.approx(t[1005])
    assert tracking(x_c, x_m, DT).j3_pct == pytest.approx(15.0, rel=1e-6)
    x_m[1011] += 0.004  # 22 ms after the stall: the stall no longer explains it
    got = tracking_apart_from_stalls(x_c, x_m, t, latency_us, DT)
    assert got.j3_pct == pytest.approx(20.0, rel=1e-6) and not got.peak_after_stall


@pytest.mark.parametrize(
    "path", sorted((REPO / "configs/hil").glob("*.toml")), ids=lambda p: p.name
)
def test_every_shipped_scenario_parses(path: Path) -> None:
    assert load_scenario(path).steps > 0


def test_the_shipped_scenarios_are_the_issue_s() -> None:
    car = load_scenario("configs/hil/quarter-car.toml")
    assert (car.kind, car.law, car.road.iso_class, car.road.speed_m_s) == (
        "quarter-car",
        "skyhook",
        "C",
        20.0,
    )
    assert car.duration_s == 60.0 and car.steps == 30_000
    # the road alone: a bump asks a stroke velocity past firmware_sim's actuator (1 m/s)
    assert car.road.bumps == ()
    bump = load_scenario("configs/hil/quarter-car-bump.toml")
    assert len(bump.road.bumps) == 1 and dataclasses.replace(bump.road, bumps=()) == car.road
    building = load_scenario("configs/hil/building.toml")
    assert (building.kind, building.law) == ("building", "clipped-optimal")


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ('law = "sky"', "law: expected one of"),
        ('iso_class = "Q"', "road.iso_class: expected one of"),
        ("speed_m_s = -3.0", "road.speed_m_s: must be positive, got -3.0"),
        ("m_s_kg = 0.0", "quarter_car.m_s_kg: must be positive"),
        ("wheels = 4", "quarter_car.wheels: unknown field"),
        ('method = "smith"', "compensation.method: expected one of"),
        ("lqr_output_weights = [1.0, 2.0]", "laws.lqr_output_weights: 3 weights"),
    ],
)
def test_a_bad_scenario_field_is_one_line_naming_it(
    tmp_path: Path, edit: str, message: str
) -> None:
    text = (REPO / "configs/hil/quarter-car.toml").read_text()
    key = edit.split(" = ")[0]
    lines = text.splitlines()
    hit = [i for i, line in enumerate(lines) if line.startswith(f"{key} =")]
    if hit:
        lines[hit[0]] = edit
    else:
        lines.insert(lines.index("[quarter_car]") + 1, edit)
    path = tmp_path / "bad.toml"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError) as info:
        load_scenario(path)
    text = str(info.value)
    assert "\n" not in text and text.startswith(str(path)) and message in text, text


def test_a_building_with_a_vehicle_law_is_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"law: 'skyhook' needs a quarter car"):
        load_scenario("configs/hil/building.toml", law="skyhook")
    assert dataclasses.replace(load_scenario("configs/hil/building.toml")).law == "clipped-optimal"


def test_the_delay_estimate_holds_while_the_setpoint_rests() -> None:
    """A setpoint that moves only by rounding (1 nm) and a noisy measured stroke say nothing of
    the delay: the estimate stays where it was."""
    from mrrig.hil.compensation import DelayEstimator

    rng = np.random.default_rng(4)
    est = DelayEstimator(max_lag=21, window_frames=1000.0, initial_frames=4.0)
    for _ in range(3000):
        est.update(1e-9 * rng.standard_normal(), 2e-6 * rng.standard_normal())
    assert est.delay_frames == 4.0


def test_the_delay_estimate_waits_a_quarter_window_then_finds_the_delay() -> None:
    """A few frames of a starting stroke and the sensor's noise are no estimate: on the
    simulator the least-squares lag of the first 20-30 frames was 13-20 frames where the rig's
    was 3, and the hybrid loop led by it went unstable. The estimate stays the initial one for
    a quarter of the window (250 frames), then finds the delay of 3 frames."""
    from mrrig.hil.compensation import DelayEstimator

    rng = np.random.default_rng(7)
    sent = np.cumsum(rng.normal(0.0, 2e-4, 1500))  # a setpoint that moves every frame
    measured = np.concatenate([np.zeros(3), sent[:-3]]) + rng.normal(0.0, 2e-6, 1500)
    measured[:40] = rng.normal(0.0, 2e-6, 40)  # the first frames: noise, nothing moved yet
    est = DelayEstimator(max_lag=21, window_frames=1000.0, initial_frames=4.0)
    seen = [est.update(sent[k - 1], measured[k]) for k in range(1, 1500)]
    assert set(seen[:249]) == {4.0}
    assert abs(seen[-1] - 3.0) < 0.05, seen[-1]


def test_the_model_predicts_its_own_stroke_with_the_force_held() -> None:
    """The model-based compensation's prediction L frames ahead is where the model goes when
    the measured force stays as it is (the road ahead known); between frames, to 1 %."""
    from mrrig.hil.road import road_input_m

    road = road_input_m("C", 20.0, 2.0, DT, seed=9)
    car = QuarterCar(QuarterCarParams(), road, DT)
    for _ in range(300):
        car.step(800.0 * car.stroke_velocity_m_s)
    force = car.force_n
    ahead = {lead: car.predicted_stroke(lead) for lead in (0.0, 3.0, 3.5, 4.0)}
    twin = QuarterCar(QuarterCarParams(), road, DT)
    twin.x, twin.k = car.x.copy(), car.k
    strokes, states = [twin.stroke_m], [twin.x.copy()]
    for _ in range(4):
        twin.step(force)
        strokes.append(twin.stroke_m)
        states.append(twin.x.copy())
    assert ahead[0.0][0] == car.stroke_m
    assert ahead[3.0][0] == pytest.approx(strokes[3], rel=1e-12, abs=1e-15)
    assert ahead[4.0][0] == pytest.approx(strokes[4], rel=1e-12, abs=1e-15)
    # half a frame after the third: the ODE with the force and the road held
    u = np.array([force, road[car.k + 3]])
    half = solve_ivp(
        lambda _t, x: car.a @ x + car.b @ u, (0, DT / 2), states[3], rtol=1e-11, atol=1e-14
    ).y[:, -1]
    assert ahead[3.5][0] == pytest.approx(half[0] - half[2], rel=1e-7)


def test_the_ground_motion_is_kanai_tajimi_shaped_seeded_and_scaled_to_its_pga() -> None:
    from scipy.signal import welch

    from mrrig.hil.ground import GroundMotion, envelope, ground_acceleration_m_s2

    g = GroundMotion(pga_m_s2=2.0, ground_frequency_hz=5.0, strong_until_s=200.0, seed=3)
    a = ground_acceleration_m_s2(g, 200.0, DT)
    assert a.size == 100_001 and np.max(np.abs(a)) == pytest.approx(2.0)
    assert np.array_equal(a, ground_acceleration_m_s2(g, 200.0, DT))
    # the strong motion's PSD against Kanai-Tajimi's shape (the scale aside), per octave
    f, psd = welch(a[1000:], fs=1.0 / DT, nperseg=4096)
    w, wg, z = 2 * np.pi * f, 2 * np.pi * 5.0, 0.6
    shape = (wg**4 + 4 * z**2 * wg**2 * w**2) / ((wg**2 - w**2) ** 2 + 4 * z**2 * wg**2 * w**2)
    bands = [(0.5, 1.0), (1.0, 2.0), (2.0, 4.0), (4.0, 8.0), (8.0, 16.0), (16.0, 32.0)]
    ratio = [
        psd[(f >= lo) & (f < hi)].mean() / shape[(f >= lo) & (f < hi)].mean() for lo, hi in bands
    ]
    assert np.ptp(np.log(ratio)) < np.log(1.3), ratio
    t = np.array([0.0, 0.5, 1.0, 6.0, 8.0])
    assert envelope(t, GroundMotion()) == pytest.approx([0.0, 0.25, 1.0, 1.0, np.exp(-1.0)])


def test_the_ground_record_is_the_filter_s_exact_recursion() -> None:
    """The record on floats (a building's run is built in a few ms, not 0.2-0.3 s) is the
    Kanai-Tajimi filter's exact discretisation stepped in matrices, to 1e-12 of the PGA."""
    from mrrig.hil.ground import GroundMotion, envelope, ground_acceleration_m_s2
    from mrrig.hil.substructure import zoh

    g = GroundMotion(seed=5)
    got = ground_acceleration_m_s2(g, 20.0, DT)
    w = 2 * np.pi * g.ground_frequency_hz
    a = np.array([[0.0, 1.0], [-w * w, -2 * g.ground_damping * w]])
    ad, bd = zoh(a, np.array([[0.0], [-1.0]]), DT)
    noise = np.random.default_rng(g.seed).standard_normal(got.size)
    x, want = np.zeros(2), np.empty(got.size)
    for k in range(got.size):
        want[k] = -(2 * g.ground_damping * w * x[1] + w * w * x[0])
        x = ad @ x + bd[:, 0] * noise[k]
    want *= envelope(np.arange(got.size) * DT, g)
    want *= g.pga_m_s2 / np.max(np.abs(want))
    assert np.max(np.abs(got - want)) <= 1e-12 * g.pga_m_s2
