"""Issue 40, finding 5: models that only look right (mrrig/loop/model_plausibility.py,
mrrig/loop/slew.py).

A random 78-unit GRU had the right format, names and units and was accepted; on the rig it
stepped the current 0 to 2 A between most frames. Meta fields far outside a physical range
(a coil lag of 1e-12 s or 1e6 s, a continuity of 1e300, a twin with eta 1e9 or an offset of
1e300 N) were accepted too. Each is refused on load in one line naming the file, the field
and the value; the random GRU by the closed-loop self-check (the daemon's start, and
`set_model`); a model the daemon runs anyway moves the coil no faster than the loop's slew
limit. The trained network passes, and its tracking is untouched by the limit."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from damper.plant import BoucWenDamper, BoucWenParams
from damper.plant_file import Plant, save_plant
from mrrig.config import load_config
from mrrig.loop.build import build_controller
from mrrig.loop.controllers import ControllerSettings, make_controller
from mrrig.loop.gru import GRUModel
from mrrig.loop.mlp import ModelError
from mrrig.loop.model_plausibility import MAX_CHATTER, SELF_CHECK_FRAMES, self_check
from mrrig.loop.slew import SlewLimit
from mrrig.loop.twin_model import SUBSTEP_S, load_forward_model
from mrrig.typed_config import ConfigError
from tests.conftest import rig_config
from tests.rig_harness import ScriptedRig

DT_S = 0.002
I_MAX_A = 2.0  # configs/rig.toml's loop.i_max_a
CHANNEL = "ws://127.0.0.1:1/"


def random_gru(seed: int = 1, hidden: int = 78) -> GRUModel:
    """A GRU of torch's initial weights (uniform in +-1/sqrt(H)), never trained: right format,
    names, units and meta (a lagged current, the paper's coil lag)."""
    rng = np.random.default_rng(seed)
    k = 1.0 / np.sqrt(hidden)

    def w(*shape: int) -> list:
        return rng.uniform(-k, k, shape).tolist()

    H = hidden
    return GRUModel(
        ["x", "xd", "xdd", "current"],
        ["m", "m/s", "m/s^2", "A"],
        "force",
        "N",
        [0.0, 0.0, 0.0, 1.0],
        [0.01, 0.3, 10.0, 0.6],
        0.0,
        1000.0,
        w(3 * H, 4),
        w(3 * H, H),
        w(3 * H),
        w(3 * H),
        w(H),
        0.0,
        w(H),
        0.0,
        meta={"kind": "gru", "current_input": "lagged", "lag_tau_s": 1 / 190, "command_unit": "A"},
    )


def _build(tmp_path: Path, model: Path):
    return build_controller(load_config(rig_config(tmp_path, CHANNEL, model)))


def _one_line(err: pytest.ExceptionInfo, *parts: str) -> str:
    text = str(err.value)
    assert "\n" not in text, text
    for part in parts:
        assert part in text, text
    return text


@pytest.mark.parametrize("seed", [1, 5])  # 5: a damper's force sign, chatters all the same
def test_a_random_gru_is_refused_by_the_self_check(tmp_path, seed):
    path = tmp_path / "random-gru.json"
    random_gru(seed).save(path)
    load_forward_model(path)  # it reads as a model: names, units, sizes and meta are fine
    with pytest.raises(ModelError) as err:
        _build(tmp_path, path)
    print(err.value)
    _one_line(err, "random-gru.json: self-check", "not a model of a damper")


def test_the_trained_network_passes_the_self_check_with_room(sim_model, tmp_path):
    ctrl = _build(tmp_path, sim_model)  # the daemon's start, as configs/rig.toml has it
    model = load_forward_model(sim_model)
    spare = _build(tmp_path, sim_model)
    result = self_check(spare, model, sim_model, DT_S, I_MAX_A, 0.045)
    print(result)
    assert ctrl.name == "network_inversion"
    assert result.chatter_own < MAX_CHATTER / 5 and result.chatter_reference < MAX_CHATTER / 5
    assert result.tracking_error < 0.1 and result.damping_share > 0.95


def _edited(tmp_path: Path, source: Path, name: str, edit) -> Path:
    doc = json.loads(source.read_text())
    edit(doc)
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


def _meta(**fields):
    return lambda doc: doc["meta"].update(fields)


def _envelope_hi_xd(value: float):
    return lambda doc: doc["meta"]["envelope"]["hi"].__setitem__(1, value)


@pytest.mark.parametrize(
    ("edit", "field", "value"),
    [
        (_meta(lag_tau_s=1e-12), "meta.lag_tau_s", "1e-12"),
        (_meta(lag_tau_s=1e6), "meta.lag_tau_s", "1000000.0"),
        (_meta(online_continuity=1e300), "meta.online_continuity", "1e+300"),
        (_meta(sample_period_s=1e3), "meta.sample_period_s", "1000.0"),
        (_meta(i_max_a=1e9), "meta.i_max_a", "1000000000.0"),
        (_envelope_hi_xd(1e300), "meta.envelope.hi[1] (xd)", "1e+300"),
        (lambda d: d.update(out_mean=1e200), "out_mean", "1e+200"),
        (lambda d: d["in_mean"].__setitem__(2, -1e30), "in_mean[2]", "-1e+30"),
    ],
    ids=[
        "tau-tiny",
        "tau-huge",
        "continuity",
        "period",
        "i-max",
        "envelope",
        "out-mean",
        "in-mean",
    ],
)
def test_a_network_with_absurd_meta_is_refused_naming_file_field_and_value(
    sim_model, tmp_path, edit, field, value
):
    path = _edited(tmp_path, sim_model, "edited.json", edit)
    with pytest.raises(ModelError) as err:
        load_forward_model(path)
    _one_line(err, "edited.json", f"{field}: expected a number in [", f"got {value}")


@pytest.mark.parametrize(
    ("edit", "field", "value"),
    [
        (_meta(lag_tau_s=1e-12), "meta.lag_tau_s", "1e-12"),
        (_meta(online_continuity=1e300), "meta.online_continuity", "1e+300"),
        (lambda d: d.update(out_std=1e-300), "out_std", "1e-300"),
        (lambda d: d.update(W_hh=[[0.0] * 300] * 900, hidden=300), "hidden", "300"),
    ],
    ids=["tau", "continuity", "out-std", "hidden"],
)
def test_a_gru_with_absurd_meta_or_size_is_refused(tmp_path, edit, field, value):
    source = tmp_path / "gru.json"
    random_gru().save(source)
    doc = json.loads(source.read_text())
    if field == "hidden":  # every array of a 300-unit GRU
        H = 300
        doc.update(
            W_ih=[[0.0] * 4] * (3 * H),
            b_ih=[0.0] * (3 * H),
            b_hh=[0.0] * (3 * H),
            W_out=[0.0] * H,
            V_out=[0.0] * H,
        )
    source.write_text(json.dumps(doc))
    path = _edited(tmp_path, source, "edited-gru.json", edit)
    with pytest.raises(ModelError) as err:
        load_forward_model(path)
    _one_line(err, "edited-gru.json", f"{field}: ", str(value))


TWIN = Plant(BoucWenParams.preset("paper-volt"), offset_n=12.5, command_unit="A")


@pytest.mark.parametrize(
    ("plant", "field", "value"),
    [
        (replace(TWIN, params=replace(TWIN.params, eta=1e9)), "params.eta", "1000000000.0"),
        (replace(TWIN, params=replace(TWIN.params, eta=1e-3)), "params.eta", "0.001"),
        (replace(TWIN, offset_n=1e300), "offset_n", "1e+300"),
        (replace(TWIN, params=replace(TWIN.params, beta=1e200)), "params.beta", "1e+200"),
        (replace(TWIN, params=replace(TWIN.params, n=50.0)), "params.n", "50.0"),
    ],
    ids=["eta-huge", "eta-tiny", "offset", "beta", "n"],
)
def test_a_twin_with_absurd_parameters_is_refused(tmp_path, plant, field, value):
    path = tmp_path / "twin.json"
    save_plant(plant, path)
    with pytest.raises(ModelError) as err:
        load_forward_model(path)
    _one_line(err, "twin.json", f"{field}: expected a number in [", f"got {value}")


def test_the_shipped_twin_passes_the_self_check(tmp_path):
    path = tmp_path / "twin.json"
    save_plant(TWIN, path)
    assert _build(tmp_path, path).name == "network_inversion"


def test_the_slew_limit_bounds_a_forced_random_gru_and_it_carries_what_was_sent():
    """A random GRU run anyway (no check), on the reference damper: it steps the command by
    up to the whole range between frames; through the loop's limit no step is over one
    period's slew, and the GRU's state carries the commands the coil got."""
    ctrl = make_controller(
        "network_inversion",
        ControllerSettings(I_MAX_A, dt_s=DT_S, model=random_gru(), ahead=True, feedback_tau_s=0.0),
    )
    slew = SlewLimit(250.0, DT_S)
    n = SELF_CHECK_FRAMES
    t = np.arange(n + 1) * DT_S
    w = 2 * np.pi * 2.0
    x, xd, xdd = 0.01 * np.sin(w * t), 0.01 * w * np.cos(w * t), -0.01 * w * w * np.sin(w * t)
    # the desired force: the reference damper's own, with a smooth current
    damper = BoucWenDamper(BoucWenParams.preset("rig-current"), SUBSTEP_S)
    want = [damper.reset(x[0], xd[0], 0.0)]
    want += [damper.step(x[k], xd[k], 0.9 + 0.7 * np.sin(8 * t[k]), DT_S) for k in range(1, n + 1)]
    asked, sent = [], []
    f = damper.reset(x[0], xd[0], 0.0)
    for k in range(n):
        if k:
            f = damper.step(x[k], xd[k], sent[-1], DT_S)
        i = ctrl.command_one(x[k], xd[k], xdd[k], f, want[k], want[k + 1])
        out = slew.limit(i)
        if out != i:
            ctrl.command_sent(out)
        slew.sent(out)
        asked.append(i)
        sent.append(out)
        assert ctrl.lanes[0].command == out  # held until the next frame, as the coil has it
    assert np.max(np.abs(np.diff(asked))) > 1.5  # it jumps rail to rail when let
    assert np.max(np.abs(np.diff(sent))) <= 250.0 * DT_S + 1e-12


def test_the_daemon_slew_limits_a_models_command(sim_model, tmp_path):
    """The daemon's loop: after the first command since arming, each command of network
    inversion at most loop.max_current_slew_a_per_s * period_s from the last one sent, and
    counted."""

    def config(channel: str) -> Path:
        return rig_config(
            tmp_path,
            channel,
            sim_model,
            bus={"interface": "virtual"},
            loop={
                "realtime": False,
                "arm_on_start": True,
                "arm_settle_s": 0.0,
                "timeout_periods": 50,
                "max_frame_age_s": 0.1,
                "max_current_slew_a_per_s": 20.0,
            },
            reference={"kind": "constant", "offset_n": 1500.0},
        )

    with ScriptedRig(tmp_path, config=config) as rig:
        commands = [rig.exchange(x=0.001 * k, force=0.0) for k in range(30)]
        limited = rig.daemon.counters["commands_slew_limited"]
    currents = [c["CurrentSetpoint"] for c in commands if c["Mode"] == 1]
    steps = np.abs(np.diff(currents))
    print(f"currents {currents[:12]}, {limited} limited")
    assert len(currents) >= 20 and limited >= 5
    assert np.max(steps) <= 20.0 * DT_S + 1e-3  # the DBC's resolution
    assert currents[-1] != currents[0]  # it does move, at the limit


@pytest.mark.parametrize("slew", [0.0, -5.0, 1e7])
def test_a_slew_limit_out_of_its_range_is_a_config_error(tmp_path, slew):
    path = rig_config(tmp_path, CHANNEL, None, loop={"max_current_slew_a_per_s": slew})
    with pytest.raises(ConfigError) as err:
        load_config(path)
    _one_line(err, "loop.max_current_slew_a_per_s: must be in [1, 1e+06] A/s", f"got {slew!r}")


def test_set_model_refuses_an_implausible_model_and_keeps_the_one_it_has(tmp_path, sim_model):
    """`set_model` reads the file under the daemon's limits and builds the controller as the
    start does: the random GRU and an absurd lag are refused in one line, the model kept."""
    from tests.test_hostile_input import _disarm
    from tests.test_model_requests import _rig, _variant

    models = tmp_path / "models"
    models.mkdir()
    gru = models / "random-gru.json"
    random_gru().save(gru)
    lag = _variant(sim_model, models / "lag.json", meta_lag_tau_s=1e-12)
    with _rig(tmp_path, sim_model, name="network_inversion") as rig:
        _disarm(rig)
        for path, part in (
            (gru, "self-check"),
            (lag, "meta.lag_tau_s: expected a number in [1e-05, 1] s, got 1e-12"),
        ):
            reply = rig.request({"cmd": "set_model", "path": str(path)})
            assert reply["ok"] is False, reply
            assert reply["error"].startswith(f"{path}: ") and part in reply["error"], reply
            assert "\n" not in reply["error"]
        assert rig.daemon.cfg.controller.model == models / "start.json"
