"""Issue 42, item 3: the continuous-state gains (G, B of eq. 39) and Heaviside's on-current
(eq. 37) are settable: in the config, in `set_controller`, and so in a plan's step."""

from __future__ import annotations

import numpy as np
import pytest

from mrrig.config import load_config
from mrrig.loop.controllers import ControlInput, ControllerSettings, make_controller
from mrrig.typed_config import ConfigError
from tests.conftest import rig_config
from tests.rig_harness import ScriptedRig


def _input(f_des: float, f_meas: float) -> ControlInput:
    z = np.zeros(1)
    return ControlInput(z, z, z, np.array([f_meas]), np.array([f_des]))


def test_continuous_state_uses_its_gain_and_b_and_heaviside_its_on_current():
    cs = make_controller("continuous_state", ControllerSettings(2.0, gain=0.004, b=0.5))
    cs.reset(1)
    # eq. 39: clip(G (f_d - B f_a) sgn(f_a), 0, i_max) = 0.004 (300 - 0.5 * 200) = 0.8 A
    assert cs.command(_input(300.0, 200.0))[0] == pytest.approx(0.8)
    hv = make_controller("heaviside", ControllerSettings(2.0, on_current_a=1.25))
    hv.reset(1)
    assert hv.command(_input(300.0, 200.0))[0] == 1.25  # eq. 37: (f_d - f_a) f_a > 0
    assert hv.command(_input(100.0, 200.0))[0] == 0.0
    with pytest.raises(ValueError, match=r"on_current_a: 2.5 A is outside \(0, 2\] A"):
        make_controller("heaviside", ControllerSettings(2.0, on_current_a=2.5))


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ({"name": "continuous_state", "gain": -1.0}, "controller.gain: -1.0 must be in (0, 1000]"),
        ({"name": "heaviside", "on_current_a": 9.0}, "controller.on_current_a: 9.0 must be in"),
    ],
)
def test_a_bad_gain_in_the_config_is_one_line_naming_it(tmp_path, section, message):
    path = rig_config(tmp_path, "ws://127.0.0.1:1/", None, controller=section)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_set_controller_takes_the_gains_and_replies_them(tmp_path):
    overrides = {"controller": {"name": "constant", "current_a": 0.5}}
    with ScriptedRig(tmp_path, overrides=overrides) as rig:
        rig.exchange()
        assert rig.request({"cmd": "disarm"})["ok"]
        reply = rig.request({"cmd": "set_controller", "name": "continuous_state",
                             "gain": 0.01, "b": 0.9})  # fmt: skip
        assert reply["ok"] and reply["settings"] == {"gain": 0.01, "b": 0.9}, reply
        reply = rig.request({"cmd": "set_controller", "name": "heaviside", "on_current_a": 1.5})
        assert reply["ok"] and reply["settings"] == {"on_current_a": 1.5}, reply
        reply = rig.request({"cmd": "set_controller", "name": "heaviside", "on_current_a": 4.0})
        assert not reply["ok"] and "on_current_a" in reply["error"], reply
