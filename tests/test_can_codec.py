"""Rules of spec/can-protocol.md for the codec: layout, E2E profile 2, validity tracking."""

from __future__ import annotations

import math

import cantools
import pytest
from cantools.autosar import check_profile2_crc, compute_profile2_crc
from hypothesis import given, settings
from hypothesis import strategies as st

from mrrig.rigio.canbus.codec import (
    DEFAULT_DBC_PATH,
    Codec,
    EncodeError,
    profile2_crc,
)
from tests.conftest import SENSORS

# The contract's test vectors: (message, counter, values, payload).
VECTORS = [
    (
        "RigSensors",
        3,
        {
            "ActuatorEnabled": 1,
            "LimitTripped": 0,
            "EStop": 0,
            "SensorFault": 0,
            "Displacement": 0.012345,
            "Force": 1234.56,
        },
        "1b 13 39 30 00 40 e2 01",
    ),
    (
        "RigSensors",
        15,
        {
            "ActuatorEnabled": 1,
            "LimitTripped": 0,
            "EStop": 0,
            "SensorFault": 0,
            "Displacement": -0.02,
            "Force": -987.65,
        },
        "41 1f e0 b1 ff 33 7e fe",
    ),
    (
        "RigStatus",
        7,
        {
            "State": 2,
            "CoilCurrent": 0.85,
            "DamperTemperature": 31.25,
            "FaultCode": 0,
            "CommandTimeouts": 0,
        },
        "c0 27 34 21 35 0c 00 00",
    ),
    (
        "DamperCommand",
        3,
        {
            "Mode": 1,
            "CurrentSetpoint": 1.2345,
            "SensorCounterEcho": 3,
            "ControllerId": 1,
            "DesiredForce": 1200.0,
        },
        "2d 13 39 30 13 c0 d4 01",
    ),
    (
        "DamperCommand",
        0,
        {
            "Mode": 0,
            "CurrentSetpoint": 0.0,
            "SensorCounterEcho": 15,
            "ControllerId": 0,
            "DesiredForce": 0.0,
        },
        "52 00 00 00 0f 00 00 00",
    ),
    (
        "ActuatorCommand",
        1,
        {"Waveform": 1, "Amplitude": 0.015, "Frequency": 2.0},
        "a6 11 dc 05 d0 07 00 00",
    ),
    (  # contract 1.1
        "ActuatorSetpoint",
        5,
        {"SensorCounterEcho": 4, "PositionSetpoint": 0.012345, "VelocityFeedforward": 0.1234},
        "77 45 39 30 00 d2 04 00",
    ),
    (
        "ActuatorSetpoint",
        0,
        {"SensorCounterEcho": 15, "PositionSetpoint": -0.0205, "VelocityFeedforward": -0.5},
        "d4 f0 ec af ff 78 ec 00",
    ),
]

CONTRACT_IDS = {  # message: (CAN ID, Data ID, sender)
    "RigSensors": (0x110, 0x51, "RIG"),
    "RigStatus": (0x111, 0x52, "RIG"),
    "DamperCommand": (0x210, 0x61, "DAEMON"),
    "ActuatorCommand": (0x211, 0x62, "DAEMON"),
    "ActuatorSetpoint": (0x212, 0x63, "DAEMON"),
}


@pytest.fixture(scope="module")
def codec() -> Codec:
    return Codec()


def _sender(codec: Codec, name: str) -> str:
    return codec.layout(name).senders[0]


def test_dbc_has_the_contract_messages_ids_data_ids_and_senders(codec: Codec) -> None:
    got = {n: (lay.frame_id, lay.data_id, lay.senders[0]) for n, lay in codec.layouts.items()}
    assert got == CONTRACT_IDS
    for lay in codec.layouts.values():
        assert lay.length == 8
        msg = codec.db.get_message_by_name(lay.name)
        assert not msg.is_extended_frame
        assert all(s.byte_order == "little_endian" for s in msg.signals)


@pytest.mark.parametrize("name,counter,values,payload", VECTORS)
def test_vector_encodes_to_exact_payload(
    codec: Codec, name: str, counter: int, values: dict, payload: str
) -> None:
    packer = codec.packer(_sender(codec, name))
    assert packer.encode(name, values, counter=counter).hex(" ") == payload


