"""The DBC read into message layouts: each message's id, length, frame format, E2E attributes
and its signals as the codec's fast and general paths need them (mrrig.rigio.canbus.codec
packs and parses with them). The DBC is the only source of the layout.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import cantools
from cantools.database.can import Message as DbcMessage

from mrrig.errors import MrrigError

# Message attributes of the DBC that define the E2E protection.
ATTR_PROFILE = "E2EProfile"
ATTR_DATA_ID = "DataID"
ATTR_CRC_SIGNAL = "E2ECRCSignal"
ATTR_COUNTER_SIGNAL = "E2ECounterSignal"
ATTR_CYCLE_TIME = "GenMsgCycleTime"
PROFILE_2 = "Profile2"


def load_dbc(path: str | Path, strict: bool = True) -> cantools.database.Database:
    """The DBC at `path`, read as UTF-8 where it is valid UTF-8 (a DBC from a text editor or
    cantools: `°C`), else as Windows-1252 (Vector's tools), never the one as the other."""
    try:
        Path(path).read_bytes().decode("utf-8")
        encoding = "utf-8-sig"
    except UnicodeDecodeError:
        encoding = "cp1252"
    return cantools.database.load_file(str(path), encoding=encoding, strict=strict)


class CodecError(MrrigError, ValueError):
    """The DBC does not describe a layout this codec supports."""


class SignalField(NamedTuple):
    """One payload signal, as the fast path needs it: raw = (word >> shift) & mask, `word` the
    payload read little-endian (Intel) or big-endian (Motorola, `big`)."""

    name: str  # the signal's name, or the role key a rig profile gave it
    shift: int
    mask: int
    sign_bit: int  # 0 for unsigned signals
    scale: float  # the DBC's, times the profile's conversion to SI
    offset: float
    raw_min: int
    raw_max: int
    labels: dict[str, int]  # value table, label -> raw
    big: bool = False  # Motorola byte order
    float_bits: int = 0  # 32 or 64: an IEEE float signal
    lo: float = -math.inf  # physical range (float signals: checked on the value)
    hi: float = math.inf
    mux: tuple[str, frozenset[int]] | None = None  # (selector signal, its values) if multiplexed
    default_raw: int = 0  # what a packer that fills unmapped signals puts (the DBC's initial)


@dataclass(frozen=True)
class MessageLayout:
    """Everything the codec knows about one message, all of it read from the DBC."""

    name: str
    frame_id: int
    length: int
    senders: tuple[str, ...]
    data_id: int
    period_s: float | None
    crc_signal: str  # "" without E2E
    counter_signal: str
    counter_shift: int
    counter_mask: int
    fields: tuple[SignalField, ...]  # payload signals, without the E2E ones; muxed ones last
    e2e: bool = True  # AUTOSAR E2E profile 2 (CRC and counter) protects it
    is_extended: bool = False  # a 29-bit identifier
    is_fd: bool = False  # a CAN FD frame
    # Intel integer signals only, nothing multiplexed: the fast path
    simple: bool = True
    constants: dict[str, float] = field(default_factory=dict)  # keys a profile declares absent

    @property
    def signal_names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    @property
    def key(self) -> int:
        return frame_key(self.frame_id, self.is_extended)


EXTENDED_KEY = 1 << 31  # beyond any 29-bit identifier: the parser's key of an extended frame


def frame_key(frame_id: int, is_extended: bool) -> int:
    return frame_id | EXTENDED_KEY if is_extended else frame_id


def _attribute(msg: DbcMessage, name: str) -> int | float | str:
    attributes = msg.dbc.attributes if msg.dbc is not None else {}
    if name in attributes:
        return attributes[name].value
    raise CodecError(f"{msg.name}: DBC message attribute {name!r} missing")


def scaling_problem(signal: cantools.database.can.Signal) -> str | None:
    """Why a signal's scale, offset and [min|max] cannot be computed with (one line, without
    the message's name), or None: a scale of 0 or not finite, an offset or a bound not finite,
    an offset beside which the scale is below the float resolution (1e308 with 0.001), or a
    range whose raw values overflow."""
    scale, offset = signal.scale, signal.offset
    if not math.isfinite(scale) or scale == 0:
        return f"scale {scale:g} (a signal needs a finite, non-zero scale)"
    if not math.isfinite(offset):
        return f"offset {offset:g} is not finite"
    if offset + scale == offset:
        return f"offset {offset:g} leaves its scale {scale:g} below the float resolution"
    ends = [b for b in (signal.minimum, signal.maximum) if b is not None]
    if not all(math.isfinite(b) and math.isfinite((b - offset) / scale) for b in ends):
        shown = "|".join("-" if b is None else f"{b:g}" for b in (signal.minimum, signal.maximum))
        return f"range [{shown}] with scale {scale:g} and offset {offset:g} overflows its raw value"
    bits = signal.length
    if not signal.is_float and not math.isfinite(float(1 << bits) * abs(scale) + abs(offset)):
        return f"{bits} bits with scale {scale:g} and offset {offset:g} overflow a float"
    return None


def _physical_to_raw(value: float, signal: cantools.database.can.Signal) -> float:
    return round((value - signal.offset) / signal.scale, 6)


class Rename(NamedTuple):
    """A rig profile's name for a signal and the factor from its DBC unit to SI."""

    key: str
    factor: float = 1.0


def _signal_field(
    msg: DbcMessage, signal: cantools.database.can.Signal, rename: Rename | None
) -> SignalField:
    where = f"{msg.name}.{signal.name}"
    if (why := scaling_problem(signal)) is not None:
        raise CodecError(f"{where}: {why}")
    mask = (1 << signal.length) - 1
    big = signal.byte_order != "little_endian"
    nbits = 8 * msg.length
    if big:
        # cantools' start bit of a Motorola signal is its MSB in the DBC's sawtooth numbering
        msb = 8 * (signal.start // 8) + (7 - signal.start % 8)
        shift = nbits - (msb + signal.length)
    else:
        shift = signal.start
    if shift < 0 or shift + signal.length > nbits:
        raise CodecError(f"{where}: does not fit in the message's {msg.length} bytes")
    float_bits = 0
    if signal.is_float:
        if signal.length not in (32, 64):
            raise CodecError(f"{where}: a float signal must be 32 or 64 bits long")
        float_bits = signal.length
    if signal.is_signed and not float_bits:
        sign_bit = 1 << (signal.length - 1)
        raw_min, raw_max = -sign_bit, sign_bit - 1
    else:
        sign_bit = 0
        raw_min, raw_max = 0, mask
    # DBC [min|max] are physical: narrow the raw range to them (rounded to absorb float error
    # of limits that are multiples of the scale); a float signal's are checked on its value
    lo, hi = -math.inf, math.inf
    if float_bits:
        if signal.minimum is not None:
            lo = signal.minimum
        if signal.maximum is not None:
            hi = signal.maximum
    else:
        if signal.minimum is not None:
            raw_min = max(raw_min, math.ceil(_physical_to_raw(signal.minimum, signal)))
        if signal.maximum is not None:
            raw_max = min(raw_max, math.floor(_physical_to_raw(signal.maximum, signal)))
    labels = {str(label): raw for raw, label in (signal.choices or {}).items()}
    mux = None
    if signal.multiplexer_ids:
        if signal.is_multiplexer:
            raise CodecError(f"{where}: nested multiplexing not supported")
        mux = (signal.multiplexer_signal, frozenset(signal.multiplexer_ids))
    name, factor = rename if rename is not None else (signal.name, 1.0)
    initial = signal.raw_initial if isinstance(signal.raw_initial, int | float) else 0
    default_raw = initial if float_bits else min(max(int(initial), raw_min), raw_max)
    return SignalField(
        name=name,
        shift=shift,
        mask=mask,
        sign_bit=sign_bit,
        scale=signal.scale * factor,
        offset=signal.offset * factor,
        raw_min=raw_min,
        raw_max=raw_max,
        labels=labels,
        big=big,
        float_bits=float_bits,
        lo=lo * factor,
        hi=hi * factor,
        mux=mux,
        default_raw=default_raw,
    )


def message_layout(
    msg: DbcMessage,
    renames: Mapping[tuple[str, str], Rename],
    constants: Mapping[str, Mapping[str, float]],
) -> MessageLayout:
    if msg.is_container:
        raise CodecError(f"{msg.name}: container messages not supported")
    if not msg.is_extended_frame and msg.frame_id > 0x7FF:
        raise CodecError(f"{msg.name}: id 0x{msg.frame_id:x} beyond 11 bits (extended?)")
    attributes = msg.dbc.attributes if msg.dbc is not None else {}
    profile = attributes["E2EProfile"].value if ATTR_PROFILE in attributes else ""
    e2e = bool(profile)
    crc_name = counter_name = ""
    data_id, counter_shift, counter_mask = 0, 0, 0
    if e2e:
        if profile != PROFILE_2:
            raise CodecError(
                f"{msg.name}: E2E profile {profile!r} not supported (want {PROFILE_2})"
            )
        crc_name = str(_attribute(msg, ATTR_CRC_SIGNAL))
        counter_name = str(_attribute(msg, ATTR_COUNTER_SIGNAL))
        data_id = int(_attribute(msg, ATTR_DATA_ID))
        crc = msg.get_signal_by_name(crc_name)
        counter = msg.get_signal_by_name(counter_name)
        # Profile 2 fixes where they live: CRC = byte 0, counter = low nibble of byte 1.
        if (crc.start, crc.length, crc.is_signed, crc.byte_order) != (
            0,
            8,
            False,
            "little_endian",
        ):
            raise CodecError(f"{msg.name}.{crc_name}: profile 2 CRC must be 0|8@1+")
        if (counter.start, counter.length, counter.is_signed, counter.byte_order) != (
            8,
            4,
            False,
            "little_endian",
        ):
            raise CodecError(f"{msg.name}.{counter_name}: profile 2 counter must be 8|4@1+")
        counter_shift, counter_mask = counter.start, (1 << counter.length) - 1
    cycle_ms = attributes.get(ATTR_CYCLE_TIME)
    period_s = cycle_ms.value / 1000.0 if cycle_ms is not None and cycle_ms.value else None
    fields = tuple(
        _signal_field(msg, s, renames.get((msg.name, s.name)))
        for s in msg.signals
        if s.name not in (crc_name, counter_name)
    )
    # the selectors first: a multiplexed signal is read after the value that selects it
    fields = tuple(f for f in fields if f.mux is None) + tuple(f for f in fields if f.mux)
    simple = not any(f.big or f.float_bits or f.mux for f in fields)
    return MessageLayout(
        name=msg.name,
        frame_id=msg.frame_id,
        length=msg.length,
        senders=tuple(msg.senders),
        data_id=data_id,
        period_s=period_s,
        crc_signal=crc_name,
        counter_signal=counter_name,
        counter_shift=counter_shift,
        counter_mask=counter_mask,
        fields=fields,
        e2e=e2e,
        is_extended=bool(msg.is_extended_frame),
        is_fd=bool(msg.is_fd),
        simple=simple,
        constants=dict(constants.get(msg.name, {})),
    )
