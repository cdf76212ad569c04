"""The all-numerical reference with the daemon's own controller path (spec/hil.md, Metrics: "the
same inverse model"): the reference's currents are the ones a daemon sends on the same frames
(an in-process `Daemon` on a python-can virtual bus, its DamperCommands decoded through the
DBC), the loop's slew limit included; so a HIL run and its reference differ only by the rig.
In-process, no rig; a few seconds (the session's trained forward model aside)."""

from __future__ import annotations

import dataclasses
import time

import can
import numpy as np
import pytest

from mrrig.api.hil import daemon_command
from mrrig.config import load_config
from mrrig.hil.reference import run_reference
from mrrig.hil.scenario import load_scenario
from mrrig.loop.daemon import Daemon
from mrrig.rigio.canbus.layout import load_dbc
from tests.conftest import REPO, rig_config

SCENARIO = "configs/hil/quarter-car-laws.toml"  # the quarter-car plan's: 0-1 A
LAW = "groundhook"
DURATION_S = 1.5
FLAGS = dict.fromkeys(("ActuatorEnabled", "LimitTripped", "EStop", "SensorFault"), 0)


def _config(tmp_path, sim_model, channel: str):
    """configs/rig.toml (network inversion, one step ahead, load-cell feedback, 250 A/s slew)
    with the session's forward model, the plan's scenario as long as the reference's (the
    road is drawn for the whole run), and room for this VM's stalls in the frame age (a
    replay, not a timing test)."""
    return rig_config(
        tmp_path,
        channel,
        sim_model,
        hil={"scenario": str(REPO / SCENARIO), "law": LAW, "duration_s": DURATION_S},
        loop={"max_frame_age_s": 1.0},
    )


def _scenario():
    return dataclasses.replace(load_scenario(REPO / SCENARIO, law=LAW), duration_s=DURATION_S)


def test_the_reference_commands_what_the_daemon_sends_on_the_same_frames(tmp_path, sim_model):
    """The reference's frames (its stroke as measured, its damper's force) replayed through a
    daemon running the scenario: every DamperCommand's current is the reference's for that
    frame, within the DBC's 0.1 mA (and the solver's tolerance: the daemon solves ahead); the
    exact inverse the reference had before (`BoucWenInverse`) is not what the daemon sends."""
    channel = f"hilref-{time.monotonic_ns()}"
    config = _config(tmp_path, sim_model, channel)
    reference = run_reference(_scenario(), command=daemon_command(config))
    exact = run_reference(_scenario())
    d = Daemon(load_config(config))
    d.bus = can.Bus(interface="virtual", channel=channel)
    listen = can.Bus(interface="virtual", channel=channel)
    dbc = load_dbc(d.codec.dbc_path)
    command_id = dbc.get_message_by_name(d.profile.command_message).frame_id
    try:
        d.controller.reset(1)
        ok, why, _ = d.supervisor.arm(d.now())
        assert ok, why
        sent = []
        for k in range(len(reference.t_s)):
            values = {"Displacement": reference.stroke_m[k], "Force": reference.force_n[k]}
            d.cycle(values | FLAGS, k % 16, time.perf_counter())
            while (msg := listen.recv(0.0)) is not None:
                if msg.arbitration_id == command_id:
                    sent.append(dbc.decode_message(msg.arbitration_id, msg.data))
    finally:
        d.bus.shutdown()
        listen.shutdown()
    # no fault: the run played out, its last frame answered SAFE (the disarm at its end)
    assert d.supervisor.fault is None and d.hil.last_end == "the scenario is played out"
    assert len(sent) == len(reference.t_s)
    modes = [str(m["Mode"]) for m in sent]
    assert modes == ["ACTIVE"] * (len(sent) - 1) + ["SAFE"]
    daemon_a = np.array([m["CurrentSetpoint"] for m in sent])
    # current[k] is the current over the frame before k: frame k's command is current[k + 1]
    np.testing.assert_allclose(daemon_a[:-1], reference.current_a[1:], rtol=0, atol=2e-4)
    assert np.max(np.abs(daemon_a[:-1] - exact.current_a[1:])) > 0.1
    assert d.counters["commands_slew_limited"] > 0  # the replay met the slew limit


def test_the_reference_s_current_moves_within_the_loop_s_slew_limit(tmp_path, sim_model):
    """Groundhook asks the damper's range within a frame: the exact inverse jumps the current
    by more than the loop lets a model's command move (250 A/s: 0.5 A a frame); with the
    daemon's path no frame moves it further, from its first command (which is free: the first
    after arming)."""
    config = _config(tmp_path, sim_model, "unused")
    step_a = load_config(config).loop.max_current_slew_a_per_s * _scenario().period_s
    exact = np.diff(run_reference(_scenario()).current_a)
    limited = np.diff(run_reference(_scenario(), command=daemon_command(config)).current_a[1:])
    assert np.max(np.abs(exact)) > step_a + 0.1
    assert np.max(np.abs(limited)) == pytest.approx(step_a)