@pytest.mark.parametrize("name,counter,values,payload", VECTORS)
def test_vector_decodes_to_exact_values(
    codec: Codec, name: str, counter: int, values: dict, payload: str
) -> None:
    parsed = codec.parser().parse(codec.layout(name).frame_id, bytes.fromhex(payload), 1.0)
    assert parsed.ok, parsed.reason
    assert parsed.counter == counter
    assert parsed.values.keys() == values.keys()
    for signal, want in values.items():
        scale = codec.db.get_message_by_name(name).get_signal_by_name(signal).scale
        # Exact up to float rounding of raw * scale, far below one scale step.
        assert math.isclose(parsed.values[signal], want, rel_tol=1e-12, abs_tol=1e-9 * scale)


@pytest.mark.parametrize("name,counter,values,payload", VECTORS)
def test_vector_agrees_with_cantools(
    codec: Codec, name: str, counter: int, values: dict, payload: str
) -> None:
    data = bytes.fromhex(payload)
    layout = codec.layout(name)
    assert check_profile2_crc(data, layout.data_id)
    decoded = codec.db.get_message_by_name(name).decode(data, decode_choices=False)
    assert decoded[layout.counter_signal] == counter


@pytest.mark.parametrize("name,counter,values,payload", VECTORS)
def test_every_single_bit_flip_is_rejected(
    codec: Codec, name: str, counter: int, values: dict, payload: str
) -> None:
    frame_id = codec.layout(name).frame_id
    data = bytes.fromhex(payload)
    assert codec.parser().parse(frame_id, data, 0.0).ok
    word = int.from_bytes(data, "little")
    for bit in range(64):
        flipped = (word ^ (1 << bit)).to_bytes(8, "little")
        parser = codec.parser()
        parsed = parser.parse(frame_id, flipped, 0.0)
        assert not parsed.ok, f"bit {bit} flip accepted"
        assert parsed.reason.startswith(f"{name}: CRC mismatch")
        assert parser.stats[name].bad_crc == 1
        assert parser.last(name) is None


def test_repeated_counter_is_rejected_and_keeps_last_good_values(codec: Codec) -> None:
    packer, parser = codec.packer("RIG"), codec.parser()
    first = packer.encode("RigSensors", SENSORS, counter=5)
    again = packer.encode("RigSensors", dict(SENSORS, Force=20.0), counter=5)
    assert parser.parse(0x110, first, 1.0).ok
    parsed = parser.parse(0x110, again, 1.002)
    assert not parsed.ok
    assert parsed.reason == "RigSensors: repeated counter 5"
    assert parser.stats["RigSensors"].repeated_counter == 1
    assert parser.last("RigSensors").values["Force"] == pytest.approx(10.0)
    assert parser.last("RigSensors").timestamp_s == 1.0


def test_counter_jump_counts_lost_frames(codec: Codec) -> None:
    packer, parser = codec.packer("RIG"), codec.parser()
    assert parser.parse(0x110, packer.encode("RigSensors", SENSORS, counter=3), 0.0).ok
    parsed = parser.parse(0x110, packer.encode("RigSensors", SENSORS, counter=7), 0.008)
    assert parsed.ok
    assert parsed.lost_frames == 3
    assert parser.stats["RigSensors"].lost_frames == 3


def test_counter_wrap_15_to_0_is_accepted_without_loss(codec: Codec) -> None:
    packer, parser = codec.packer("RIG"), codec.parser()
    assert parser.parse(0x110, packer.encode("RigSensors", SENSORS, counter=15), 0.0).ok
    parsed = parser.parse(0x110, packer.encode("RigSensors", SENSORS, counter=0), 0.002)
    assert parsed.ok and parsed.counter == 0 and parsed.lost_frames == 0


