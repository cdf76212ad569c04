"""One frame of the hybrid loop (spec/hil.md): the measured damper force into the numerical
model, the law's demand out, the model's next stroke through the delay compensation to the
actuator. The daemon calls `HybridStep.step` once per valid sensor frame; the all-numerical
reference calls the same, with the simulator's damper model in place of the rig."""

from __future__ import annotations

from dataclasses import dataclass

from mrrig.hil.compensation import NoCompensation, make_compensator
from mrrig.hil.laws import Demand, Law
from mrrig.hil.scenario import Scenario


@dataclass(frozen=True)
class Frame:
    """What one step gives: the law's demand for the coming frame, the model's stroke for the
    next frame's time (x_c, the commanded stroke of the metrics) and its velocity, the
    setpoint that goes to the actuator with its velocity feedforward, and the delay the
    compensator works with (telemetry)."""

    demand: Demand
    target_m: float
    target_velocity_m_s: float
    setpoint_m: float
    setpoint_velocity_m_s: float
    delay_s: float


class HybridStep:
    """The scenario's substructure, law and compensator, stepped frame by frame."""

    def __init__(self, scenario: Scenario, law: str | None = None, compensate: bool = True):
        self.scenario = scenario
        self.substructure = scenario.substructure()
        self.law = Law(
            law or scenario.law, scenario.laws, self.substructure, scenario.damper.i_max_a
        )
        c = scenario.compensation
        self.compensator = (
            make_compensator(
                c.method,
                c.order,
                scenario.period_s,
                c.initial_delay_s,
                c.max_delay_s,
                self.substructure,
            )
            if compensate
            else NoCompensation(scenario.period_s)
        )

    @property
    def done(self) -> bool:
        """The excitation record is played out."""
        return self.substructure.k >= self.substructure.steps

    def step(self, measured_force_n: float, measured_stroke_m: float) -> Frame:
        """Frame k: the law on the model's state and the measured force, the model advanced
        with that force, the next stroke compensated against the measured one."""
        demand = self.law.demand(measured_force_n)
        sub = self.substructure
        sub.step(measured_force_n)
        target, target_velocity = sub.stroke_m, sub.stroke_velocity_m_s
        setpoint, velocity = self.compensator.update(target, measured_stroke_m)
        return Frame(demand, target, target_velocity, setpoint, velocity, self.compensator.delay_s)
