"""firmware_sim's servo-hydraulic actuator (`firmware_sim/actuator.py`, spec/hil.md "Actuator
delay and its compensation"): its step and frequency response are its configured transfer
function's, its limits hold, its spread is seeded, and uncompensated it lags a 2 Hz stroke by
several ms (J1, spec/hil.md "Metrics"), as a real servo does. Pure numerics, at 500 Hz."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import signal

from firmware_sim.actuator import ServoActuator, ServoParams
from firmware_sim.config import ActuatorConfig, ConfigError, ServoConfig, load_config
from tests.test_firmware import QUIET, Rig

T = 0.002  # the contract's RigSensors period: the simulator's rate
STROKE_M = 0.04


def tracking_delay_s(x_m: np.ndarray, x_c: np.ndarray, period_s: float = T) -> float:
    """J1 (spec/hil.md): the lag at the maximum of the cross-correlation of the measured x_m
    and the commanded x_c over lags 0..49 samples, one-sided."""
    n = len(x_c)
    corr = [float(np.dot(x_m[lag:], x_c[: n - lag])) for lag in range(50)]
    return int(np.argmax(corr)) * period_s


def play(
    servo: ServoActuator, setpoints: np.ndarray, feedforward: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The piston's position and velocity after each period of the setpoints."""
    ff = np.zeros_like(setpoints) if feedforward is None else feedforward
    out = np.array([servo.step(float(r), float(w), T) for r, w in zip(setpoints, ff, strict=True)])
    return out[:, 0], out[:, 1]


def sine(frequency_hz: float, amplitude_m: float, seconds: float) -> tuple[np.ndarray, ...]:
    """Sample times (the end of each period), the sine and its rate."""
    t = np.arange(1, round(seconds / T) + 1) * T
    w = 2 * math.pi * frequency_hz
    return t, amplitude_m * np.sin(w * t), amplitude_m * w * np.cos(w * t)


@pytest.mark.parametrize("delay_s", [0.002, 0.0023])
def test_the_step_response_is_the_transfer_function_s_to_the_sampled_setpoint(delay_s):
    """A 1 mm step at the 5th period: the piston follows g b2 / (s^2 + b1 s + b2) e^(-s D)
    driven by the setpoint's samples joined by straight lines (scipy's lsim on a 10 us grid,
    an independent integration), within 0.01 um; the overshoot is the pair's."""
    params = ServoParams(transport_delay_s=delay_s)
    n, step_m = 100, 0.001
    setpoints = np.where(np.arange(1, n + 1) >= 5, step_m, 0.0)
    x, _ = play(ServoActuator(params, STROKE_M), setpoints)

    grid = 200  # lsim points per period
    t_samples = np.arange(0, n + 1) * T
    r_samples = np.concatenate([[0.0], setpoints])
    t_fine = np.linspace(0.0, n * T, n * grid + 1)
    u = np.interp(t_fine - delay_s, t_samples, r_samples, left=0.0)
    b1, b2 = params.b1_per_s, params.b2_per_s2
    _, y, _ = signal.lsim(
        signal.lti([params.static_gain * b2], [1.0, b1, b2]), u, t_fine, interp=True
    )
    expected = y[::grid][1:]
    err_m = float(np.max(np.abs(x - expected)))
    zeta = b1 / (2 * math.sqrt(b2))
    overshoot = x.max() / step_m - 1
    ideal = math.exp(-math.pi * zeta / math.sqrt(1 - zeta * zeta))
    print(
        f"\nstep 1 mm, delay {delay_s * 1e3:.1f} ms: max |x - lsim| {err_m * 1e6:.2e} um; "
        f"overshoot {overshoot * 100:.2f} % (an ideal step's {ideal * 100:.2f} %, zeta {zeta:.3f})"
    )
    assert err_m < 1e-8
    # nothing moves before the setpoint's rise (from 4 T) has come through the delay
    moved = np.arange(1, n + 1) * T > 4 * T + delay_s + 1e-12
    assert np.all(x[~moved] == 0.0) and np.all(x[moved] > 0.0)
    assert x[-1] == pytest.approx(step_m, rel=1e-4)
    assert overshoot == pytest.approx(ideal, abs=0.01)


