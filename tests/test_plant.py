import dataclasses
import tracemalloc

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from damper.plant import (
    BoucWenDamper,
    BoucWenParams,
    damper_force,
    simulate,
    state_derivative,
)
from damper.signals import sine

PAPER = BoucWenParams.preset("paper-volt")


def test_presets_hold_paper_table_3_and_rig_current_uses_the_same_numbers():
    assert (PAPER.c0a, PAPER.c1b, PAPER.alpha_b, PAPER.gamma, PAPER.beta, PAPER.eta) == (
        784.0,
        34622.0,
        38430.0,
        136320.0,
        2059020.0,
        190.0,
    )
    assert BoucWenParams.preset("rig-current") == PAPER


def test_unknown_preset_names_itself_and_the_known_ones():
    with pytest.raises(ValueError, match="'lord'.*paper-volt, rig-current"):
        BoucWenParams.preset("lord")


@pytest.mark.parametrize("command", [0.0, 1.0, 2.0])
@pytest.mark.long
def test_step_matches_tight_radau_reference_within_5_n(command):
    amp_m, freq_hz, dt_s = 0.015, 4.0, 2e-3
    t = np.arange(1001) * dt_s
    x, xd, _ = sine(t, amp_m, freq_hz)

    def rhs(ti, s):
        xi, xdi, _ = sine(ti, amp_m, freq_hz)
        return state_derivative(s, xi, xdi, command, PAPER)

    ref = solve_ivp(
        rhs,
        (0.0, t[-1]),
        [0.0, x[0], command],
        method="Radau",
        t_eval=t,
        rtol=1e-8,
        atol=[1e-11, 1e-11, 1e-11],
    )
    assert ref.success
    f_ref = np.array([damper_force(ref.y[:, k], x[k], xd[k], PAPER) for k in range(t.size)])

    damper = BoucWenDamper(PAPER)
    f = [damper.reset(x[0], xd[0], command)]
    f += [damper.step(x[k], xd[k], command, dt_s) for k in range(1, t.size)]
    err = np.max(np.abs(np.array(f) - f_ref))
    print(f"command {command}: max |f - f_Radau| = {err:.3g} N (peak {np.abs(f_ref).max():.0f} N)")
    assert err < 5.0


def _spencer_zdot(z, y, u, x, xd, p):
    alpha = p.alpha_a + p.alpha_b * u
    c0 = p.c0a + p.c0b * u
    c1 = p.c1a + p.c1b * u
    yd = (alpha * z + c0 * xd + p.k0 * (x - y)) / (c0 + c1)
    r = xd - yd
    # n = 2: z|z|^(n-1) = z|z|, |z|^n = z^2
    return -p.gamma * abs(r) * z * abs(z) - p.beta * r * z * z + p.A * r


def test_z_rate_follows_spencer_gamma_beta_convention():
    # z < 0 < x' - y': here the two conventions give different z' (they agree when z and
    # x' - y' have the same sign).
    z, y, u, x, xd, v = -0.003, 0.001, 0.5, 0.004, 0.2, 1.0
    zd, yd, ud = state_derivative(np.array([z, y, u]), x, xd, v, PAPER)
    assert zd == pytest.approx(_spencer_zdot(z, y, u, x, xd, PAPER), rel=1e-12)
    swapped = dataclasses.replace(PAPER, gamma=PAPER.beta, beta=PAPER.gamma)
    assert abs(zd - _spencer_zdot(z, y, u, x, xd, swapped)) > 0.01 * abs(zd)
    assert ud == pytest.approx(-PAPER.eta * (u - v))


def test_swapped_gamma_beta_convention_changes_the_force_loop():
    t = np.arange(1001) * 1e-3
    x, xd, _ = sine(t, 0.015, 2.0)
    swapped = dataclasses.replace(PAPER, gamma=PAPER.beta, beta=PAPER.gamma)
    last_cycle = t >= 0.5
    for command in (0.0, 1.0):
        f = simulate(PAPER, t, x, xd, np.full_like(t, command))[last_cycle]
        f_sw = simulate(swapped, t, x, xd, np.full_like(t, command))[last_cycle]
        rel = np.sqrt(np.mean((f - f_sw) ** 2)) / np.sqrt(np.mean(f**2))
        print(f"command {command}: swapped convention changes the loop by {100 * rel:.1f} % rms")
        assert rel > 0.02


def test_scalar_and_batch_steps_give_the_same_forces():
    t = np.arange(101) * 2e-3
    amps = np.array([0.010, 0.015, 0.020])
    cmds = np.array([0.0, 0.7, 1.8])
    x, xd, _ = sine(t[None, :], amps[:, None], 3.0)
    batch = BoucWenDamper(PAPER)
    f_batch = [batch.reset(x[:, 0], xd[:, 0], cmds)]
    f_batch += [batch.step(x[:, k], xd[:, k], cmds, 2e-3) for k in range(1, t.size)]
    f_batch = np.array(f_batch).T
    for i in range(3):
        one = BoucWenDamper(PAPER)
        xs, vs = x[i].tolist(), xd[i].tolist()
        f_one = [one.reset(xs[0], vs[0], float(cmds[i]))]
        f_one += [one.step(xs[k], vs[k], float(cmds[i]), 2e-3) for k in range(1, t.size)]
        assert all(type(f) is float for f in f_one)
        np.testing.assert_array_equal(f_batch[i], f_one)