def test_packer_counter_rolls_per_message_and_wraps(codec: Codec) -> None:
    packer, parser = codec.packer("DAEMON"), codec.parser()
    command = {
        "Mode": 0,
        "CurrentSetpoint": 0.0,
        "SensorCounterEcho": 0,
        "ControllerId": 0,
        "DesiredForce": 0.0,
    }
    actuator = {"Waveform": 0, "Amplitude": 0.0, "Frequency": 0.0}
    counters = []
    for i in range(40):
        counters.append(parser.parse(0x210, packer.encode("DamperCommand", command), i).counter)
        if i % 10 == 0:  # another message's counter must not disturb this one
            assert parser.parse(0x211, packer.encode("ActuatorCommand", actuator), i).ok
    assert counters == [i % 16 for i in range(40)]
    assert parser.stats["DamperCommand"].frames_ok == 40
    assert parser.stats["DamperCommand"].lost_frames == 0
    assert [parser.stats["ActuatorCommand"].last.counter] == [3]


def test_packer_refuses_e2e_missing_unknown_signals_and_other_senders(codec: Codec) -> None:
    packer = codec.packer("RIG")
    with pytest.raises(EncodeError, match="E2E signals .*E2E_Counter.* filled by the packer"):
        packer.encode("RigSensors", dict(SENSORS, E2E_Counter=1))
    with pytest.raises(EncodeError, match="E2E signals .*E2E_CRC"):
        packer.encode("RigSensors", dict(SENSORS, E2E_CRC=0))
    with pytest.raises(EncodeError, match="missing \\['Force'\\]"):
        packer.encode("RigSensors", {k: v for k, v in SENSORS.items() if k != "Force"})
    with pytest.raises(EncodeError, match="unknown \\['Speed'\\]"):
        packer.encode("RigSensors", dict(SENSORS, Speed=1.0))
    with pytest.raises(EncodeError, match="RIG does not send 'DamperCommand'"):
        packer.encode("DamperCommand", {})


@pytest.mark.parametrize(
    "signal,value",
    [
        ("CurrentSetpoint", 6.6),
        ("CurrentSetpoint", -0.001),
        ("Mode", 2),
        ("DesiredForce", 1e6),
        ("DesiredForce", math.nan),
        ("Mode", "BOOST"),
    ],
)
def test_packer_refuses_values_outside_the_dbc_range(
    codec: Codec, signal: str, value: float | str
) -> None:
    command = {
        "Mode": 1,
        "CurrentSetpoint": 1.0,
        "SensorCounterEcho": 0,
        "ControllerId": 1,
        "DesiredForce": 0.0,
    }
    with pytest.raises(EncodeError, match=f"DamperCommand: {signal}="):
        codec.packer("DAEMON").encode("DamperCommand", dict(command, **{signal: value}))


def test_packer_takes_value_table_labels(codec: Codec) -> None:
    packer = codec.packer("DAEMON")
    labelled = {
        "Mode": "ACTIVE",
        "CurrentSetpoint": 1.2345,
        "SensorCounterEcho": 3,
        "ControllerId": "NETWORK_INVERSION",
        "DesiredForce": 1200.0,
    }
    assert packer.encode("DamperCommand", labelled, counter=3).hex(" ") == VECTORS[3][3]


def test_unknown_id_and_wrong_length_are_rejected_and_counted(codec: Codec) -> None:
    parser = codec.parser()
    data = bytes.fromhex(VECTORS[0][3])
    unknown = parser.parse(0x123, data, 0.0)
    assert not unknown.ok and unknown.reason == "0x123: unknown id"
    short = parser.parse(0x110, data[:7], 0.0)
    assert not short.ok and short.reason == "RigSensors: wrong length 7 (want 8)"
    assert parser.unknown_id == 1
    assert parser.stats["RigSensors"].wrong_length == 1
    assert parser.last("RigSensors") is None


def test_value_outside_dbc_range_with_good_crc_is_rejected(codec: Codec) -> None:
    msg = codec.db.get_message_by_name("DamperCommand")
    raw = msg.encode(
        {
            "E2E_CRC": 0,
            "E2E_Counter": 0,
            "Mode": 5,
            "CurrentSetpoint": 0,
            "SensorCounterEcho": 0,
            "ControllerId": 0,
            "DesiredForce": 0,
        },
        strict=False,
    )
    data = bytes([compute_profile2_crc(raw, 0x61)]) + raw[1:]
    parser = codec.parser()
    parsed = parser.parse(0x210, data, 0.0)
    assert not parsed.ok
    assert parsed.reason == "DamperCommand: Mode raw 5 outside DBC range [0, 1]"
    assert parser.stats["DamperCommand"].decode_errors == 1
    assert parser.last("DamperCommand") is None