@pytest.mark.parametrize("ff_gain", [0.0, 1.0])
def test_the_frequency_response_matches_the_configured_transfer_function(ff_gain):
    """At 1, 2, 5, 10 and 20 Hz, the gain and phase fitted to the piston's steady motion are
    `transfer(f)`'s times the straight-line hold's sinc^2(f T) (the setpoint's samples joined
    by lines: no phase, 0.5 % less gain at 20 Hz), within 0.01 % and 0.01 degrees, for the
    seeded actuator (not the nominal one) and a feedforward from none to full."""
    params = dataclasses.replace(ServoConfig().actual(), velocity_ff_gain=ff_gain)
    assert params != ServoParams(velocity_ff_gain=ff_gain)
    for f in (1.0, 2.0, 5.0, 10.0, 20.0):
        t, r, rd = sine(f, 0.005, 3.0)
        x, _ = play(ServoActuator(params, STROKE_M), r, rd)
        steady = t > 1.0
        w = 2 * math.pi * f
        basis = np.column_stack([np.sin(w * t[steady]), np.cos(w * t[steady])])
        (xs, xc), *_ = np.linalg.lstsq(basis, x[steady], rcond=None)
        measured = complex(xs, xc) / 0.005
        expected = params.transfer(f) * np.sinc(f * T) ** 2
        delay_ms = -np.angle(measured) / w * 1e3
        print(
            f"\nk_ff {ff_gain:g}, {f:4g} Hz: gain {abs(measured):.5f} (TF {abs(expected):.5f}), "
            f"delay {delay_ms:.3f} ms (TF {-np.angle(expected) / w * 1e3:.3f} ms)"
        )
        assert abs(measured) == pytest.approx(abs(expected), rel=1e-4)
        assert math.degrees(abs(np.angle(measured / expected))) < 0.01


def test_uncompensated_j1_at_2_hz_is_several_ms_as_a_real_servo_s():
    """J1 of the default (seeded) actuator on a 10 mm, 2 Hz sine, setpoint straight through
    (no compensation, no feedforward): several ms, at the sample nearest the transfer
    function's phase delay."""
    params = ServoConfig().actual()
    t, r, _ = sine(2.0, 0.01, 10.0)
    x, _ = play(ServoActuator(params, STROKE_M), r)
    j1_s = tracking_delay_s(x[t > 1.0], r[t > 1.0])
    phase_delay_s = -np.angle(params.transfer(2.0)) / (2 * math.pi * 2.0)
    nominal_s = -np.angle(ServoParams().transfer(2.0)) / (2 * math.pi * 2.0)
    print(
        f"\nJ1 at 2 Hz, uncompensated: {j1_s * 1e3:.0f} ms (this actuator's phase delay "
        f"{phase_delay_s * 1e3:.2f} ms, the nominal one's {nominal_s * 1e3:.2f} ms)"
    )
    assert 0.004 <= j1_s <= 0.010
    assert abs(j1_s - phase_delay_s) <= T / 2


def test_the_stroke_and_velocity_limits_hold_and_are_counted():
    """A 60 mm sine on a 40 mm stroke is clamped to it; a 30 mm, 15 Hz sine (2.8 m/s) is
    rate-limited to 1 m/s per period; a jump is too; the piston never leaves the stroke nor
    moves faster than the valve's limit."""
    params = ServoParams()
    servo = ServoActuator(params, STROKE_M)
    _, r, _ = sine(2.0, 0.06, 2.0)
    x, v = play(servo, r)
    assert np.max(np.abs(x)) <= STROKE_M
    assert np.max(np.abs(x)) > 0.039  # it does reach the end
    assert servo.clamped_setpoints == int(np.sum(np.abs(r) > STROKE_M))
    assert servo.rate_limited_setpoints == 0

    servo = ServoActuator(params, STROKE_M)
    _, r, rd = sine(15.0, 0.03, 1.0)
    x, v = play(servo, r, rd)
    assert np.max(np.abs(v)) <= params.velocity_limit_m_s
    assert np.max(np.abs(v)) == pytest.approx(params.velocity_limit_m_s)
    assert np.max(np.abs(np.diff(x))) <= params.velocity_limit_m_s * T + 1e-12
    assert servo.rate_limited_setpoints > 0

    servo = ServoActuator(params, STROKE_M)
    servo.step(0.03, 0.0, T)
    assert servo.setpoint_m == pytest.approx(params.velocity_limit_m_s * T)
    assert servo.rate_limited_setpoints == 1