def test_simulate_numpy_batch_equals_per_run_scalar_simulation():
    # 40 runs take the numpy batch path; each row alone takes the float path.
    t = np.arange(61) * 2e-3
    amps = np.linspace(0.005, 0.02, 40)
    x, xd, _ = sine(t[None, :], amps[:, None], 4.0)
    cmd = np.linspace(0.0, 2.0, 40)[:, None] + 0.3 * np.sin(20.0 * t)
    f = simulate(PAPER, t, x, xd, cmd)
    assert f.shape == (40, t.size)
    for i in (0, 17, 39):
        np.testing.assert_array_equal(f[i], simulate(PAPER, t, x[i], xd[i], cmd[i]))


def test_simulate_holds_the_previous_command_over_each_interval():
    t = np.arange(3) * 2e-3
    x = np.array([0.0, 0.001, 0.002])
    xd = np.full(3, 0.5)
    f = simulate(PAPER, t, x, xd, np.array([0.0, 0.0, 2.0]))
    f_zero = simulate(PAPER, t, x, xd, np.zeros(3))
    assert f[2] == f_zero[2]  # the command at the last sample never acts


@pytest.mark.parametrize("speed_m_s", [0.8, 2.0, 10.0])
def test_a_step_faster_than_its_substeps_are_stable_for_takes_more_of_them(speed_m_s):
    # the daemon's Bouc-Wen reference steps with 0.25 ms sub-steps, stable to about 0.35 m/s;
    # a velocity spike of the estimate after a bus stall (0.8 m/s) used to give NaN
    rig = BoucWenParams.preset("rig-current")
    forces = []
    for substep_s in (2.5e-4, 1e-5):
        damper, x = BoucWenDamper(rig, substep_s), -0.012
        damper.reset(x, 0.06, 0.5)
        for _ in range(100):
            x += 0.06 * 2e-3
            damper.step(x, 0.06, 0.5, 2e-3)
        f = []
        for _ in range(5):
            x += speed_m_s * 2e-3
            f.append(damper.step(x, speed_m_s, 0.5, 2e-3))
        forces.append(f)
    assert np.all(np.isfinite(forces[0]))
    np.testing.assert_allclose(forces[0], forces[1], atol=1.0)


def test_fast_steps_keep_one_table_of_sub_steps_not_one_per_speed():
    # the daemon's Bouc-Wen reference after each bus stall: the stall's travel in one step, a
    # new speed and so a new number of sub-steps each time; a node table kept per number
    # grew the daemon by MBs over a 10-minute run (docs/measurements.md)
    from damper.plant import _MAX_SUBSTEPS, _hermite_nodes

    damper = BoucWenDamper(BoucWenParams.preset("rig-current"), 2.5e-4)
    damper.reset(0.0, 0.0, 0.5)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        largest = _hermite_nodes(2e-3, _MAX_SUBSTEPS)
        one_table = tracemalloc.get_traced_memory()[0] - before
        del largest
        x, sign = 0.0, 1.0
        for speed in np.linspace(0.4, 17.0, 20):  # 9 to 384 sub-steps
            x = sign * 0.5 * speed * 2e-3
            damper.step(x, sign * speed, 0.5, 2e-3)
            sign = -sign
        kept = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert kept < 2 * one_table, f"{kept} bytes kept after 20 speeds, one table {one_table}"


def test_step_rejects_non_positive_interval():
    with pytest.raises(ValueError, match="dt_s"):
        BoucWenDamper(PAPER).step(0.0, 0.0, 0.0, 0.0)


def test_at_75_degc_the_force_at_the_same_current_and_motion_is_15_percent_less():
    """The `heating` preset's default: every force parameter falls 0.3 % per K."""
    from damper.plant import params_at_temperature

    warm = params_at_temperature(PAPER, 50.0, -0.003, -0.003, -0.003)
    t = np.arange(0, 1.0, 1e-3)
    x, xd = 0.01 * np.sin(2 * np.pi * 3 * t), 0.01 * 2 * np.pi * 3 * np.cos(2 * np.pi * 3 * t)
    forces = []
    for p in (PAPER, warm):
        d = BoucWenDamper(p)
        d.reset(x[0], xd[0], 1.0)
        forces.append(
            np.array([d.step(a, b, 1.0, 1e-3) for a, b in zip(x[1:], xd[1:], strict=True)])
        )
    np.testing.assert_allclose(forces[1], 0.85 * forces[0], rtol=1e-9, atol=1e-9)
    d = BoucWenDamper(PAPER)
    with pytest.raises(ValueError, match="gamma"):
        d.set_params(dataclasses.replace(PAPER, gamma=1.0))
