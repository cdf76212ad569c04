"""The fast codec on layouts other than the contract's: Motorola and Intel byte order, signed,
IEEE float and multiplexed signals, 29-bit identifiers and CAN FD frames, messages without
E2E. Whatever cantools decodes from a frame, the codec decodes the same; a frame cantools
cannot decode, or whose value lies outside its signal's DBC range, the codec rejects."""

from __future__ import annotations

import math
from pathlib import Path

import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mrrig.pycan import can
from mrrig.rigio.canbus.codec import Codec, CodecError

LAYOUTS_DBC = Path(__file__).parent / "data" / "layouts.dbc"
CODEC = Codec(LAYOUTS_DBC)
DB = cantools.database.load_file(str(LAYOUTS_DBC), strict=True)


def _cantools_view(msg, data: bytes) -> dict[str, float] | None:
    """cantools' values of a frame, or None where it cannot decode it or a value lies outside
    its signal's [min|max] (the codec's rejection)."""
    try:
        decoded = msg.decode(data, decode_choices=False)
    except cantools.database.DecodeError:
        return None
    for name, value in decoded.items():
        sig = msg.get_signal_by_name(name)
        lo = -math.inf if sig.minimum is None else sig.minimum
        hi = math.inf if sig.maximum is None else sig.maximum
        if not lo <= value <= hi:  # NaN too
            return None
    return decoded


def _frame(name: str) -> st.SearchStrategy[bytes]:
    """Random payloads; for the multiplexed message, mostly a selector value that exists."""
    msg = DB.get_message_by_name(name)
    body = st.binary(min_size=msg.length, max_size=msg.length)
    if not msg.is_multiplexed():
        return body
    return st.tuples(body, st.sampled_from([0, 1, 7])).map(
        lambda pair: pair[0][:9] + bytes([pair[1]]) + pair[0][10:]
    )


@pytest.mark.parametrize("name", [m.name for m in DB.messages])
@settings(max_examples=400, deadline=None)
@given(data=st.data())
def test_fast_decode_equals_cantools_on_random_frames(name: str, data: st.DataObject) -> None:
    msg = DB.get_message_by_name(name)
    frame = data.draw(_frame(name))
    expected = _cantools_view(msg, frame)
    parsed = CODEC.parser().parse(msg.frame_id, frame, 0.0, msg.is_extended_frame, msg.is_fd)
    assert parsed.ok == (expected is not None), (parsed.reason, expected)
    if parsed.ok:
        assert parsed.values == pytest.approx(expected, rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("name", [m.name for m in DB.messages])
@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_fast_encode_equals_cantools(name: str, data: st.DataObject) -> None:
    """What cantools decoded from a valid frame, the codec packs to the bytes cantools packs."""
    msg = DB.get_message_by_name(name)
    values = _cantools_view(msg, data.draw(_frame(name)))
    if values is None:
        return
    sender = msg.senders[0]
    fast = CODEC.packer(sender).encode(name, values)
    assert fast == msg.encode(values, scaling=True, strict=False)


def test_frame_formats_come_from_the_dbc() -> None:
    sensors, command = CODEC.layout("LabSensors"), CODEC.layout("LabCommand")
    assert (sensors.is_extended, sensors.is_fd, sensors.e2e, sensors.period_s) == (
        True,
        False,
        False,
        0.001,
    )
    assert (command.is_extended, command.is_fd, command.length) == (False, True, 64)
    msg = CODEC.packer("HOST").message("LabCommand", {"Current": 1.0, "Force": 5.0, "Gain": 2})
    assert (msg.is_fd, msg.is_extended_id, len(msg.data)) == (True, False, 64)


def test_ids_are_accepted_only_in_the_frame_format_the_dbc_declares() -> None:
    parser = CODEC.parser()
    frame = bytes(16)
    ok = parser.parse_message(
        can.Message(arbitration_id=0x19000000, is_extended_id=True, data=frame)
    )
    assert ok.ok, ok.reason
    # the same ID as an 11-bit frame does not exist; an FD frame of a classic message is refused
    assert parser.parse(0x19000000 & 0x7FF, frame, 0.0).name is None
    fd = parser.parse_message(
        can.Message(arbitration_id=0x19000000, is_extended_id=True, is_fd=True, data=frame)
    )
    assert not fd.ok and "CAN FD" in fd.reason
    classic = parser.parse(0x400, bytes(64), 0.0, is_extended=False, is_fd=False)
    assert not classic.ok and "classic" in classic.reason
    assert parser.parse(0x400, bytes(64), 0.0, is_fd=True).ok


def test_a_message_without_e2e_has_no_counter_and_no_crc_check() -> None:
    parser = CODEC.parser()
    first = parser.parse(0x400, bytes(64), 0.0, is_fd=True)
    again = parser.parse(0x400, bytes(64), 0.0, is_fd=True)  # a repeat is not refused
    assert first.ok and again.ok and first.counter is None and again.lost_frames == 0


def test_a_dbc_cantools_refuses_is_one_line_naming_the_file(tmp_path) -> None:
    text = LAYOUTS_DBC.read_text().replace(" SG_ Fault m1 :", " SG_ Fault m1M :")
    path = tmp_path / "overlap.dbc"
    path.write_text(text)
    with pytest.raises(CodecError) as err:
        Codec(path)
    assert str(err.value).startswith(f"{path}: cannot read the DBC: ")
    assert "\n" not in str(err.value)
