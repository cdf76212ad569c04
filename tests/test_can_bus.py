"""python-can buses and the can_remote bridge between processes (no CAN in this kernel)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import uuid

import can
import pytest

from mrrig.rigio.canbus.bus import BusError, find_free_port, open_bus, start_bridge, stop_bridge
from mrrig.rigio.canbus.codec import Codec
from tests.conftest import SENSORS

RECV_TIMEOUT_S = 5.0

# The firmware's side, in its own process: answer each valid RigSensors with a DamperCommand
# echoing its counter, as the daemon must.
ECHO_CHILD = textwrap.dedent("""
    import sys
    from mrrig.rigio.canbus.bus import open_bus
    from mrrig.rigio.canbus.codec import Codec

    codec = Codec()
    parser, packer = codec.parser(), codec.packer("DAEMON")
    bus = open_bus("remote", sys.argv[1])
    print("ready", flush=True)
    answered = 0
    while answered < int(sys.argv[2]):
        msg = bus.recv(5.0)
        if msg is None:
            break
        parsed = parser.parse_message(msg)
        if parsed.ok and parsed.name == "RigSensors":
            bus.send(packer.message("DamperCommand", {
                "Mode": 1, "CurrentSetpoint": 0.5, "SensorCounterEcho": parsed.counter,
                "ControllerId": 1, "DesiredForce": parsed.values["Force"]}))
            answered += 1
    bus.shutdown()
    print(answered, parser.stats["RigSensors"].lost_frames, flush=True)
""")


def _frame(arbitration_id: int = 0x110, fill: int = 1) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, is_extended_id=False, data=[fill] * 8)


def test_virtual_buses_exchange_frames_without_own_echo() -> None:
    channel = f"test-{uuid.uuid4()}"
    a, b = open_bus("virtual", channel), open_bus("virtual", channel)
    try:
        a.send(_frame(), timeout=1.0)
        got = b.recv(1.0)
        assert got is not None and got.arbitration_id == 0x110 and not got.is_extended_id
        assert a.recv(0.05) is None
    finally:
        a.shutdown()
        b.shutdown()


def test_open_bus_failure_names_interface_and_channel() -> None:
    url = f"ws://127.0.0.1:{find_free_port()}/"
    with pytest.raises(BusError, match=f"interface='remote' channel='{url}'"):
        open_bus("remote", url)
    with pytest.raises(BusError, match="interface='no-such-interface' channel='x'"):
        open_bus("no-such-interface", "x")


def test_start_bridge_refuses_a_port_in_use(bridge: str) -> None:
    port = int(bridge.rsplit(":", 1)[1].strip("/"))
    with pytest.raises(BusError, match=f"port 127.0.0.1:{port} already in use"):
        start_bridge(port)


def test_bridge_broadcasts_to_other_clients_not_back_to_the_sender(bridge: str) -> None:
    a, b, c = (open_bus("remote", bridge) for _ in range(3))
    own = open_bus("remote", bridge, receive_own_messages=True)
    try:
        a.send(_frame(0x110, 1))
        for bus in (b, c, own):
            got = bus.recv(RECV_TIMEOUT_S)
            assert got is not None and bytes(got.data) == bytes([1] * 8)
        assert a.recv(0.2) is None
        own.send(_frame(0x111, 2))
        for bus in (a, b, c, own):
            got = bus.recv(RECV_TIMEOUT_S)
            assert got is not None and got.arbitration_id == 0x111
    finally:
        for bus in (a, b, c, own):
            bus.shutdown()


def test_two_processes_exchange_frames_through_the_bridge(bridge: str) -> None:
    n_frames = 30
    codec = Codec()
    packer, parser = codec.packer("RIG"), codec.parser()
    child = subprocess.Popen(
        [sys.executable, "-c", ECHO_CHILD, bridge, str(n_frames)],
        stdout=subprocess.PIPE,
        text=True,
    )
    bus = None
    try:
        assert child.stdout is not None
        assert child.stdout.readline().strip() == "ready"
        bus = open_bus("remote", bridge)
        echoes = []
        for i in range(n_frames):
            sent = packer.encode("RigSensors", dict(SENSORS, Force=float(i)))
            bus.send(can.Message(arbitration_id=0x110, is_extended_id=False, data=sent))
            reply = bus.recv(RECV_TIMEOUT_S)
            assert reply is not None, f"no reply to frame {i}"
            parsed = parser.parse_message(reply)
            assert parsed.ok and parsed.name == "DamperCommand", parsed.reason
            assert parsed.values["DesiredForce"] == pytest.approx(float(i))
            echoes.append(parsed.values["SensorCounterEcho"])
        out, _ = child.communicate(timeout=RECV_TIMEOUT_S)
    finally:
        if bus is not None:
            bus.shutdown()
        if child.poll() is None:
            child.kill()
            child.wait()
    assert echoes == [i % 16 for i in range(n_frames)]
    assert out.split() == [str(n_frames), "0"]
    assert parser.stats["DamperCommand"].lost_frames == 0


def test_dead_bridge_raises_bus_error_on_recv_and_send() -> None:
    port = find_free_port()
    proc = start_bridge(port)
    bus = open_bus("remote", f"ws://127.0.0.1:{port}/")
    try:
        stop_bridge(proc)
        with pytest.raises(BusError, match="lost"):
            bus.recv(RECV_TIMEOUT_S)
        with pytest.raises(BusError):
            bus.send(_frame())
    finally:
        bus.shutdown()
        stop_bridge(proc)
