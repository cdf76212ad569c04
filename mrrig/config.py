"""The rig daemon's configuration: TOML parsed once into typed, validated objects.

A relative path (the file's own and those in it) is taken from the working directory, else
beside the config file, else from the shipped configs (`mrrig.resources`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from mrrig.loop.adaptation import AdaptationSettings
from mrrig.loop.controllers import CONTROLLERS
from mrrig.loop.detectors import DetectorSettings
from mrrig.resources import resolve
from mrrig.typed_config import ConfigError, load_toml, parse

__all__ = ["ConfigError", "DaemonConfig", "load_config", "reference_from_table"]

# sane bounds of a damper test rig, well inside the DBC's ranges (+-8.3 m, +-83 kN)
X_RANGE_LIMIT_M = 0.5
F_RANGE_LIMIT_N = 80000.0
ACTUATOR_AMPLITUDE_MAX_M = 0.04  # [actuator] and set_profile: what a rig profile must carry
ACTUATOR_FREQUENCY_MAX_HZ = 20.0
# loop.max_current_slew_a_per_s: slower is no control; the most, 2000 A a frame at 500 Hz
MIN_SLEW_A_PER_S, MAX_SLEW_A_PER_S = 1.0, 1e6
# every setting that scales a wait is bounded at load: a sensor timeout of 1e8 periods made the
# daemon deaf to a stop once the frames stopped
MAX_SENSOR_TIMEOUT_S = 1.0
MAX_ARM_SETTLE_S = 60.0


@dataclass(frozen=True)
class RigSection:
    name: str = "sim"
    # the run's identity (recording, catalog): the damper under test, who runs it (default:
    # the local user), free-text tags
    specimen: str | None = None
    operator: str | None = None
    tags: tuple[str, ...] = ()

    def check(self) -> None:
        if not self.name or not all(c.isalnum() or c in "-_" for c in self.name):
            raise ValueError("name: use letters, digits, '-' and '_' only (it is a Zenoh key)")


@dataclass(frozen=True)
class BusSection:
    interface: str
    channel: str
    options: dict[str, Any] = field(default_factory=dict)  # other can.Bus keywords
    send_timeout_s: float = 0.001

    def check(self) -> None:
        if "multicast" in self.interface:
            # traffic stays on this machine (127.0.0.1, the kernel's CAN, in-process)
            raise ValueError(
                f"interface: {self.interface} multicasts off this machine; not allowed"
            )
        if not 0 < self.send_timeout_s <= 0.002:
            raise ValueError("send_timeout_s: must be in (0, 0.002] s (one sensor period)")
        if self.options.get("receive_own_messages"):
            # the daemon takes a command it did not send for a second daemon on the rig
            raise ValueError(
                "options.receive_own_messages: the daemon must not receive its own frames"
            )


@dataclass(frozen=True)
class CanSection:
    """`[can]` of the daemon's and the simulator's configs: the rig profile
    (mrrig/rigio/canbus/profile.py), the lab's DBC (found beside the config file) and
    `signals`, role = "MESSAGE.SIGNAL" or "absent". Without `dbc`: the CAN contract's
    configs/mrrig.dbc, whose roles `signals` may remap."""

    dbc: Path | None = None
    signals: dict[str, str] = field(default_factory=dict)

    def check(self) -> None:
        for role, text in self.signals.items():
            if not isinstance(text, str):
                raise ValueError(f'signals.{role}: expected "MESSAGE.SIGNAL" or "absent"')


NUMERICS = ("compiled", "python")


@dataclass(frozen=True)
class LoopSection:
    period_s: float = 0.002  # the firmware's RigSensors period
    i_max_a: float = 2.0  # commands are clamped to [0, i_max_a]
    # a model's command within this slew of the last one sent (mrrig/loop/slew.py; 1e6: no
    # limit in effect):
    # 0 to 2 A in 4 frames at 500 Hz, faster than the coil follows (tau about 5 ms)
    max_current_slew_a_per_s: float = 250.0
    timeout_periods: int = 3  # no sensor frame for this many periods -> FAULT + SAFE
    bad_frame_budget: int = 3  # bad CRC / repeated counter frames tolerated per window
    lost_frame_budget: int = 5  # lost frames (counter jumps) tolerated per window
    budget_window_s: float = 1.0
    x_range_m: tuple[float, float] = (-0.045, 0.045)
    f_range_n: tuple[float, float] = (-6000.0, 6000.0)
    realtime: bool = True  # SCHED_FIFO where permitted
    cpu: int | None = None  # pin the loop to this CPU where permitted
    # with realtime: idle CPUs poll rather than halt while the loop runs (PM QoS wake-up
    # latency 0 us): a halted CPU of a virtual machine can wake tens of ms late
    poll_idle: bool = True
    arm_on_start: bool = False
    arm_settle_s: float = 1.0  # arm_on_start arms after this long of valid sensor frames
    duration_s: float | None = None  # stop by itself after this long (tests, demo)
    telemetry_batch: int = 10  # samples per hand-off to the telemetry process
    # a sensor frame older than this when answered (from its receive timestamp at the bus)
    # was held up by a stall: answered SAFE, and a fault. Absent: one period (a real bus)
    max_frame_age_s: float | None = None
    # the frame's numerics: "compiled" (numba: mrrig/loop/compiled.py; the Python path where
    # numba is missing) or "python" (the reference they are tested equal to)
    numerics: str = "compiled"
    # the controller's work per frame the daemon's start-up check allows (mrrig.loop.model_fit
    # `check_cost`): the spec's 300 us on the rig's machine; a software-emulated machine (CI's
    # SocketCAN VM) runs the same work several times slower
    work_budget_us: float = 300.0

    @property
    def frame_age_limit_s(self) -> float:
        return self.period_s if self.max_frame_age_s is None else self.max_frame_age_s

    def check(self) -> None:
        if not 0.0005 <= self.period_s <= 0.1:
            raise ValueError("period_s: must be in [0.0005, 0.1] s")
        if not 10.0 <= self.work_budget_us <= self.period_s * 1e6:
            raise ValueError(
                f"work_budget_us: must be in [10, {self.period_s * 1e6:g}] us (at most one"
                f" period), got {self.work_budget_us!r}"
            )
        if not 0 < self.i_max_a <= 5.0:
            raise ValueError("i_max_a: must be in (0, 5] A")
        if not MIN_SLEW_A_PER_S <= self.max_current_slew_a_per_s <= MAX_SLEW_A_PER_S:
            raise ValueError(
                f"max_current_slew_a_per_s: must be in [{MIN_SLEW_A_PER_S:g}, "
                f"{MAX_SLEW_A_PER_S:g}] A/s ({MAX_SLEW_A_PER_S:g}: no limit in effect), got "
                f"{self.max_current_slew_a_per_s!r}"
            )
        if self.timeout_periods < 1:
            raise ValueError("timeout_periods: must be at least 1")
        if self.numerics not in NUMERICS:
            raise ValueError(f"numerics: one of {', '.join(NUMERICS)}, got {self.numerics!r}")
        if self.timeout_periods * self.period_s > MAX_SENSOR_TIMEOUT_S:
            raise ValueError(
                f"timeout_periods: {self.timeout_periods} periods of {self.period_s:g} s is a "
                f"sensor timeout of {self.timeout_periods * self.period_s:g} s (at most "
                f"{MAX_SENSOR_TIMEOUT_S:g} s: a rig without frames for longer is not supervised)"
            )
        if self.bad_frame_budget < 0 or self.lost_frame_budget < 0:
            raise ValueError("bad_frame_budget, lost_frame_budget: must be >= 0")
        if not 0 < self.budget_window_s <= 60:
            raise ValueError("budget_window_s: must be in (0, 60] s")
        if self.x_range_m[0] >= self.x_range_m[1]:
            raise ValueError("x_range_m: lower bound must be below the upper bound")
        if not (-X_RANGE_LIMIT_M <= self.x_range_m[0] and self.x_range_m[1] <= X_RANGE_LIMIT_M):
            raise ValueError(
                f"x_range_m: must lie in [-{X_RANGE_LIMIT_M:g}, {X_RANGE_LIMIT_M:g}] m"
            )
        if self.f_range_n[0] >= self.f_range_n[1]:
            raise ValueError("f_range_n: lower bound must be below the upper bound")
        if not (-F_RANGE_LIMIT_N <= self.f_range_n[0] and self.f_range_n[1] <= F_RANGE_LIMIT_N):
            raise ValueError(
                f"f_range_n: must lie in [-{F_RANGE_LIMIT_N:g}, {F_RANGE_LIMIT_N:g}] N"
            )
        if not 0 <= self.arm_settle_s <= MAX_ARM_SETTLE_S:
            raise ValueError(f"arm_settle_s: must be in [0, {MAX_ARM_SETTLE_S:g}] s")
        if self.max_frame_age_s is not None and not 0 < self.max_frame_age_s <= 1.0:
            raise ValueError("max_frame_age_s: must be in (0, 1] s")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError("duration_s: must be positive")
        if not 1 <= self.telemetry_batch <= 40:
            raise ValueError("telemetry_batch: must be in [1, 40]")


@dataclass(frozen=True)
class EstimatorSection:
    q: float = 1.0  # Kalman process noise (white jerk), (m/s^2)^2 per s... see estimation.py
    r0_m2: float = 4e-10  # Kalman measurement noise at rest, m^2 (eq. 24)

    def check(self) -> None:
        if not (self.q > 0 and self.r0_m2 > 0):
            raise ValueError("q, r0_m2: must be positive")


@dataclass(frozen=True)
class ControllerSection:
    name: str = "network_inversion"  # a controller of the registry (controllers.CONTROLLERS)
    model: Path | None = None  # the forward model (network inversion) or the inverse MLP / RNN
    method: Literal["exact", "gradient", "flow"] = "exact"
    # network inversion for the instant the command first acts on (the next desired force at
    # the state one period ahead, the coil lag inverted for a model of the lagged current);
    # false: for the present instant
    ahead: bool = True
    # load-cell feedback correction (network inversion): on by default; its residual's time
    # constant (0, the default: the last residual as it is; a low-pass filters the load
    # cell's noise but lags: `mrrig bench paper` and `mrrig demo` measured both)
    feedback: bool = True
    feedback_tau_s: float = 0.0
    # the exact solve's weight toward the previous command; absent: the model's own
    # (`online_continuity`, chosen by `mrrig train` on its training rows), else 0 (the root)
    continuity: float | None = None
    current_a: float = 0.0  # for the constant controller
    gain: float = 0.021  # continuous_state's G (A/N, eq. 39)
    b: float = 1.0  # continuous_state's B (eq. 39)
    on_current_a: float | None = None  # heaviside's current when on (eq. 37); absent: i_max_a

    def check(self) -> None:
        for name in ("gain", "b"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 < value <= 1e3):
                raise ValueError(f"{name}: {value!r} must be in (0, 1000]")
        on = self.on_current_a
        if on is not None and not (math.isfinite(on) and 0 < on <= 5.0):
            raise ValueError(f"on_current_a: {on!r} must be in (0, 5] A")
        if self.name not in CONTROLLERS:
            raise ValueError(
                f"name: unknown controller {self.name!r} (known: {', '.join(CONTROLLERS)})"
            )
        if CONTROLLERS[self.name].needs_model and self.model is None:
            raise ValueError(f"model: controller {self.name} needs a model file")
        if not 0 <= self.feedback_tau_s <= 10:
            raise ValueError("feedback_tau_s: must be in [0, 10] s")
        if self.continuity is not None and not self.continuity >= 0:
            raise ValueError("continuity: must be >= 0")


@dataclass(frozen=True)
class AdaptationSection(AdaptationSettings):
    """On-line adaptation of network inversion's model force (mrrig/loop/adaptation.py): a gain and
    an offset estimated from the load cell after each command, frozen while not armed."""

    enabled: bool = False

    def settings(self) -> AdaptationSettings | None:
        if not self.enabled:
            return None
        fields = {k: getattr(self, k) for k in AdaptationSettings.__dataclass_fields__}
        return AdaptationSettings(**fields)


@dataclass(frozen=True)
class ReferenceSection:
    kind: Literal["constant", "sine", "noise", "csv", "bouc_wen", "paper_case", "zenoh"] = (
        "constant"
    )
    offset_n: float = 0.0
    amplitude_n: float = 0.0
    freq_hz: float = 1.0
    seed: int = 0
    path: Path | None = None  # csv
    timeout_s: float = 0.1  # zenoh: stale after this long
    preset: str = "rig-current"  # bouc_wen: a preset, or a plant file (mrrig identify, .json)
    current_a: float = 0.5  # bouc_wen: the reference damper's current, A
    current_amp_a: float = 0.0
    current_freq_hz: float = 1.0
    case: int = 1  # paper_case: Table 6's validation case, 1-7 in the table's column order
    current_scale: float = 1.0  # paper_case: A per paper volt of the case's coil input

    def check(self) -> None:
        if not 1 <= self.case <= 7:
            raise ValueError("case: must be 1-7 (Table 6's validation cases)")
        if not 0 < self.current_scale <= 2:
            raise ValueError("current_scale: must be in (0, 2] A per V")
        if self.kind == "csv" and self.path is None:
            raise ValueError("path: a csv reference needs a path")
        if not 0 <= self.amplitude_n <= F_RANGE_LIMIT_N:
            raise ValueError(f"amplitude_n: must be in [0, {F_RANGE_LIMIT_N:g}] N")
        if not abs(self.offset_n) + self.amplitude_n <= F_RANGE_LIMIT_N:
            raise ValueError(f"offset_n: |offset_n| + amplitude_n must be <= {F_RANGE_LIMIT_N:g} N")
        if not 0 < self.freq_hz <= 250:
            raise ValueError("freq_hz: must be in (0, 250] Hz (half the sensor rate)")
        if not 0 < self.timeout_s <= 10:
            raise ValueError("timeout_s: must be in (0, 10] s")
        if not (0 <= self.current_a <= 5 and 0 <= self.current_amp_a <= 5):
            raise ValueError("current_a, current_amp_a: must be in [0, 5] A")
        if not 0 < self.current_freq_hz <= 250:
            raise ValueError("current_freq_hz: must be in (0, 250] Hz")


@dataclass(frozen=True)
class ActuatorSection:
    """The ActuatorCommand. `stream` (contract 1.1) follows ActuatorSetpoint frames, one per
    sensor frame: its amplitude_m is the envelope |x| the stream may use, its frequency 0."""

    waveform: Literal["stop", "sine", "random", "hold", "stream"] = "stop"
    amplitude_m: float = 0.0
    frequency_hz: float = 0.0

    def check(self) -> None:
        if not 0 <= self.amplitude_m <= ACTUATOR_AMPLITUDE_MAX_M:
            raise ValueError(f"amplitude_m: must be in [0, {ACTUATOR_AMPLITUDE_MAX_M:g}] m")
        if not 0 <= self.frequency_hz <= ACTUATOR_FREQUENCY_MAX_HZ:
            raise ValueError(f"frequency_hz: must be in [0, {ACTUATOR_FREQUENCY_MAX_HZ:g}] Hz")
        if self.waveform == "stream" and self.frequency_hz != 0:
            raise ValueError("frequency_hz: must be 0 for stream (the setpoints set the motion)")
        if self.waveform == "stream" and self.amplitude_m == 0:
            raise ValueError("amplitude_m: stream needs its envelope (the largest |x| it uses)")


HilLaw = Literal[
    "skyhook", "groundhook", "hybrid", "clipped-optimal", "passive-soft", "passive-hard"
]
HilCompensation = Literal["none", "polynomial", "adaptive", "model"]


@dataclass(frozen=True)
class HilSection:
    """A hybrid simulation in the loop (the HIL specification; mrrig/loop/hil_loop.py): the scenario
    runs each time the rig is armed, the actuator in STREAM within +-envelope_m. The limits
    are the safety checks' (mrrig/hil/watch.py): a fault, HOLD, then STOP after hold_s."""

    scenario: Path | None = None  # configs/hil/*.toml; none: no hybrid simulation
    law: HilLaw | None = None  # the scenario's, if none
    compensation: HilCompensation | None = None  # the scenario's, if none
    duration_s: float | None = None  # the scenario's, if none
    envelope_m: float = 0.04  # the STREAM's: no setpoint beyond +-envelope_m
    tracking_limit_m: float = 0.02  # |x_m - x_c|
    max_setpoint_velocity_m_s: float = 3.0  # a setpoint's step per frame / period
    # a playback's recorded stroke (kind = "playback") is refused before arming beyond it,
    # as beyond envelope_m and max_setpoint_velocity_m_s: the actuator's force over its moving
    # mass (its data sheet); firmware_sim's servo has no such limit
    max_setpoint_acceleration_m_s2: float = 200.0
    energy_limit_j: float = 0.1  # the damper's delivered energy (-F s' dt) over the window
    energy_window_s: float = 0.25  # s
    hold_s: float = 0.5  # HOLD after a run ends, then STOP (the firmware ramps to rest)

    def check(self) -> None:
        if not 0 < self.envelope_m <= ACTUATOR_AMPLITUDE_MAX_M:
            raise ValueError(f"envelope_m: must be in (0, {ACTUATOR_AMPLITUDE_MAX_M:g}] m")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError("duration_s: must be positive")
        positive = ("tracking_limit_m", "max_setpoint_velocity_m_s", "energy_limit_j")
        for name in positive + ("max_setpoint_acceleration_m_s2",):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: must be positive")
        if not 0.01 <= self.energy_window_s <= 10:
            raise ValueError("energy_window_s: must be in [0.01, 10] s")
        if not 0 <= self.hold_s <= 10:
            raise ValueError("hold_s: must be in [0, 10] s")


