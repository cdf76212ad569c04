"""What each role of a rig profile must carry, and whether its signal can.

A signal carries the physical values its raw bits reach through its scale and offset, within
the DBC's [min|max], in SI units after the profile's unit (`representable`). The daemon's
limits (`daemon_limits`: the command current up to `loop.i_max_a`, the measured and desired
force over `loop.f_range_n`, the displacement and the actuator's position setpoint over
`loop.x_range_m`, the actuator's amplitude
and frequency up to their bounds, every controller's id) and the simulator's
(`firmware_limits`: the displacement over its stroke) are
each a range the role's signal must cover; one that does not (a command signal that cannot
carry 2 A, a force in kN declared as N) is refused at start-up and by `mrrig dbc check`, in
one line naming the file, the message, the signal and both ranges.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, NamedTuple

from mrrig.config import ACTUATOR_AMPLITUDE_MAX_M, ACTUATOR_FREQUENCY_MAX_HZ
from mrrig.loop.controllers import CONTROLLERS
from mrrig.rigio.canbus.codec import Codec
from mrrig.rigio.canbus.layout import SignalField

if TYPE_CHECKING:
    from mrrig.config import DaemonConfig
    from mrrig.rigio.canbus.profile import Mapped, Role

# the SI unit of each dimension of the unit table (mrrig.rigio.canbus.profile.UNITS)
SI_UNIT = {
    "length": "m",
    "force": "N",
    "current": "A",
    "voltage": "V",
    "frequency": "Hz",
    "velocity": "m/s",
}


class Carry(NamedTuple):
    """A range of values one role's signal must carry, and the setting it comes from."""

    lo: float
    hi: float
    what: str


Limits = Mapping[str, Carry]  # role -> what its signal must carry


class Span(NamedTuple):
    lo: float
    hi: float
    step: float  # the value of one raw step (0 for a float signal)


def representable(f: SignalField) -> Span:
    """The physical values a field's signal reaches (SI, as the codec decodes it)."""
    if f.float_bits:
        return Span(f.lo, f.hi, 0.0)
    a, b = f.raw_min * f.scale + f.offset, f.raw_max * f.scale + f.offset
    return Span(min(a, b), max(a, b), abs(f.scale))


def daemon_limits(cfg: DaemonConfig) -> dict[str, Carry]:
    """What the daemon sends and reads, by role, from its config."""
    loop = cfg.loop
    f_lo, f_hi = loop.f_range_n
    x_lo, x_hi = loop.x_range_m
    return {
        "command_setpoint": Carry(0.0, loop.i_max_a, "loop.i_max_a"),
        "coil_current": Carry(0.0, loop.i_max_a, "loop.i_max_a"),
        "force": Carry(f_lo, f_hi, "loop.f_range_n"),
        "desired_force": Carry(f_lo, f_hi, "loop.f_range_n"),
        "displacement": Carry(x_lo, x_hi, "loop.x_range_m"),
        "actuator_setpoint": Carry(x_lo, x_hi, "loop.x_range_m"),
        "actuator_amplitude": Carry(0.0, ACTUATOR_AMPLITUDE_MAX_M, "actuator.amplitude_m bound"),
        "actuator_frequency": Carry(0.0, ACTUATOR_FREQUENCY_MAX_HZ, "actuator.frequency_hz bound"),
        "controller_id": Carry(
            0, max(c.controller_id for c in CONTROLLERS.values()), "the controllers' ids"
        ),
    }


def firmware_limits(stroke_m: float) -> dict[str, Carry]:
    """What the simulator sends, by role: the displacement over its stroke (its coil current
    is clipped to its signal's range; a value no signal carries faults it, not the process)."""
    return {"displacement": Carry(-stroke_m, stroke_m, "actuator.stroke_m")}


def carry_problems(
    codec: Codec,
    mapped: Mapping[str, Mapped],
    roles: Mapping[str, Role],
    limits: Limits,
    source: str,
) -> list[str]:
    """One line for each mapped role whose signal does not carry its limit's range."""
    problems = []
    for role, need in limits.items():
        m = mapped.get(role)
        if m is None:
            continue
        lay = codec.layout(m.message)
        f = next(f for f in lay.fields if f.name == roles[role].key)
        span = representable(f)
        tol = 0.499 * span.step  # a value within half a raw step rounds onto the end
        if span.lo <= need.lo + tol and span.hi >= need.hi - tol:
            continue
        unit = SI_UNIT.get(roles[role].dimension, "")
        unit = f" {unit}" if unit else ""
        problems.append(
            f"{codec.dbc_path.name}: {m.message}.{m.signal} ({role}) carries"
            f" [{span.lo:g}, {span.hi:g}]{unit}, but {source}'s {need.what} needs"
            f" [{need.lo:g}, {need.hi:g}]{unit}"
        )
    return problems
