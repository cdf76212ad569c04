"""Closed-loop force tracking against the simulated damper: controller -> plant -> load cell.

Pure numerics: the same loop as the rig daemon (estimate -> controller -> clamp -> apply), but
with the plant in-process and many cases integrated at once (a batch of independent dampers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from damper.plant import BoucWenDamper, BoucWenParams
from mrrig.loop.controllers import ControlInput, Controller


@dataclass
class ClosedLoopResult:
    f_des: np.ndarray  # (B, n) desired force, N
    f_act: np.ndarray  # (B, n) the damper's force, N
    command: np.ndarray  # (B, n) the controller's command (V or A)


def closed_loop(
    controller: Controller,
    params: BoucWenParams,
    dt_s: float,
    x: np.ndarray,
    xd: np.ndarray,
    xdd: np.ndarray,
    f_des: np.ndarray,
    substep_s: float = 1e-4,
    u0: np.ndarray | float = 0.0,
) -> ClosedLoopResult:
    """Track `f_des` (B, n) on dampers moved along `x` (B, n), one command per sample.

    At sample k the controller sees the state and the damper's force f_a(k) (the load cell,
    fed back every sample) and its command is held over [k, k+1]; f_a(k) is compared with
    f_des(k), as in the paper's Table 6. The reference is known ahead: the controller also
    gets f_des(k+1) (`ControlInput.f_des_next`; at the last sample f_des(k)).
    After each command the controller learns from that instant (`after_send`, the
    adaptation), as the rig daemon lets it after the command has gone out.
    The dampers start at rest with the coil state u0 (B,) (command units; the controllers are
    not told it). A reference made by `simulate` starts at rest with u = its first command:
    with that u0, a controller that commands the reference's own voltages tracks it exactly.
    """
    x, xd, xdd, f_des = (np.atleast_2d(np.asarray(a, dtype=float)) for a in (x, xd, xdd, f_des))
    batch, n = f_des.shape
    # one float-state damper per lane: for a handful of lanes that is much faster than a numpy
    # batch (the plant's step is dominated by per-operation overhead)
    plants = [BoucWenDamper(params, substep_s=substep_s) for _ in range(batch)]
    xs, xds = x.tolist(), xd.tolist()
    u0s = np.broadcast_to(np.asarray(u0, dtype=float), (batch,)).tolist()
    f_a = np.array([p.reset(xs[b][0], xds[b][0], u0s[b]) for b, p in enumerate(plants)])
    controller.reset(batch)
    f_act = np.empty((batch, n))
    command = np.empty((batch, n))
    for k in range(n):
        f_act[:, k] = f_a
        s = ControlInput(
            x=x[:, k],
            xd=xd[:, k],
            xdd=xdd[:, k],
            f_meas=f_a,
            f_des=f_des[:, k],
            f_des_next=f_des[:, min(k + 1, n - 1)],
        )
        command[:, k] = controller.command(s)
        controller.after_send()  # the rig daemon's on-line learning, once the command is out
        if k + 1 < n:
            cmd = command[:, k].tolist()
            f_a = np.array(
                [p.step(xs[b][k + 1], xds[b][k + 1], cmd[b], dt_s) for b, p in enumerate(plants)]
            )
    return ClosedLoopResult(f_des=f_des, f_act=f_act, command=command)
