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
from tests.lockstep_rig import run_lockstep

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
    config = rig_config(
        tmp_path,
        "unused",
        None,
        bus={"interface": "virtual"},
        loop={"realtime": False, "arm_on_start": True, "arm_settle_s": 0.0},
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