def test_the_spread_is_seeded_within_its_bounds_and_zero_is_the_nominal_actuator():
    nominal = ServoParams()
    a = ServoConfig(seed=7).actual()
    assert a == ServoConfig(seed=7).actual()
    assert a != ServoConfig(seed=8).actual()
    for name in ("b1_per_s", "b2_per_s2", "transport_delay_s"):
        ratio = getattr(a, name) / getattr(nominal, name)
        assert 0.8 <= ratio <= 1.2 and ratio != 1.0
    assert (a.static_gain, a.velocity_ff_gain) == (1.0, 0.0)
    assert ServoConfig(spread=0.0).actual() == nominal
    # the same seed plays the same motion
    _, r, _ = sine(3.0, 0.01, 1.0)
    assert np.array_equal(
        play(ServoActuator(a, STROKE_M), r)[0],
        play(ServoActuator(ServoConfig(seed=7).actual(), STROKE_M), r)[0],
    )


def _displacements(servo_waveforms: bool) -> tuple[np.ndarray, np.ndarray]:
    """The motion generator's sine (10 mm, 2 Hz, autostart) and the Displacement the firmware
    sends, noise off, for 6 s."""
    act = ActuatorConfig(autostart="SINE", servo=ServoConfig(waveforms=servo_waveforms))
    rig = Rig(dataclasses.replace(QUIET, actuator=act))
    waveform = []
    for _ in range(3000):
        rig.tick()
        waveform.append(rig.fw.actuator.x_m)
    sent = [p.values["Displacement"] for p in rig.sensors if p.ok]
    assert len(sent) == len(waveform)
    return np.array(waveform)[1000:], np.array(sent)[1000:]


def test_with_servo_waveforms_on_the_rig_s_stroke_lags_its_sine_by_the_servo_and_off_not():
    """`[actuator.servo] waveforms = true`: the sine is the servo's setpoint and the sent
    Displacement lags it by the seeded actuator's J1; off (the default), the Displacement is
    the sine itself (to the DBC's 1 um)."""
    waveform, sent = _displacements(True)
    j1_s = tracking_delay_s(sent, waveform)
    print(f"\nfirmware, servo on the waveforms: J1 at 2 Hz {j1_s * 1e3:.0f} ms")
    assert 0.004 <= j1_s <= 0.010
    waveform, sent = _displacements(False)
    assert tracking_delay_s(sent, waveform) == 0.0
    assert np.max(np.abs(sent - waveform)) <= 0.5e-6 + 1e-12


def test_servo_parameters_are_read_from_actuator_servo_and_a_bad_one_is_named(tmp_path):
    config = load_config("configs/sim.toml")
    assert config.actuator.servo == ServoConfig()
    good = tmp_path / "sim.toml"
    good.write_text(
        "[actuator.servo]\nwaveforms = true\nb1_per_s = 300.0\ntransport_delay_s = 0.004\n"
        "spread = 0.0\n"
    )
    servo = load_config(good).actuator.servo
    assert servo.waveforms and servo.actual() == ServoParams(
        b1_per_s=300.0, transport_delay_s=0.004
    )
    for text, field in (
        ("b2_per_s2 = -1.0", "b2_per_s2: must be in"),
        ("spread = 0.9", "spread: must be in"),
        ("velocity_ff_gain = 2.0", "velocity_ff_gain: must be in"),
        ("bandwidth_hz = 50.0", "bandwidth_hz: unknown field"),
    ):
        good.write_text(f"[actuator.servo]\n{text}\n")
        with pytest.raises(ConfigError, match=rf"sim.toml: actuator\.servo\.{field}"):
            load_config(good)