@dataclass(frozen=True)
class TelemetrySection:
    enabled: bool = True
    zenoh_config: Path = Path("configs/zenoh-daemon.json5")
    rate_hz: float = 50.0
    # a config off loopback without authentication and access control runs only with this
    # (a closed lab network), warned in every status and recording (mrrig.rigio.zenoh_config)
    insecure: bool = False
    # no heartbeat from the telemetry process for this long: fault telemetry_lost (the rig is
    # not left ARMED unobserved longer), and the process is restarted once
    heartbeat_timeout_s: float = 5.0

    def check(self) -> None:
        if not 1 <= self.rate_hz <= 500:
            raise ValueError("rate_hz: must be in [1, 500]")
        if not 0.3 <= self.heartbeat_timeout_s <= 30:
            raise ValueError("heartbeat_timeout_s: must be in [0.3, 30] s")


@dataclass(frozen=True)
class ControlSection:
    """Limits of the control plane (mrrig/<rig>/control)."""

    # set_model / set_controller model files and set_profile CSV files must lie inside one of
    # these (after symlinks); the configured model's and profile's own directories are allowed
    model_dirs: tuple[Path, ...] = (Path("models"),)
    profile_dirs: tuple[Path, ...] = (Path("profiles"),)
    max_file_bytes: int = 4_000_000
    read_timeout_s: float = 1.0
    armed_amplitude_step_m: float = 0.005  # the largest actuator amplitude step while ARMED
    # an arm over the control plane holds a lease its client renews (`renew`); unrenewed this
    # long, the daemon disarms and stops the actuator (a client killed while armed)
    lease_timeout_s: float = 2.0

    def check(self) -> None:
        if not 0 < self.max_file_bytes <= 100_000_000:
            raise ValueError("max_file_bytes: must be in (0, 1e8]")
        if not 0 < self.read_timeout_s <= 10:
            raise ValueError("read_timeout_s: must be in (0, 10] s")
        if not 0 <= self.armed_amplitude_step_m <= 0.04:
            raise ValueError("armed_amplitude_step_m: must be in [0, 0.04] m")
        if not 0.2 <= self.lease_timeout_s <= 60:
            raise ValueError("lease_timeout_s: must be in [0.2, 60] s")