def test_bad_crc_never_updates_last_good_values(codec: Codec) -> None:
    packer, parser = codec.packer("RIG"), codec.parser()
    assert parser.parse(0x110, packer.encode("RigSensors", SENSORS), 1.0).ok
    bad = bytearray(packer.encode("RigSensors", dict(SENSORS, Force=-50.0)))
    bad[0] ^= 0xFF
    assert not parser.parse(0x110, bytes(bad), 2.0).ok
    assert parser.last("RigSensors").values["Force"] == pytest.approx(10.0)
    # The rejected frame's counter is not taken as reference either: the next one is no jump.
    nxt = parser.parse(0x110, packer.encode("RigSensors", SENSORS), 3.0)
    assert nxt.ok and nxt.lost_frames == 1


def test_parse_message_rejects_29_bit_ids(codec: Codec) -> None:
    parser = codec.parser()
    msg = codec.packer("RIG").message("RigSensors", SENSORS)
    assert msg.arbitration_id == 0x110 and not msg.is_extended_id
    assert parser.parse_message(msg, 0.0).ok
    msg.is_extended_id = True
    assert not parser.parse_message(msg, 0.1).ok
    assert parser.unknown_id == 1


# --- the fast path against cantools --------------------------------------------------------


def _in_range_values(codec: Codec, name: str) -> st.SearchStrategy[dict[str, float]]:
    msg = codec.db.get_message_by_name(name)
    strategies = {}
    for f in codec.layout(name).fields:
        sig = msg.get_signal_by_name(f.name)
        if sig.scale == 1 and sig.offset == 0:
            strategies[f.name] = st.integers(int(sig.minimum), int(sig.maximum))
        else:
            strategies[f.name] = st.floats(sig.minimum, sig.maximum, allow_nan=False)
    return st.fixed_dictionaries(strategies)


MESSAGES = list(CONTRACT_IDS)
FAST_CODEC = Codec()


@pytest.mark.parametrize("name", MESSAGES)
@settings(max_examples=300, deadline=None)
@given(data=st.data(), counter=st.integers(0, 15))
def test_fast_encode_and_decode_equal_cantools(
    name: str, data: st.DataObject, counter: int
) -> None:
    values = data.draw(_in_range_values(FAST_CODEC, name))
    layout = FAST_CODEC.layout(name)
    msg = FAST_CODEC.db.get_message_by_name(name)
    fast = FAST_CODEC.packer(layout.senders[0]).encode(name, values, counter=counter)
    slow = msg.encode(dict(values, **{layout.crc_signal: 0, layout.counter_signal: counter}))
    slow = bytes([compute_profile2_crc(slow, layout.data_id)]) + slow[1:]
    assert fast == slow
    parsed = FAST_CODEC.parser().parse(layout.frame_id, fast, 0.0)
    decoded = msg.decode(fast, decode_choices=False)
    assert parsed.ok
    assert parsed.values == {k: decoded[k] for k in layout.signal_names}


@pytest.mark.parametrize("name", MESSAGES)
@settings(max_examples=300, deadline=None)
@given(body=st.binary(min_size=7, max_size=7))
def test_fast_decode_of_any_valid_frame_equals_cantools(name: str, body: bytes) -> None:
    layout = FAST_CODEC.layout(name)
    data = bytes([compute_profile2_crc(b"\0" + body, layout.data_id)]) + body
    parsed = FAST_CODEC.parser().parse(layout.frame_id, data, 0.0)
    msg = FAST_CODEC.db.get_message_by_name(name)
    decoded = msg.decode(data, decode_choices=False)
    in_range = all(
        msg.get_signal_by_name(n).minimum <= decoded[n] <= msg.get_signal_by_name(n).maximum
        for n in layout.signal_names
    )
    assert parsed.ok == in_range
    if parsed.ok:
        assert parsed.values == {k: decoded[k] for k in layout.signal_names}


@settings(max_examples=500, deadline=None)
@given(payload=st.binary(min_size=2, max_size=8), data_id=st.integers(0, 255))
def test_crc8h2f_table_equals_cantools_autosar(payload: bytes, data_id: int) -> None:
    assert profile2_crc(payload, data_id) == compute_profile2_crc(payload, data_id)


