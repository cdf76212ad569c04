"""A rig profile: the lab's DBC and the mapping of mrrig's roles to its messages and signals.

`[can] dbc = "FILE"` (found beside the config file) and `[can.signals]` map each role to
"MESSAGE.SIGNAL", or declare it "absent"; a role left out keeps the contract's name
(`DEFAULT_SIGNALS`) where the DBC has that signal, else it is absent (one log line names
them all; a role the loop needs is an error). Without `dbc` the profile is the CAN
contract's (`configs/mrrig.dbc`). The roles contract 1.1 brought (`actuator_setpoint`, its
velocity and echo: ActuatorSetpoint) are absent where a profile leaves them out and its DBC
lacks them, without a word: a profile written for 1.0 loads as it did, and refuses the STREAM
waveform in one line (`RigProfile.stream_refusal`). The codec
decodes a mapped signal under the role's key (the contract's signal name) in SI units, so the
loop reads `values["Displacement"]` in metres whatever the layout; a sensor role the layout
lacks reads as the value that keeps its check quiet, and the start-up line names every
protection that is off (README: Safety, "A rig profile without E2E").

Units: the DBC's unit of each mapped signal, converted by `UNITS` (its symbols, and their usual
spellings: `Newton`, `newtons`, `°C`, `µm`, `millimetres`, ...: `unit_of`); a unit the table
does not know, or one of another dimension than the role's, is a one-line error naming the
signal.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import cantools

from mrrig.errors import MrrigError
from mrrig.rigio.canbus.codec import DEFAULT_DBC_PATH, Codec, Packer
from mrrig.rigio.canbus.layout import (
    CodecError,
    MessageLayout,
    Rename,
    load_dbc,
    scaling_problem,
)
from mrrig.rigio.canbus.profile_limits import Limits, carry_problems

logger = logging.getLogger(__name__)

ABSENT = "absent"
CLASSIC_MAX_BYTES = 8

# unit as a DBC writes it -> (dimension, factor to SI); temperatures stay in degC (the loop's)
UNITS: dict[str, tuple[str, float]] = {
    "m": ("length", 1.0),
    "mm": ("length", 1e-3),
    "um": ("length", 1e-6),
    "N": ("force", 1.0),
    "kN": ("force", 1e3),
    "A": ("current", 1.0),
    "mA": ("current", 1e-3),
    "V": ("voltage", 1.0),
    "degC": ("temperature", 1.0),
    "Hz": ("frequency", 1.0),
    "m/s": ("velocity", 1.0),
    "mm/s": ("velocity", 1e-3),
    "": ("", 1.0),  # a flag, a code, a counter
}
# other spellings of UNITS' symbols, as DBCs from other tools write them (compared in lower
# case, a plural's "s" dropped); symbols themselves are case-sensitive (mA is not MA)
UNIT_SPELLINGS: dict[str, str] = {
    "meter": "m",
    "metre": "m",
    "millimeter": "mm",
    "millimetre": "mm",
    "micrometer": "um",
    "micrometre": "um",
    "micron": "um",
    "µm": "um",  # micro sign
    "μm": "um",  # Greek mu
    "newton": "N",
    "kilonewton": "kN",
    "ampere": "A",
    "amp": "A",
    "milliampere": "mA",
    "milliamp": "mA",
    "volt": "V",
    "°c": "degC",
    "℃": "degC",
    "deg c": "degC",
    "degc": "degC",
    "celsius": "degC",
    "degree celsius": "degC",
    "degrees celsius": "degC",
    "hertz": "Hz",
    "hz": "Hz",
}


def unit_of(text: str) -> tuple[str, float] | None:
    """(dimension, factor to SI) of a DBC's unit `text`: a symbol of UNITS or one of its
    UNIT_SPELLINGS; None where it is neither."""
    text = text.strip()
    if text in UNITS:
        return UNITS[text]
    word = text.lower()
    symbol = UNIT_SPELLINGS.get(word)
    if symbol is None and len(word) > 2 and word.endswith("s"):
        symbol = UNIT_SPELLINGS.get(word[:-1])
    return None if symbol is None else UNITS[symbol]


class Role(NamedTuple):
    key: str  # the loop's name of the value: the contract's signal name
    group: str  # sensors (the frame the loop answers), status, command, actuator
    dimension: str  # of UNITS; "" a flag, code or counter
    required: bool
    absent_value: float = math.nan  # what the loop reads where the layout lacks the role
    protection: str = ""  # what is off without it (named at start-up)
    contract: str = "1.0"  # the contract version that brought it; see `check_profile`


ROLES: dict[str, Role] = {
    "displacement": Role("Displacement", "sensors", "length", True),
    "force": Role("Force", "sensors", "force", True),
    "actuator_enabled": Role("ActuatorEnabled", "sensors", "", False, 1.0),
    "estop": Role("EStop", "sensors", "", False, 0.0, "the E-stop flag"),
    "limit_tripped": Role("LimitTripped", "sensors", "", False, 0.0, "the stroke-limit flag"),
    "sensor_fault": Role("SensorFault", "sensors", "", False, 0.0, "the sensor-fault flag"),
    "coil_current": Role("CoilCurrent", "status", "current", False),
    "damper_temperature": Role("DamperTemperature", "status", "temperature", False),
    "firmware_state": Role("State", "status", "", False),
    "firmware_fault": Role("FaultCode", "status", "", False, 0.0, "the firmware's fault code"),
    "watchdog_trips": Role(
        "CommandTimeouts", "status", "", False, 0.0, "the firmware watchdog's trip count"
    ),
    "command_mode": Role("Mode", "command", "", False),
    "command_setpoint": Role("CurrentSetpoint", "command", "current", True),
    "counter_echo": Role(
        "SensorCounterEcho", "command", "", False, protection="the counter echo (late commands)"
    ),
    "controller_id": Role("ControllerId", "command", "", False),
    "desired_force": Role("DesiredForce", "command", "force", False),
    "actuator_waveform": Role("Waveform", "actuator", "", False),
    "actuator_amplitude": Role("Amplitude", "actuator", "length", False),
    "actuator_frequency": Role("Frequency", "actuator", "frequency", False),
    # contract 1.1: the position setpoint a STREAM follows, one per sensor frame
    "actuator_setpoint": Role("PositionSetpoint", "setpoint", "length", False, contract="1.1"),
    "setpoint_velocity": Role("VelocityFeedforward", "setpoint", "velocity", False, contract="1.1"),
    "setpoint_counter_echo": Role("SensorCounterEcho", "setpoint", "", False, contract="1.1"),
}
CONTRACT_MESSAGES = {
    "sensors": "RigSensors",
    "status": "RigStatus",
    "command": "DamperCommand",
    "actuator": "ActuatorCommand",
    "setpoint": "ActuatorSetpoint",
}
DEFAULT_SIGNALS = {
    name: f"{CONTRACT_MESSAGES[role.group]}.{role.key}" for name, role in ROLES.items()
}
WAVEFORM_LABELS = ("STOP", "SINE", "RANDOM", "HOLD")
STREAM_LABEL = "STREAM"  # contract 1.1: the waveform that follows ActuatorSetpoint frames
WATCHDOG_LABEL = "COMMAND_TIMEOUT"  # the fault code that only the watchdog's FAULT carries


class ProfileError(MrrigError, ValueError):
    """A rig profile that cannot be used: the first of its problems, one line."""


@dataclass(frozen=True)
class Mapped:
    """One role as the daemon uses it."""

    role: str
    message: str
    signal: str
    unit: str
    factor: float


@dataclass
class RigProfile:
    """The checked profile: its codec, the messages of each group, what protections are off."""

    dbc_path: Path
    codec: Codec
    mapped: dict[str, Mapped]
    sensor_message: str
    status_message: str | None
    command_message: str
    actuator_message: str | None
    setpoint_message: str | None = None  # contract 1.1's ActuatorSetpoint, if it has one
    source: str = ""  # the config whose [can] this is
    protections_off: list[str] = field(default_factory=list)
    # the roles [can.signals] left out that the DBC has no contract signal for: absent
    unmapped: list[str] = field(default_factory=list)

    def packer(self) -> Packer:
        """The daemon's packer: the command, actuator and setpoint messages, unmapped signals
        at the DBC's initial value."""
        sends = (self.command_message, self.actuator_message, self.setpoint_message)
        return Packer(self.codec, None, tuple(m for m in sends if m is not None))

    def stream_refusal(self) -> str | None:
        """Why this profile cannot run the STREAM waveform (one line), None where it can: a
        profile of contract 1.0 has no ActuatorSetpoint to stream with."""
        if "actuator_setpoint" in self.mapped:
            return None
        return (
            f"waveform stream: the rig profile of {self.source} ({self.dbc_path.name}) has no"
            " actuator_setpoint role (contract 1.1's ActuatorSetpoint); map"
            " can.signals.actuator_setpoint to stream"
        )

    @property
    def sensor_layout(self) -> MessageLayout:
        return self.codec.layout(self.sensor_message)

    def firmware_status(self, v: Mapping[str, float]) -> tuple[str, int, str, int] | None:
        """(state, fault code, its label, watchdog trips) of a status frame's values, None
        where the layout has neither a state nor a fault code. The code is 1 only for the
        watchdog's own fault (its value table's COMMAND_TIMEOUT): another layout's code 1 is
        a fault like any other."""
        fault, state = self.mapped.get("firmware_fault"), self.mapped.get("firmware_state")
        if fault is None and state is None:
            return None
        code = int(v["FaultCode"])
        label = str(code)
        if fault is not None:
            label = self.codec.choices(fault.message, fault.signal).get(code, label)
        if state is not None:
            state_name = self.codec.choices(state.message, state.signal).get(int(v["State"]), "?")
        else:
            state_name = "FAULT" if code else "RUNNING"
        if code == 1 and label != WATCHDOG_LABEL:
            code = -1
        return state_name, code, label, int(v["CommandTimeouts"])

    def startup_line(self) -> str:
        name = self.dbc_path.name
        if not self.protections_off:
            return f"CAN profile {name}: E2E, counter echo and the firmware's flags all on"
        return f"CAN profile {name}: protections off: " + "; ".join(self.protections_off)

    def unmapped_line(self) -> str | None:
        """The roles taken as absent because [can.signals] does not map them, in one line;
        None where it maps or declares every one."""
        if not self.unmapped:
            return None
        return (
            f"CAN profile {self.dbc_path.name}: not mapped in [can.signals], so absent:"
            f" {', '.join(self.unmapped)}"
        )