@dataclass(frozen=True)
class RecordingSection:
    enabled: bool = True
    directory: Path = Path("recordings")
    live_url: str | None = None  # e.g. rerun+http://127.0.0.1:9876/proxy
    can_log: Path | None = None  # every frame, in python-can's format for its suffix (.blf, ...)

    def check(self) -> None:
        if self.can_log is None:
            return
        # python-can's writers: only when a log is asked for
        from mrrig.rigio.canlog import BusLogError, check_writable

        try:
            check_writable(self.can_log)
        except BusLogError as exc:
            raise ValueError(f"can_log: {exc}") from None


@dataclass(frozen=True)
class CatalogSection:
    """Where the sidecar registers each finished run (mrrig.catalog): `url` an SQLite file or
    `postgresql+psycopg://...` (default: `<recording.directory>/catalog.sqlite`); a remote
    catalog that cannot be reached gets the run later (`mrrig runs sync`) from `spool`
    (default: that local file)."""

    enabled: bool = True
    url: str | None = None
    spool: Path | None = None


@dataclass(frozen=True)
class DaemonConfig:
    bus: BusSection
    rig: RigSection = field(default_factory=RigSection)
    can: CanSection = field(default_factory=CanSection)
    loop: LoopSection = field(default_factory=LoopSection)
    estimator: EstimatorSection = field(default_factory=EstimatorSection)
    controller: ControllerSection = field(default_factory=ControllerSection)
    adaptation: AdaptationSection = field(default_factory=AdaptationSection)
    reference: ReferenceSection = field(default_factory=ReferenceSection)
    actuator: ActuatorSection = field(default_factory=ActuatorSection)
    hil: HilSection = field(default_factory=HilSection)
    telemetry: TelemetrySection = field(default_factory=TelemetrySection)
    recording: RecordingSection = field(default_factory=RecordingSection)
    control: ControlSection = field(default_factory=ControlSection)
    catalog: CatalogSection = field(default_factory=CatalogSection)
    # error detectors while armed (mrrig/loop/detectors.py): [detectors.velocity] etc.
    detectors: DetectorSettings = field(default_factory=DetectorSettings)
    source: str = "<defaults>"  # the file it came from, for error messages


def load_config(
    path: str | Path, overrides: dict[str, dict[str, Any]] | None = None
) -> DaemonConfig:
    """Load and check a daemon config; `overrides` ({section: {field: value}}) win over the file.
    The file and the paths in it are found as `mrrig.resources.resolve` says."""
    path = resolve(path)
    table = load_toml(path)
    for section, values in (overrides or {}).items():
        table.setdefault(section, {}).update(values)
    table.pop("source", None)
    cfg = parse(DaemonConfig, table, str(path))
    return replace(cfg, source=str(path))


def reference_from_table(table: dict[str, Any], source: str) -> ReferenceSection:
    """A reference section from a control request (same checks as the file)."""
    return parse(ReferenceSection, table, source, "reference")