# --- the DBC is the only source of the layout ------------------------------------------------


def _edited_codec(tmp_path, *edits: tuple[str, str]) -> Codec:
    text = DEFAULT_DBC_PATH.read_text()
    for old, new in edits:
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "edited.dbc"
    path.write_text(text)
    return Codec(path)


def test_data_id_is_read_from_the_dbc(codec: Codec, tmp_path) -> None:
    edited = _edited_codec(tmp_path, ('BA_ "DataID" BO_ 272 81;', 'BA_ "DataID" BO_ 272 153;'))
    assert edited.layout("RigSensors").data_id == 153
    data = edited.packer("RIG").encode("RigSensors", SENSORS, counter=1)
    assert check_profile2_crc(data, 153)
    parsed = codec.parser().parse(0x110, data, 0.0)
    assert not parsed.ok and "CRC mismatch" in parsed.reason


def test_e2e_signal_names_are_read_from_the_dbc(tmp_path) -> None:
    edited = _edited_codec(tmp_path, ("E2E_Counter", "SeqCnt"), ("E2E_CRC", "Chk"))
    layout = edited.layout("RigSensors")
    assert (layout.crc_signal, layout.counter_signal) == ("Chk", "SeqCnt")
    packer = edited.packer("RIG")
    assert packer.encode("RigSensors", VECTORS[0][2], counter=3).hex(" ") == VECTORS[0][3]
    with pytest.raises(EncodeError, match="SeqCnt"):
        packer.encode("RigSensors", dict(SENSORS, SeqCnt=2))


def test_signal_layout_and_scale_are_read_from_the_dbc(tmp_path) -> None:
    edited = _edited_codec(
        tmp_path,
        (
            " SG_ Force : 40|24@1- (0.01,0) [-83886.08|83886.07]",
            " SG_ Force : 40|24@1- (0.1,0) [-838860.8|838860.7]",
        ),
    )
    data = edited.packer("RIG").encode("RigSensors", dict(SENSORS, Force=1234.5))
    assert int.from_bytes(data[5:8], "little") == 12345
    assert edited.parser().parse(0x110, data, 0.0).values["Force"] == pytest.approx(1234.5)


def test_cycle_times_come_from_the_dbc(codec: Codec) -> None:
    assert codec.layout("RigSensors").period_s == pytest.approx(0.002)
    assert codec.layout("RigStatus").period_s == pytest.approx(0.1)


def test_value_tables_come_from_the_dbc(codec: Codec) -> None:
    assert codec.choices("RigStatus", "State") == {0: "BOOT", 1: "IDLE", 2: "RUNNING", 3: "FAULT"}
    assert codec.choices("DamperCommand", "ControllerId")[1] == "NETWORK_INVERSION"
    assert codec.choices("ActuatorCommand", "Waveform")[2] == "RANDOM"
    assert codec.choices("RigSensors", "Force") == {}


def test_contract_1_1_codes_stream_and_setpoint_timeout_round_trip(codec: Codec) -> None:
    """Waveform 4 STREAM and FaultCode 7 (actuator setpoint timeout) are in the value tables
    and inside their signals' ranges: a frame carrying either is sent and accepted."""
    assert codec.choices("ActuatorCommand", "Waveform")[4] == "STREAM"
    assert codec.choices("RigStatus", "FaultCode")[7] == "ACTUATOR_SETPOINT_TIMEOUT"
    stream = {"Waveform": "STREAM", "Amplitude": 0.03, "Frequency": 0.0}
    data = codec.packer("DAEMON").encode("ActuatorCommand", stream)
    parsed = codec.parser().parse(0x211, data, 0.0)
    assert parsed.ok, parsed.reason
    assert parsed.values["Waveform"] == 4
    status = dict(VECTORS[2][2], FaultCode="ACTUATOR_SETPOINT_TIMEOUT")
    parsed = codec.parser().parse(0x111, codec.packer("RIG").encode("RigStatus", status), 0.0)
    assert parsed.ok, parsed.reason
    assert parsed.values["FaultCode"] == 7


def test_codec_loads_with_cantools_strict(codec: Codec) -> None:
    assert cantools.database.load_file(str(DEFAULT_DBC_PATH), strict=True).messages
