"""A simulated rig in lockstep: the real `Daemon` and firmware_sim's real `Firmware` exchange
their CAN frames (the DBC's codec, python-can's `virtual` bus) one period at a time on a
simulated clock, each command acting over the period after the frame it answers (an ideal
bus, no stalls). Deterministic and about 10x faster than the rig's time, and it keeps what
only the simulator knows: the true motion and force beside each of the daemon's samples.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_sim.config import load_config as load_sim_config
from firmware_sim.firmware import Firmware
from mrrig.config import load_config
from mrrig.loop.daemon import ACTUATOR_PERIOD_S, Daemon
from mrrig.pycan import can
from mrrig.rigio.canbus.profile import contract_profile
from tests.conftest import REPO, rig_config

_channels = itertools.count()


@dataclass
class LockstepRun:
    samples: np.ndarray  # the daemon's samples (SAMPLE_DTYPE), one per sensor frame
    x_true: np.ndarray  # the actuator's displacement (m) and velocity (m/s) at each frame
    xd_true: np.ndarray
    f_true: np.ndarray  # the damper's force before the load cell's noise (N)
    daemon: Daemon | None = None  # the daemon as the run left it


def lockstep_config(tmp_path: Path, model: Path | None = None, **sections) -> Path:
    """A daemon config for a lockstep replay (`run_lockstep`): a virtual bus, armed at start
    with no settling, and room for this VM's stalls in the frame age (a frame's age is wall
    time, the lockstep's clock simulated: a replay, not a timing test)."""
    loop = {"realtime": False, "arm_on_start": True, "arm_settle_s": 0.0, "max_frame_age_s": 1.0}
    return rig_config(
        tmp_path, "unused", model, bus={"interface": "virtual"}, loop=loop, **sections
    )


def run_lockstep(
    config: Path,
    actuator: tuple[str, float, float],
    seconds: float,
    preroll_s: float = 1.0,
    sim_config: Path = REPO / "configs/sim.toml",
    seed: int = 1,
    arm: bool = False,
    actuator_commands: bool = False,
) -> LockstepRun:
    """`config`: a daemon config (armed at its first frame: arm_on_start, arm_settle_s 0);
    `actuator`: (waveform, amplitude m, frequency Hz) commanded to the firmware directly, which
    runs `preroll_s` before the daemon hears its first frame (the motion ramped in). `arm`:
    the daemon arms at its first frame, as `Daemon.run` with the config's arm_on_start;
    `actuator_commands`: the daemon's ActuatorCommands go out after each frame as its loop
    sends them (on a change, and every ACTUATOR_PERIOD_S): a HIL run's STREAM, HOLD, STOP."""
    daemon = Daemon(load_config(config), keep_batches=True)
    channel = f"lockstep-{next(_channels)}-{time.time_ns()}"
    daemon.bus = can.Bus(interface="virtual", channel=channel)
    rig_end = can.Bus(interface="virtual", channel=channel)
    firmware = Firmware(
        dataclasses.replace(load_sim_config(sim_config), seed=seed), contract_profile(), ()
    )
    firmware.actuator.command(*actuator)
    daemon.controller.reset(1)
    daemon._arm_pending = arm
    period_s = firmware.period_s
    wall0 = time.time()
    preroll = round(preroll_s / period_s)
    truth: list[tuple[float, float, float]] = []
    try:
        for k in range(preroll + round(seconds / period_s)):
            t_sim = k * period_s
            frames = firmware.tick(t_sim)
            for frame in frames:
                firmware.sent(frame, t_sim)
                if k < preroll:
                    continue
                msg = can.Message(
                    arbitration_id=frame.frame_id,
                    is_extended_id=frame.is_extended,
                    dlc=len(frame.data),
                    data=frame.data,
                    timestamp=wall0 + t_sim,
                )
                t_rx = time.perf_counter()
                daemon.t0 = t_rx - t_sim  # the daemon's clock reads the simulated time
                daemon.on_frame(msg, t_rx)
                if actuator_commands and t_sim - daemon._last_actuator_sent >= ACTUATOR_PERIOD_S:
                    daemon._send_actuator()
                if frame.frame_id == firmware.sensors_id:
                    motion = firmware.actuator
                    truth.append((motion.x_m, motion.xd_m_s, firmware.force_n))
                while (answer := rig_end.recv(0)) is not None:
                    firmware.on_frame(
                        answer.arbitration_id, bytes(answer.data), t_sim, answer.is_extended_id
                    )
        daemon._flush_samples()
    finally:
        daemon.bus.shutdown()
        rig_end.shutdown()
    samples = np.concatenate(daemon.batches.handed_over())
    x, xd, f = np.array(truth).T
    return LockstepRun(samples, x, xd, f, daemon)
