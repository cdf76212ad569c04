"""The simulator's config (`configs/sim.toml`), parsed once into frozen dataclasses.

The CAN contract's own numbers (periods, the 20 ms watchdog, 5 recovery commands, the 500 ms
actuator timeout) are not configurable: they live in `firmware_sim.firmware` and the DBC.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Literal

from damper.plant_file import load_plant
from firmware_sim.actuator import ServoParams
from mrrig.config import CanSection
from mrrig.resources import resolve
from mrrig.typed_config import ConfigError, load_toml, parse

FaultKind = Literal[
    "drop_frames",
    "corrupt_crc",
    "freeze_counter",
    "sensor_spike",
    "estop",
    "stroke_limit",
    "sensor_fault",
    "silent",
]
FAULT_KINDS: tuple[str, ...] = FaultKind.__args__  # type: ignore[attr-defined]

# CoilCurrent is 16 bits at 0.1 mA in the DBC.
_MAX_CURRENT_A = 6.5535


@dataclass(frozen=True)
class BusConfig:
    """python-can bus (`mrrig.rigio.canbus.open_bus`); the frames are `[can]`'s."""

    interface: str = "remote"
    channel: str = "ws://127.0.0.1:54701/"
    send_timeout_s: float = 0.001

    def check(self) -> None:
        if not self.send_timeout_s > 0.0:
            raise ValueError("send_timeout_s: must be positive")


@dataclass(frozen=True)
class TimingConfig:
    """How the loop meets its absolute deadlines."""

    lead_s: float = 0.0008  # compute the frame this long before its deadline
    spin_s: float = 0.0001  # busy-wait this last part before the deadline
    realtime_priority: int = 0  # SCHED_FIFO priority 1..99; 0 = normal scheduling
    # with a realtime priority: idle CPUs poll rather than halt while it runs (PM QoS)
    poll_idle: bool = True
    time_scale: float = 1.0  # > 1: everything that many times slower (emulated VMs only)

    def check(self) -> None:
        if not 1.0 <= self.time_scale <= 100.0:
            raise ValueError("time_scale: must be in [1, 100]")
        if not 0.0 <= self.spin_s <= self.lead_s < 0.002:
            raise ValueError("lead_s, spin_s: need 0 <= spin_s <= lead_s < 0.002")
        if not 0 <= self.realtime_priority <= 99:
            raise ValueError("realtime_priority: must be in [0, 99]")


@dataclass(frozen=True)
class DamperConfig:
    """The plant (preset rig-current) and the coil driver's limit."""

    current_limit_a: float = 2.0
    substep_s: float = 1e-4

    def check(self) -> None:
        if not 0.0 < self.current_limit_a <= _MAX_CURRENT_A:
            raise ValueError(f"current_limit_a: must be in (0, {_MAX_CURRENT_A}]")
        if not 0.0 < self.substep_s <= 2e-4:
            raise ValueError("substep_s: must be in (0, 2e-4] (the plant is stiff)")


@dataclass(frozen=True)
class PlantConfig:
    """The damper: the preset rig-current (no file), or a plant file (`mrrig identify`: the
    twin of a measured damper). A twin whose command is in V takes `command_per_a` V per A of
    the rig's setpoint (its driver's input for a current: the lab's mapping, an assumption)."""

    file: Path | None = None
    command_per_a: float = 1.0

    def check(self) -> None:
        if not 0.0 < self.command_per_a <= 100.0:
            raise ValueError("command_per_a: must be in (0, 100]")
        if self.file is not None:
            try:
                load_plant(self.file)
            except ValueError as exc:
                raise ValueError(f"file: {exc}") from None


@dataclass(frozen=True)
class SensorConfig:
    """Measurement noise (standard deviations) and the size of an injected spike."""

    displacement_noise_m: float = 2e-6
    force_noise_n: float = 2.0
    current_noise_a: float = 0.002
    spike_displacement_m: float = 0.02
    spike_force_n: float = 5000.0

    def check(self) -> None:
        for name in ("displacement_noise_m", "force_noise_n", "current_noise_a"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name}: must be >= 0")


@dataclass(frozen=True)
class ThermalConfig:
    """First-order damper temperature: heated by the coil's and the damper's dissipated power,
    C dT/dt = P - (T - ambient) / R; with `heating` on, the Bouc-Wen force parameters are
    scaled by temperature (`damper.plant.params_at_temperature`, from `ambient_degc`)."""

    ambient_degc: float = 25.0
    heat_capacity_j_per_k: float = 1500.0  # C
    thermal_resistance_k_per_w: float = 0.6  # R, to ambient (time constant R C)
    coil_resistance_ohm: float = 4.0
    heating: bool = False  # the force depends on the temperature (off: the paper's damper)
    # per kelvin above ambient; -0.003 for all three: the force at a fixed current and motion
    # falls 15 % from 25 to 75 degC
    viscous_per_k: float = -0.003
    yield_per_k: float = -0.003
    stiffness_per_k: float = -0.003

    def check(self) -> None:
        if not (self.heat_capacity_j_per_k > 0.0 and self.thermal_resistance_k_per_w > 0.0):
            raise ValueError(
                "heat_capacity_j_per_k and thermal_resistance_k_per_w: must be positive"
            )
        for name in ("viscous_per_k", "yield_per_k", "stiffness_per_k"):
            if not -0.02 <= getattr(self, name) <= 0.02:
                raise ValueError(f"{name}: must be in [-0.02, 0.02] per K")