def _message_of(codec_db: cantools.database.Database, text: str) -> tuple[str, str] | str:
    """(message, signal) of "MESSAGE.SIGNAL", or why not."""
    message, sep, signal = text.partition(".")
    if not sep or not message or not signal:
        return f"{text!r}: want MESSAGE.SIGNAL or {ABSENT!r}"
    try:
        msg = codec_db.get_message_by_name(message)
    except KeyError:
        return f"{text!r}: no message {message!r} in the DBC"
    if signal not in {s.name for s in msg.signals}:
        return f"{text!r}: message {message} has no signal {signal!r}"
    return message, signal


def layout_problems(db: cantools.database.Database, dbc: str) -> list[str]:
    """Problems of the DBC itself: an ID two messages share, a frame its signals overflow or
    that is longer than its format carries."""
    problems = []
    seen: dict[tuple[int, bool], str] = {}
    for msg in db.messages:
        key = (msg.frame_id, bool(msg.is_extended_frame))
        if key in seen:
            problems.append(
                f"{dbc}: ID clash: {seen[key]} and {msg.name} both use 0x{msg.frame_id:X}"
            )
        seen[key] = msg.name
        if not msg.is_fd and msg.length > CLASSIC_MAX_BYTES:
            problems.append(
                f"{dbc}: frame overflow: {msg.name} is {msg.length} bytes, a classic CAN frame"
                f" carries {CLASSIC_MAX_BYTES} (CAN FD: VFrameFormat)"
            )
        for sig in msg.signals:
            if (why := scaling_problem(sig)) is not None:
                problems.append(f"{dbc}: {msg.name}.{sig.name}: {why}")
            if sig.byte_order == "little_endian":
                lo, hi = sig.start, sig.start + sig.length
            else:
                msb = 8 * (sig.start // 8) + (7 - sig.start % 8)
                lo, hi = msb, msb + sig.length
            if lo < 0 or hi > 8 * msg.length:
                problems.append(
                    f"{dbc}: frame overflow: {msg.name}.{sig.name} ({sig.length} bits from"
                    f" {sig.start}) beyond the frame's {msg.length} bytes"
                )
    return problems


def check_profile(
    dbc_path: Path | None,
    signals: Mapping[str, str],
    period_s: float | None,
    source: str,
    limits: Limits | None = None,
) -> tuple[RigProfile | None, list[str]]:
    """The profile of `[can]` and every problem found (one line each): (profile, []) when it
    can be used, (None, problems) otherwise. `period_s`: the config's sensor period, checked
    against the sensor message's GenMsgCycleTime where the DBC has one; `limits`: what each
    role's signal must carry (mrrig/rigio/canbus/profile_limits.py)."""
    contract = dbc_path is None
    path = DEFAULT_DBC_PATH if dbc_path is None else Path(dbc_path)
    dbc = path.name
    try:
        # not strict: an overflowing signal is a problem to report, not a refusal to read
        db = load_dbc(path, strict=False)
    except (OSError, cantools.database.UnsupportedDatabaseFormatError, ValueError) as exc:
        return None, [f"{path}: cannot read the DBC: {' '.join(str(exc).split())}"]
    problems = layout_problems(db, dbc)
    # a role the table leaves out keeps the contract's name where the DBC has it (a DBC that
    # is the contract's with other IDs needs no table); else it is unmapped
    table = dict(signals)
    for name, default in DEFAULT_SIGNALS.items():
        if name not in table and (contract or not isinstance(_message_of(db, default), str)):
            table[name] = default
    for name in sorted(set(table) - set(ROLES)):
        problems.append(f"{source}: can.signals.{name}: unknown role (known: {', '.join(ROLES)})")
    mapped: dict[str, Mapped] = {}
    unmapped: list[str] = []
    for name, role in ROLES.items():
        where = f"{source}: can.signals.{name}"
        text = table.get(name)
        if text is None and role.contract != "1.0":
            continue  # a profile written for contract 1.0: absent
        if text is None and role.required:
            problems.append(
                f"{where}: unmapped role, which the loop needs (map it to MESSAGE.SIGNAL of {dbc})"
            )
            continue
        if text is None:
            unmapped.append(name)
            continue
        if text == ABSENT:
            if role.required:
                problems.append(f"{where}: cannot be absent (the loop needs it)")
            continue
        found = _message_of(db, text)
        if isinstance(found, str):
            problems.append(f"{where}: {found}")
            continue
        message, signal = found
        unit = db.get_message_by_name(message).get_signal_by_name(signal).unit or ""
        if (si := unit_of(unit)) is None:
            known = ", ".join(u for u in UNITS if u)
            problems.append(
                f"{dbc}: {message}.{signal}: unit {unit!r} not in the unit table ({known})"
            )
            continue
        dimension, factor = si
        if dimension != role.dimension:
            want = role.dimension or "no unit"
            problems.append(
                f"{dbc}: {message}.{signal}: unit {unit!r} ({dimension or 'none'}) for role"
                f" {name}, which wants {want}"
            )
            continue
        mapped[name] = Mapped(name, message, signal, unit, factor)
    groups: dict[str, str] = {}
    for name, m in mapped.items():
        group = ROLES[name].group
        first = groups.setdefault(group, m.message)
        if first != m.message:
            problems.append(
                f"{source}: can.signals.{name}: in {m.message}, but the other {group} roles are"
                f" in {first} (one message per group)"
            )
    received = {groups.get("sensors"), groups.get("status")} - {None}
    for group in ("command", "actuator", "setpoint"):
        if groups.get(group) in received:
            problems.append(
                f"{source}: can.signals: {groups[group]} carries both what the rig sends and"
                f" the {group} the daemon sends"
            )
    sensors = groups.get("sensors")
    if sensors is not None:
        problems += _period_problems(db, sensors, groups.get("command"), period_s, dbc, source)
    if (w := mapped.get("actuator_waveform")) is not None:
        sig = db.get_message_by_name(w.message).get_signal_by_name(w.signal)
        labels = {str(v) for v in (sig.choices or {}).values()}
        if missing := [lab for lab in WAVEFORM_LABELS if lab not in labels]:
            problems.append(
                f"{dbc}: {w.message}.{w.signal}: value table lacks {', '.join(missing)}"
                " (actuator_waveform)"
            )
    problems += _setpoint_problems(db, mapped, groups, dbc, source)
    actuator = [name for name in ROLES if ROLES[name].group == "actuator"]
    if mapped.keys() & set(actuator) and (missing := [n for n in actuator if n not in mapped]):
        problems.append(
            f"{source}: can.signals: {groups['actuator']} carries the actuator's command without"
            f' {", ".join(missing)} (map each, or declare every actuator_* role "{ABSENT}")'
        )
    if problems:
        return None, problems
    renames = {(m.message, m.signal): Rename(ROLES[m.role].key, m.factor) for m in mapped.values()}
    constants: dict[str, dict[str, float]] = {}
    for name, role in ROLES.items():
        if name not in mapped and role.group in groups and role.group in ("sensors", "status"):
            constants.setdefault(groups[role.group], {})[role.key] = role.absent_value
    try:
        codec = Codec(path, renames, constants)
    except CodecError as exc:
        return None, [str(exc)]
    profile = RigProfile(
        dbc_path=path,
        codec=codec,
        mapped=mapped,
        sensor_message=groups["sensors"],
        status_message=groups.get("status"),
        command_message=groups["command"],
        actuator_message=groups.get("actuator"),
        setpoint_message=groups.get("setpoint"),
        source=source,
        unmapped=unmapped,
    )
    if limits is not None and (problems := carry_problems(codec, mapped, ROLES, limits, source)):
        return None, problems
    profile.protections_off = _protections_off(profile)
    for echo in ("counter_echo", "setpoint_counter_echo"):
        if mapped.get(echo) is not None and not profile.sensor_layout.e2e:
            return None, [
                f"{source}: can.signals.{echo}: {profile.sensor_message} has no E2E counter to echo"
            ]
    return profile, []


def _setpoint_problems(
    db: cantools.database.Database,
    mapped: Mapping[str, Mapped],
    groups: Mapping[str, str],
    dbc: str,
    source: str,
) -> list[str]:
    """Contract 1.1's setpoint: a message of its own, with the position, and a STREAM
    waveform in the actuator command to start it."""
    message = groups.get("setpoint")
    if message is None:
        return []
    if "actuator_setpoint" not in mapped:
        return [
            f"{source}: can.signals: {message} carries the setpoint's velocity or echo without"
            ' actuator_setpoint (map it, or declare every setpoint role "absent")'
        ]
    for group in ("command", "actuator"):
        if groups.get(group) == message:
            return [
                f"{source}: can.signals.actuator_setpoint: {message} carries the {group} too"
                " (the setpoint goes once per sensor frame, in a message of its own)"
            ]
    w = mapped.get("actuator_waveform")
    if w is None:
        return [
            f"{source}: can.signals.actuator_setpoint: needs actuator_waveform (its STREAM"
            " command starts the stream)"
        ]
    sig = db.get_message_by_name(w.message).get_signal_by_name(w.signal)
    if STREAM_LABEL not in {str(v) for v in (sig.choices or {}).values()}:
        return [
            f"{dbc}: {w.message}.{w.signal}: value table lacks {STREAM_LABEL}"
            " (actuator_setpoint streams)"
        ]
    return []


def _period_problems(
    db: cantools.database.Database,
    sensors: str,
    command: str | None,
    period_s: float | None,
    dbc: str,
    source: str,
) -> list[str]:
    problems = []
    cycle = _cycle_ms(db, sensors)
    if cycle and period_s is not None and not math.isclose(cycle / 1e3, period_s):
        problems.append(
            f"{source}: period mismatch: loop.period_s {period_s:g} s, but {sensors}'s"
            f" GenMsgCycleTime in {dbc} is {cycle:g} ms"
        )
    command_cycle = _cycle_ms(db, command) if command is not None else None
    if cycle and command_cycle and command_cycle != cycle:
        problems.append(
            f"{dbc}: period mismatch: {command} every {command_cycle:g} ms, but one answers each"
            f" {sensors} frame (every {cycle:g} ms)"
        )
    return problems


def _cycle_ms(db: cantools.database.Database, message: str) -> float | None:
    attrs = db.get_message_by_name(message).dbc
    attr = attrs.attributes.get("GenMsgCycleTime") if attrs is not None else None
    return attr.value if attr is not None and attr.value else None


def _protections_off(p: RigProfile) -> list[str]:
    off = []
    if not p.sensor_layout.e2e:
        off.append(
            f"E2E on {p.sensor_message} (no CRC: a corrupted frame is not refused; no counter:"
            " repeated and lost frames are not seen)"
        )
    if not p.codec.layout(p.command_message).e2e:
        off.append(f"E2E on {p.command_message} (the firmware cannot refuse a corrupted command)")
    for name, role in ROLES.items():
        if role.protection and name not in p.mapped:
            off.append(role.protection)
    if p.setpoint_message is not None and "setpoint_counter_echo" not in p.mapped:
        off.append("the setpoint's counter echo (late setpoints)")
    return off


def contract_profile() -> RigProfile:
    """The CAN contract's profile (configs/mrrig.dbc, every role in its place)."""
    return load_profile(None, {}, None, "the CAN contract")


def load_profile(
    dbc_path: Path | None,
    signals: Mapping[str, str],
    period_s: float | None,
    source: str,
    limits: Limits | None = None,
) -> RigProfile:
    """The profile, or a `ProfileError` with its first problem (`mrrig dbc check` lists all)."""
    profile, problems = check_profile(dbc_path, signals, period_s, source, limits)
    if profile is None:
        more = f" (and {len(problems) - 1} more: mrrig dbc check)" if len(problems) > 1 else ""
        raise ProfileError(problems[0] + more)
    if (line := profile.unmapped_line()) is not None:
        logger.info("%s", line)
    return profile
