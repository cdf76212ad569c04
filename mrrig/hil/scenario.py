"""A HIL scenario file (configs/hil/*.toml), parsed once into typed, checked objects
(mrrig.typed_config): the substructure and its excitation, the law, the damper's current range
and the delay compensation. Every bad field is a one-line ConfigError naming file and field."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from mrrig.errors import MrrigError
from mrrig.hil.ground import GroundMotion, ground_acceleration_m_s2
from mrrig.hil.laws import VEHICLE_LAWS, LawName, LawParams
from mrrig.hil.playback import StrokePlayback, load_resampled
from mrrig.hil.road import Bump, road_input_m
from mrrig.hil.substructure import BuildingParams, QuarterCar, QuarterCarParams, ShearBuilding
from mrrig.typed_config import ConfigError, load_toml, parse


@dataclass(frozen=True)
class BumpConfig:
    height_m: float
    length_m: float
    at_m: float

    def check(self) -> None:
        if not self.length_m > 0.0:
            raise ValueError(f"length_m: must be positive, got {self.length_m}")


@dataclass(frozen=True)
class RoadConfig:
    iso_class: Literal["A", "B", "C", "D", "E", "F", "G", "H"] = "C"
    speed_m_s: float = 20.0
    seed: int = 1
    bumps: tuple[BumpConfig, ...] = ()

    def check(self) -> None:
        if not self.speed_m_s > 0.0:
            raise ValueError(f"speed_m_s: must be positive, got {self.speed_m_s}")


@dataclass(frozen=True)
class DamperConfig:
    """The damper's command range, and the reference's Bouc-Wen sub-step (firmware_sim's)."""

    i_max_a: float = 2.0
    substep_s: float = 1e-4

    def check(self) -> None:
        if not self.i_max_a > 0.0:
            raise ValueError(f"i_max_a: must be positive, got {self.i_max_a}")
        if not 0.0 < self.substep_s <= 1e-3:
            raise ValueError(f"substep_s: must be in (0, 1e-3] s, got {self.substep_s}")


@dataclass(frozen=True)
class CompensationConfig:
    """Actuator delay compensation (mrrig.hil.compensation): `polynomial` extrapolates the
    setpoint over the delay estimated on line, `adaptive` adapts its lead to the measured
    tracking error, `model` sends the model's own prediction over the estimated delay; `none`
    sends the model's stroke as it is."""

    method: Literal["none", "polynomial", "adaptive", "model"] = "model"
    order: int = 3
    initial_delay_s: float = 0.006
    max_delay_s: float = 0.04

    def check(self) -> None:
        if not 1 <= self.order <= 4:
            raise ValueError(f"order: 1 to 4, got {self.order}")
        if not 0.0 <= self.initial_delay_s <= self.max_delay_s:
            raise ValueError(
                f"initial_delay_s: must be in [0, max_delay_s = {self.max_delay_s}], "
                f"got {self.initial_delay_s}"
            )


# a playback has no model for a law to act on: the damper at a fixed current
PLAYBACK_LAWS = ("passive-soft", "passive-hard")


@dataclass(frozen=True)
class PlaybackConfig:
    """A recorded stroke played by the actuator (`kind = "playback"`; mrrig.hil.playback):
    the stroke CSV (t_s, x_m[, v_m_s]), relative to the scenario file."""

    file: Path | None = None


@dataclass(frozen=True)
class Scenario:
    kind: Literal["quarter-car", "building", "playback"]
    law: LawName = "skyhook"
    duration_s: float = 60.0
    period_s: float = 0.002
    quarter_car: QuarterCarParams = field(default_factory=QuarterCarParams)
    road: RoadConfig = field(default_factory=RoadConfig)
    building: BuildingParams = field(default_factory=BuildingParams)
    ground: GroundMotion = field(default_factory=GroundMotion)
    laws: LawParams = field(default_factory=LawParams)
    damper: DamperConfig = field(default_factory=DamperConfig)
    compensation: CompensationConfig = field(default_factory=CompensationConfig)
    playback: PlaybackConfig = field(default_factory=PlaybackConfig)

    def check(self) -> None:
        if not 0.0 < self.period_s <= 0.01:
            raise ValueError(f"period_s: must be in (0, 0.01] s, got {self.period_s}")
        if not self.period_s <= self.duration_s <= 3600.0:
            raise ValueError(f"duration_s: must be in [period_s, 3600] s, got {self.duration_s}")
        if self.kind == "building" and self.law in VEHICLE_LAWS:
            raise ValueError(f"law: {self.law!r} needs a quarter car (a body and a wheel)")
        if self.kind == "playback":
            self._check_playback()
            return
        outputs = 3 if self.kind == "quarter-car" else 2 * len(self.building.masses_kg)
        weights = self.laws.lqr_output_weights
        if weights and len(weights) != outputs:
            raise ValueError(
                f"laws.lqr_output_weights: {outputs} weights for this {self.kind}, "
                f"got {len(weights)}"
            )

    def _check_playback(self) -> None:
        if self.playback.file is None:
            raise ValueError("playback.file: a playback needs its stroke CSV (t_s, x_m[, v_m_s])")
        if self.law not in PLAYBACK_LAWS:
            raise ValueError(
                f"law: {self.law!r} needs a numerical model; a playback takes "
                f"{' or '.join(PLAYBACK_LAWS)} (the damper at 0 A or damper.i_max_a)"
            )
        record = self.stroke()
        if self.duration_s > record.duration_s + 1e-9:
            raise ValueError(
                f"duration_s: {self.duration_s:g} s is longer than the record "
                f"({record.duration_s:g} s of {self.playback.file})"
            )

    def stroke(self):
        """A playback's stroke file resampled to `period_s` (read once; `mrrig.hil.playback`)."""
        return load_resampled(str(self.playback.file), self.period_s)

    def played_stroke(self):
        """What a playback plays of its record: `duration_s` of it (frames 0..steps)."""
        return self.stroke().head(self.steps + 1)

    @property
    def steps(self) -> int:
        return max(1, round(self.duration_s / self.period_s))

    def substructure(self) -> QuarterCar | ShearBuilding | StrokePlayback:
        """A fresh substructure with its seeded excitation record (a playback: its stroke)."""
        if self.kind == "playback":
            return StrokePlayback(self.played_stroke())
        if self.kind == "quarter-car":
            r = self.road
            bumps = tuple(Bump(b.height_m, b.length_m, b.at_m) for b in r.bumps)
            road = road_input_m(
                r.iso_class, r.speed_m_s, self.duration_s, self.period_s, r.seed, bumps
            )
            return QuarterCar(self.quarter_car, road, self.period_s)
        ground = ground_acceleration_m_s2(self.ground, self.duration_s, self.period_s)
        return ShearBuilding(self.building, np.asarray(ground), self.period_s)


def load_scenario(path: str | Path, law: str | None = None) -> Scenario:
    """The scenario of a TOML file; `law` replaces the file's law (the plan's law table).
    A stroke CSV (`*.csv`) is a playback of it; a playback's law is passive-soft and its
    duration its record's unless the file (or `law`) sets them."""
    if Path(path).suffix.lower() == ".csv":
        data: dict = {"kind": "playback", "playback": {"file": str(path)}}
    else:
        data = load_toml(path)
    if law is not None:
        data = {**data, "law": law}
    if data.get("kind") == "playback" and "law" not in data:
        data = {**data, "law": PLAYBACK_LAWS[0]}
    if data.get("kind") == "playback" and "duration_s" not in data:
        where = str(path)
        base = parse(PlaybackConfig, data.get("playback", {}), where, "playback")
        period = data.get("period_s", Scenario.period_s)
        ok_period = isinstance(period, int | float) and not isinstance(period, bool) and period > 0
        if base.file is not None and ok_period:  # else the full parse names what is wrong
            try:
                record = load_resampled(str(base.file), float(period))
            except MrrigError as exc:  # a stroke CSV given as the scenario names itself
                text = str(exc)
                raise ConfigError(text if text.startswith(where) else f"{where}: {text}") from None
            data = {**data, "duration_s": record.duration_s}
    return parse(Scenario, data, str(path))
