"""Whether a force profile is within reach of a semi-active damper (numerics: no I/O).

An MR damper only dissipates: the current sets how much force it gives, never its sign, which
is the sign of the piston velocity (the viscous and yield terms of the modified Bouc-Wen model,
eqs 30-36: F = c1 yd + k1 (x - x0), yd following xd). A desired force of the other sign asks
the damper to put power into the motion (f_des * xd < 0), which no current gives: a profile
that asks for it in a large share of its samples has an Et near 1 however good the controller.

A sample counts as opposed when |f_des| > `F_DEADBAND_N` and |xd| > `V_DEADBAND_M_S` and the
signs differ. The deadbands leave out the reversals, where the damper's hysteresis (eq. 34's z
lags the velocity) and the accumulator's stiffness give a force against the motion for a
moment: the Bouc-Wen reference damper's own force (`BoucWenReference`, reachable by
construction) is opposed in 0.5 % of the samples of a 10 mm, 1 Hz stroke, 2.6 % at 2 Hz; a
sine force on a sine stroke of the same frequency from 0 % to over 90 %, with the phase
between them.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from mrrig.loop.reference import ForceReference

F_DEADBAND_N = 50.0  # the load cell's noise and the static force about rest are below it
V_DEADBAND_M_S = 0.005  # the velocity estimate's noise and the reversals are below it
# before arming: the phase between a reference and the stroke, tried at this many points
PHASES = 8
PREDICT_S = 5.0  # at most this much of a step is evaluated before arming (a Bouc-Wen
# reference: 8 phases of it in about 1 s)


def opposed(f_des: np.ndarray, xd: np.ndarray) -> np.ndarray:
    """Per sample: whether the desired force opposes the motion (beyond the deadbands)."""
    f = np.asarray(f_des, dtype=float)
    v = np.asarray(xd, dtype=float)
    return (f * v < 0) & (np.abs(f) > F_DEADBAND_N) & (np.abs(v) > V_DEADBAND_M_S)


def opposed_share(f_des: np.ndarray, xd: np.ndarray) -> float:
    """The share of the samples whose desired force opposes the motion; NaN without samples
    (a NaN force or velocity counts as not opposed)."""
    f = np.asarray(f_des, dtype=float)
    return float(opposed(f, xd).mean()) if f.size else math.nan


def predicted_shares(
    make_reference: Callable[[], ForceReference],
    amplitude_m: float,
    frequency_hz: float,
    duration_s: float,
    dt_s: float,
) -> np.ndarray:
    """`opposed_share` of a reference on a sine stroke x = A sin(2 pi f t + phi), at `PHASES`
    phases phi: the rig sets the phase between them when it arms, so before arming a step
    only the range is known. The reference is evaluated at each sample as the daemon does
    (time, displacement, velocity), from time 0, over at most `PREDICT_S`; `make_reference`
    gives a new one per phase (a reference damper has a state)."""
    t = np.arange(0.0, min(duration_s, PREDICT_S), dt_s)
    w = 2 * math.pi * frequency_hz
    out = np.empty(PHASES)
    for k in range(PHASES):
        phase = w * t + 2 * math.pi * k / PHASES
        x, xd = amplitude_m * np.sin(phase), amplitude_m * w * np.cos(phase)
        reference = make_reference()
        reference.reset(0.0, float(x[0]) if x.size else 0.0)
        f = np.fromiter(
            (reference.force(*s) for s in zip(t.tolist(), x.tolist(), xd.tolist(), strict=True)),
            float,
            t.size,
        )
        out[k] = opposed_share(f, xd)
    return out
