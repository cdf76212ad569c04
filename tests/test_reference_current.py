"""The ideal controller of a reference damper (`reference_current`): its own current as the
command, the floor a plan prints beside the daemon's Et (issue 43, item 4)."""

from __future__ import annotations

import numpy as np
import pytest

from mrrig.config import load_config
from mrrig.loop.reference import PAPER_CASE_DT_S, paper_case_command
from mrrig.loop.samples import RigState
from mrrig.offline.metrics import error_norm
from tests.conftest import rig_config
from tests.lockstep_rig import lockstep_config, run_lockstep

DT_S = 0.002


def test_the_ideal_controller_commands_the_cases_own_current_and_tracks_near_the_noise(
    tmp_path,
):
    """Case 2 (a random current) over the simulated rig in lockstep: each armed frame's
    command is the case's current over the period it acts on (the reference damper's, the
    zero-order hold's second millisecond), and the measured force follows the desired one
    (Et 0.0125-0.0216 a second over seconds 1-6: the reference damper starts at rest where
    it is armed, y = x, and its internal displacement y relaxes toward the plant's with
    (c0 + c1) / k0, about 14 s)."""
    config = lockstep_config(
        tmp_path,
        controller={"name": "reference_current"},
        reference={"kind": "paper_case", "case": 4, "current_scale": 0.5, "preset": "rig-current"},
    )
    run = run_lockstep(config, ("RANDOM", 0.02, 2.0), seconds=4.0, preroll_s=2.0, arm=True)
    s = run.samples
    armed = s["state"] == RigState.ARMED
    assert armed.all(), "armed from the first frame"
    current = 0.5 * paper_case_command(4)
    k = np.round((s["t"] - s["t"][0] + DT_S) / PAPER_CASE_DT_S).astype(int) - 1
    np.testing.assert_allclose(s["i_cmd"], current[k % current.size], rtol=0, atol=1e-12)
    judged = slice(1000, None)  # after 2 s
    et = error_norm(s["f_des"][judged], s["f_meas"][judged])
    assert et < 0.025, f"the ideal controller's Et {et:.4f}"


def test_arming_the_ideal_controller_on_a_reference_without_a_current_is_refused(tmp_path):
    from mrrig.loop.daemon import Daemon, build_controller, build_reference
    from mrrig.rigio.control import Preparer, RequestError, parse_request

    config = rig_config(tmp_path, "unused", None, reference={"kind": "constant", "offset_n": 0})
    d = Daemon(load_config(config, {"controller": {"name": "reference_current"}}))
    prep = Preparer(d, build_controller, build_reference)
    arm = prep.prepare(parse_request(b'{"cmd": "arm"}'))
    with pytest.raises(RequestError, match=r"^arm: controller reference_current .* constant has"):
        d.requests.apply(arm)
    assert d.supervisor.state is not RigState.ARMED
    profile = b'{"cmd": "set_profile", "kind": "paper_case", "case": 5, "current_scale": 0.5}'
    d.requests.apply(prep.prepare(parse_request(profile)))
    d.requests.apply(prep.prepare(parse_request(b'{"cmd": "arm"}')))
    assert d.supervisor.state is RigState.ARMED


def _moved(reference, seconds: float, t0: float = 0.0) -> float:
    """The reference damper moved along a 1 Hz, 1 cm sine for `seconds`; the end time."""
    k = round(seconds / DT_S)
    for j in range(1, k + 1):
        t = t0 + j * DT_S
        w = 2 * np.pi
        reference.force(t, 0.01 * np.sin(w * t), 0.01 * w * np.cos(w * t))
    return t0 + k * DT_S


def test_a_reference_damper_keeps_its_motion_state_over_arm_controller_and_profile(tmp_path):
    """The damper under test moves all along, and its internal displacement y sits near the
    stroke's centre; a reference damper restarted at rest where it is armed (y = x) asked for
    k0 (x - y) more, decaying over (c0 + c1) / k0 (about 14 s): on the simulated rig the
    ideal controller's Et on case 1, k=1 was 0.0614 (lockstep, 12 s after 2 s), 0.0099 with
    y where the motion put it. An arm, a set_controller and a set_profile of the same damper
    keep y (and z); one after a source without a damper starts at rest."""
    from mrrig.loop.daemon import Daemon, build_controller, build_reference
    from mrrig.rigio.control import Preparer, parse_request

    config = rig_config(
        tmp_path,
        "unused",
        None,
        reference={"kind": "paper_case", "case": 1, "current_scale": 0.5, "preset": "rig-current"},
    )
    d = Daemon(load_config(config, {"controller": {"name": "reference_current"}}))
    prep = Preparer(d, build_controller, build_reference)

    def apply(text: str) -> None:
        d.requests.apply(prep.prepare(parse_request(text.encode())))

    t = _moved(d.reference, 3.25)  # x = 0.01 m, y far from it
    z, y, _u = d.reference._damper.state
    assert abs(0.01 - y) > 2e-3
    d.t0 = d.now() + d.t0 - t  # the daemon's clock at the motion's end
    d.last_x = 0.01
    profile = '{"cmd": "set_profile", "kind": "paper_case", "case": 4, "current_scale": 0.5}'
    for request in ('{"cmd": "set_controller", "name": "reference_current"}', profile):
        apply(request)
        assert d.reference._damper.state[:2] == (z, y), request
    apply('{"cmd": "arm"}')
    assert d.reference._damper.state[:2] == (z, y)
    assert d.reference._t0 >= t  # the case restarts at the arm
    apply('{"cmd": "disarm"}')
    apply('{"cmd": "set_profile", "kind": "constant"}')
    apply(profile)  # after a source without a damper: at rest at x
    assert d.reference._damper.state[:2] == (0.0, 0.01)
