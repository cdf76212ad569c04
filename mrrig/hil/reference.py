"""The all-numerical reference (spec/hil.md, Metrics): the scenario with the simulator's own damper
model in place of the rig, stepped entirely in numerics, so that every HIL run is judged
against what it should have been.

The damper is firmware_sim's: the modified Bouc-Wen model, preset "rig-current" (the paper's
Table 3 per ampere, 0 to i_max), RK4 sub-steps of `substep_s`. The stroke goes to the damper
exactly as the model computed it (an ideal actuator), so the reference is what a HIL run with
perfect tracking would give.

The law's desired force becomes a current one of two ways. With `DaemonCommand` (what a HIL
run is judged against: `mrrig hil`, a plan's `hil` step), the way the daemon computes a
frame's command: its Kalman estimate of the stroke, its controller (the config's, network
inversion of its forward model by default) on the measured force, the loop's current clamp
and slew limit (`mrrig.loop.slew.loop_command`) and the run's current range (`Demand.current`),
so that the reference and the HIL run differ only by the rig (servo, transport, measurement).
Without it, through the exact inverse of the simulator's own model (`BoucWenInverse`).
"""

from __future__ import annotations

import math
from dataclasses import astuple, dataclass

import numpy as np

from damper.plant import BoucWenDamper, BoucWenParams, bouc_wen_force
from mrrig.hil.laws import LAWS, Demand
from mrrig.hil.playback import StrokePlayback
from mrrig.hil.scenario import Scenario
from mrrig.hil.stepper import HybridStep
from mrrig.hil.substructure import QuarterCar
from mrrig.loop.controllers import Controller
from mrrig.loop.estimation import RealtimeKalman
from mrrig.loop.slew import SlewLimit, loop_command

# firmware_sim's plant preset (firmware_sim/firmware.py, PLANT_PRESET)
SIM_PLANT_PRESET = "rig-current"
_BISECTIONS = 24


class BoucWenInverse:
    """The current that makes the Bouc-Wen damper give a desired force at the end of the next
    step: the lagged command state after the step, u1 = v + (u - v) e^(-eta dt) (eq. 36 with v
    held), is found by bisection on the force of eq. 30 at the next kinematics (z and y as
    they are now), then v from u1; the current is clipped to [0, i_max] (what the damper can
    give)."""

    def __init__(self, params: BoucWenParams, i_max_a: float, period_s: float) -> None:
        self._k = astuple(params)
        self.i_max_a = i_max_a
        self._decay = math.exp(-params.eta * period_s)

    def current_a(self, damper: BoucWenDamper, x1_m: float, v1_m_s: float, force_n: float) -> float:
        z, y, u = damper.state
        k, decay = self._k, self._decay
        lo, hi = u * decay, self.i_max_a + (u - self.i_max_a) * decay
        f_lo = bouc_wen_force(z, y, lo, x1_m, v1_m_s, k)  # eq. 30
        f_hi = bouc_wen_force(z, y, hi, x1_m, v1_m_s, k)
        rising = f_hi >= f_lo
        if (force_n <= f_lo) == rising:
            return 0.0
        if (force_n >= f_hi) == rising:
            return self.i_max_a
        for _ in range(_BISECTIONS):
            mid = 0.5 * (lo + hi)
            if (bouc_wen_force(z, y, mid, x1_m, v1_m_s, k) < force_n) == rising:
                lo = mid
            else:
                hi = mid
        u1 = 0.5 * (lo + hi)
        v = (u1 - u * decay) / (1.0 - decay)
        return min(max(v, 0.0), self.i_max_a)