@dataclass(frozen=True)
class ServoConfig(ServoParams):
    """`[actuator.servo]`: the servo-hydraulic actuator's nominal parameters
    (`firmware_sim.actuator.ServoParams`, the RTHS benchmark's by default) and the seeded
    spread of the actuator the simulator runs around them. STREAM always goes through it;
    `waveforms` sends SINE, RANDOM, HOLD and STOP through it too (off: the piston is the
    motion generator itself, as before)."""

    waveforms: bool = False
    spread: float = 0.2  # b1, b2 and the transport delay each within +-20 % of nominal
    seed: int = 1  # of the spread: the same seed, the same actuator

    def check(self) -> None:
        super().check()
        if not 0.0 <= self.spread <= 0.5:
            raise ValueError("spread: must be in [0, 0.5]")

    def actual(self) -> ServoParams:
        """The actuator the simulator runs: the nominal parameters with the seeded spread."""
        nominal = ServoParams(**{f.name: getattr(self, f.name) for f in fields(ServoParams)})
        return nominal.with_spread(self.spread, self.seed)


@dataclass(frozen=True)
class ActuatorConfig:
    """The hydraulic actuator: its motion generator and its servo."""

    stroke_m: float = 0.04  # largest |displacement|; commanded amplitudes are clamped to it
    ramp_s: float = 0.5  # every change of amplitude or frequency takes this long
    random_record_s: float = 30.0  # RANDOM repeats after this long (periodic noise record)
    autostart: Literal["STOP", "SINE", "RANDOM"] = "STOP"  # STOP: wait for ActuatorCommand
    autostart_amplitude_m: float = 0.01
    autostart_frequency_hz: float = 2.0
    servo: ServoConfig = field(default_factory=ServoConfig)

    def check(self) -> None:
        if not 0.0 < self.stroke_m <= 0.65535:
            raise ValueError("stroke_m: must be in (0, 0.65535]")
        if not self.ramp_s > 0.0:
            raise ValueError("ramp_s: must be positive")
        if not self.random_record_s >= 1.0:
            raise ValueError("random_record_s: must be >= 1")
        if not 0.0 <= self.autostart_amplitude_m <= self.stroke_m:
            raise ValueError("autostart_amplitude_m: must be in [0, stroke_m]")
        if not self.autostart_frequency_hz >= 0.0:
            raise ValueError("autostart_frequency_hz: must be >= 0")


@dataclass(frozen=True)
class CommandConfig:
    """Budget of bad command frames (bad CRC, repeated counter) before FaultCode 6."""

    bad_frame_budget: int = 5
    bad_frame_window_s: float = 1.0
    # a test instrument, not firmware: ACTIVE commands that reached the bus longer than this
    # after the sensor frame they answer are counted (the daemon's loop.max_frame_age_s), and
    # so are those the firmware applied longer than this after it sent their frame
    stale_answer_age_s: float = 0.01

    def check(self) -> None:
        if self.bad_frame_budget < 0 or not self.bad_frame_window_s > 0.0:
            raise ValueError("bad_frame_budget >= 0 and bad_frame_window_s > 0 required")
        if not self.stale_answer_age_s > 0.0:
            raise ValueError("stale_answer_age_s: must be > 0")


@dataclass(frozen=True)
class FaultSpec:
    """One fault injection: `kind` is active over [start_s, start_s + duration_s).

    duration_s = 0 means one sensor period (a single frame for drop_frames, sensor_spike...).
    Times are seconds since the simulator booted.
    """

    kind: FaultKind
    start_s: float
    duration_s: float = 0.0

    def check(self) -> None:
        if not (self.start_s >= 0.0 and self.duration_s >= 0.0):
            raise ValueError("start_s and duration_s: must be >= 0")

    @classmethod
    def from_cli(cls, text: str) -> FaultSpec:
        """Parse `KIND@START_S[:DURATION_S]`, e.g. `estop@5:2`."""
        kind, sep, when = text.partition("@")
        if not sep or kind not in FAULT_KINDS:
            raise ValueError(
                f"fault {text!r}: want KIND@START_S[:DURATION_S], KIND one of "
                f"{', '.join(FAULT_KINDS)}"
            )
        start, _, duration = when.partition(":")
        try:
            spec = cls(kind, float(start), float(duration) if duration else 0.0)  # type: ignore[arg-type]
        except ValueError:
            raise ValueError(f"fault {text!r}: START_S and DURATION_S must be numbers") from None
        spec.check()
        return spec


@dataclass(frozen=True)
class SimConfig:
    """Everything `firmware_sim` reads from its TOML file."""

    seed: int = 1
    bus: BusConfig = field(default_factory=BusConfig)
    # the rig profile, the same table as the daemon's: a lab's layout on the simulated rig
    can: CanSection = field(default_factory=CanSection)
    timing: TimingConfig = field(default_factory=TimingConfig)
    damper: DamperConfig = field(default_factory=DamperConfig)
    plant: PlantConfig = field(default_factory=PlantConfig)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    thermal: ThermalConfig = field(default_factory=ThermalConfig)
    actuator: ActuatorConfig = field(default_factory=ActuatorConfig)
    commands: CommandConfig = field(default_factory=CommandConfig)
    faults: tuple[FaultSpec, ...] = ()


def load_config(path: str | Path) -> SimConfig:
    """Read and validate a simulator config; raises a one-line `ConfigError`."""
    path = resolve(path)
    return parse(SimConfig, load_toml(path), str(path))


__all__ = [
    "FAULT_KINDS",
    "ActuatorConfig",
    "BusConfig",
    "CommandConfig",
    "ConfigError",
    "DamperConfig",
    "FaultKind",
    "FaultSpec",
    "PlantConfig",
    "SensorConfig",
    "ServoConfig",
    "SimConfig",
    "ThermalConfig",
    "TimingConfig",
    "load_config",
]