class DaemonCommand:
    """The daemon's path from a frame's measured stroke and force and the law's demand to the
    current it sends (mrrig/loop/daemon.py, `Daemon.cycle`, armed, one run streaming): the
    Kalman estimate of the stroke, the desired force within `loop.f_range_n` (0 N where the
    law asks a current: `HilDemand`), the controller's `command_one` (with that force as the
    next one too, for a controller that solves one step ahead: a HIL demand is not known
    ahead), `loop_command` (clamp, slew limit), the run's range, then the slew limit told
    what went out and the controller's on-line adaptation (`after_send`). The daemon's
    `prepare_one` work ahead is left out: it changes no result beyond the solver's tolerance.
    `controller`: built from the daemon's config (`mrrig.loop.daemon.build_controller`), the
    rest its `[loop]` and `[estimator]` (`mrrig.api.hil.daemon_command`)."""

    def __init__(
        self,
        controller: Controller,
        *,
        period_s: float,
        i_max_a: float,
        max_current_slew_a_per_s: float,
        f_range_n: tuple[float, float],
        kalman_q: float,
        kalman_r0_m2: float,
    ) -> None:
        self.controller = controller
        self.name = controller.name
        self.i_max_a = i_max_a
        self.f_range_n = f_range_n
        self._kalman = (period_s, kalman_q, kalman_r0_m2)
        self._slew = (max_current_slew_a_per_s, period_s)
        self.reset()

    def reset(self) -> None:
        """A run's start, as arming the daemon: the controller reset, the slew limit free."""
        period_s, q, r0 = self._kalman
        self.kf = RealtimeKalman(period_s, q=q, r0=r0)
        self.slew = SlewLimit(*self._slew)
        self.controller.reset(1)

    def current_a(self, x_meas: float, f_meas: float, demand: Demand, range_a: float) -> float:
        x, xd, xdd = self.kf.update(x_meas)
        lo, hi = self.f_range_n
        f_des = min(max(demand.force_n if demand.force_n is not None else 0.0, lo), hi)
        f_next = f_des if self.controller.wants_next_target else None
        i = self.controller.command_one(x, xd, xdd, f_meas, f_des, f_next)
        if not math.isfinite(i):
            raise FloatingPointError(f"the {self.name} controller's command is not finite")
        i_max = self.i_max_a
        i_a, _ = loop_command(self.slew, self.controller, i, i_max)
        i_a = demand.current(i_a, range_a, i_max)
        self.slew.sent(i_a)
        self.controller.after_send()
        return i_a


@dataclass(frozen=True)
class ReferenceRun:
    """The recorded series of a run (one sample per frame) and the figures of spec/hil.md."""

    scenario: Scenario
    t_s: np.ndarray
    stroke_m: np.ndarray  # the commanded stroke x_c (what the model asked)
    stroke_velocity_m_s: np.ndarray
    force_n: np.ndarray  # the damper's force at each frame
    desired_force_n: np.ndarray  # the law's force for the frame after (nan: a current asked)
    current_a: np.ndarray
    # quarter car: body acceleration, suspension travel, dynamic tyre load
    # building: storey drifts and absolute floor accelerations, one column per storey
    # playback: the damper's force
    outputs: dict[str, np.ndarray]

    def figures(self) -> dict[str, float]:
        """RMS and peak of every output, the stroke and force envelope, the energy the damper
        took from the model (sum F s' dt, > 0 for a passive device)."""
        out: dict[str, float] = {}
        for name, series in self.outputs.items():
            cols = series.reshape(series.shape[0], -1)
            for j in range(cols.shape[1]):
                key = name if cols.shape[1] == 1 else f"{name}_{j + 1}"
                out[f"rms_{key}"] = float(np.sqrt(np.mean(cols[:, j] ** 2)))
                out[f"peak_{key}"] = float(np.max(np.abs(cols[:, j])))
        out["max_abs_stroke_m"] = float(np.max(np.abs(self.stroke_m)))
        out["max_abs_force_n"] = float(np.max(np.abs(self.force_n)))
        out["dissipated_j"] = float(
            np.sum(self.force_n * self.stroke_velocity_m_s) * self.scenario.period_s
        )
        return out


def run_reference(
    scenario: Scenario, law: str | None = None, command: DaemonCommand | None = None
) -> ReferenceRun:
    """The scenario (with `law` in place of its own, if given) all-numerically: the hybrid
    loop's own step (`HybridStep`) with an ideal actuator (the stroke as the model computed it,
    no compensation) and the simulator's damper in place of the rig; the law's force through
    the daemon's controller path (`command`, reset here) or, without one, `BoucWenInverse`."""
    dt = scenario.period_s
    if command is not None:
        command.reset()
    loop = HybridStep(scenario, law, compensate=False)
    sub = loop.substructure
    params = BoucWenParams.preset(SIM_PLANT_PRESET)
    damper = BoucWenDamper(params, scenario.damper.substep_s)
    inverse = BoucWenInverse(params, scenario.damper.i_max_a, dt)
    n = sub.steps
    quarter_car = isinstance(sub, QuarterCar)
    playback = isinstance(sub, StrokePlayback)
    stroke, velocity, force, desired, current = (np.empty(n) for _ in range(5))
    if quarter_car:
        names = ("body_acceleration_m_s2", "suspension_travel_m", "tyre_load_n")
        outputs = {k: np.empty(n) for k in names}
    elif playback:  # the damper's force on the recorded stroke
        outputs = {"force_n": force}
    else:
        outputs = {k: np.empty((n, sub.n)) for k in ("drift_m", "acceleration_m_s2")}
    f = damper.reset(0.0)
    i_a = 0.0
    for k in range(n):
        stroke[k], velocity[k], force[k], current[k] = (
            sub.stroke_m,
            sub.stroke_velocity_m_s,
            f,
            i_a,
        )
        frame = loop.step(f, stroke[k])
        if quarter_car:
            outputs["body_acceleration_m_s2"][k] = sub.body_acceleration_m_s2
            outputs["suspension_travel_m"][k] = stroke[k]
            outputs["tyre_load_n"][k] = sub.tyre_load_n
        elif not playback:
            outputs["drift_m"][k] = sub.drifts_m
            outputs["acceleration_m_s2"][k] = sub.accelerations_m_s2
        x1, v1 = frame.target_m, frame.target_velocity_m_s
        if command is not None:
            i_a = command.current_a(stroke[k], f, frame.demand, scenario.damper.i_max_a)
            desired[k] = math.nan if frame.demand.force_n is None else frame.demand.force_n
        elif frame.demand.current_a is not None:
            i_a, desired[k] = frame.demand.current_a, math.nan
        else:
            i_a = inverse.current_a(damper, x1, v1, frame.demand.force_n)
            desired[k] = frame.demand.force_n
        f = damper.step(x1, v1, i_a, dt)
        if not math.isfinite(f):
            raise FloatingPointError(f"the reference's damper force is not finite at step {k}")
    return ReferenceRun(
        scenario, np.arange(n) * dt, stroke, velocity, force, desired, current, outputs
    )


def envelope_problem(
    figures: dict[str, float], stroke_limit_m: float, force_limit_n: float
) -> str | None:
    """Why the reference's stroke and force envelope does not fit a rig (spec/hil.md: refuse
    before arming what exceeds the rig's limits), or None."""
    stroke, force = figures["max_abs_stroke_m"], figures["max_abs_force_n"]
    if stroke > stroke_limit_m:
        return (
            f"the reference strokes {stroke * 1e3:.1f} mm, beyond the rig's "
            f"{stroke_limit_m * 1e3:g} mm"
        )
    if force > force_limit_n:
        return f"the reference's force reaches {force:.0f} N, beyond the rig's {force_limit_n:g} N"
    return None


@dataclass(frozen=True)
class LawRow:
    law: str
    rms_body_acceleration_m_s2: float
    rms_suspension_travel_m: float
    rms_tyre_load_n: float
    max_abs_stroke_m: float


def law_table(
    scenario: Scenario, laws: tuple[str, ...] = LAWS, command: DaemonCommand | None = None
) -> list[LawRow]:
    """Every law on the scenario's road (quarter car): each law's RMS body acceleration,
    suspension travel and dynamic tyre load, and its peak stroke (does it fit the rig?)."""
    rows = []
    for name in laws:
        fig = run_reference(scenario, name, command).figures()
        rows.append(
            LawRow(
                name,
                fig["rms_body_acceleration_m_s2"],
                fig["rms_suspension_travel_m"],
                fig["rms_tyre_load_n"],
                fig["max_abs_stroke_m"],
            )
        )
    return rows


def percent_change(value: float, against: float) -> float:
    """100 (value - against) / against: negative = better (less) than the passive setting."""
    return 100.0 * (value - against) / against
