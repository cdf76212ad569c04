"""What `mrrig bench fuzz` sends: random JSON requests, hostile CAN frames, and request chains of
individually valid changes (mrrig/offline/bench/fuzz.py runs them against a live rig)."""

from __future__ import annotations

import json
import math
import random
from typing import Any

from mrrig.pycan import can

# a chain's CHAIN_LENGTH requests, each a step on from the one before (issue 32: six 4 mm steps
# took an armed rig from 15 mm to 39 mm)
CHAIN_LENGTH = 6
AMPLITUDE_STEP_M = 0.004
FREQUENCY_STEP_HZ = 0.5
FORCE_STEP_N = 1500.0


def random_json(rng: random.Random, depth: int = 0) -> Any:
    kind = rng.randrange(9 if depth < 6 else 6)
    if kind == 0:
        return None
    if kind == 1:
        return rng.random() < 0.5
    if kind == 2:
        return rng.choice([0, -1, 1, 2**63, -(2**31), rng.randrange(-1000, 1000)])
    if kind == 3:
        return rng.choice([0.0, -0.0, 1e308, -1e308, 5e-324, rng.uniform(-1e4, 1e4)])
    if kind == 4:
        return "".join(chr(rng.randrange(1, 0x2FFF)) for _ in range(rng.randrange(12)))
    if kind == 5:
        return rng.choice(["sine", "csv", "stop", "heaviside", "../../etc/passwd", ""])
    if kind in (6, 7):
        return {
            rng.choice(["kind", "path", "amplitude_n", "x", "name", "waveform", "zz"]): (
                random_json(rng, depth + 1)
            )
            for _ in range(rng.randrange(4))
        }
    return [random_json(rng, depth + 1) for _ in range(rng.randrange(4))]


COMMANDS = [
    "arm", "disarm", "reset", "status", "set_profile", "set_controller", "actuator", "set_model",
    "set_hil",
]  # fmt: skip
# set_hil's fields (a [hil] daemon's next runs): each refused in one line or a run the scenario
# takes (tests/test_hil_safety.py sends every one to a daemon that runs a scenario; the bench's
# runs none, and refuses each in one line)
SET_HIL_VALUES: dict[str, tuple[Any, ...]] = {
    "law": ("skyhook", "passive-hard", "clipped-optimal", "sky", "", 3, None, ["skyhook"]),
    "compensation": ("none", "model", "magic", 1, None),
    "duration_s": (
        math.nan, math.inf, -1.0, 0.0, 0.001, 0.002, 2.0, 3600.0, 3600.0001, 1e308, "10", True,
        None,
    ),
}  # fmt: skip


def random_request(rng: random.Random) -> str | bytes:
    """A request: mostly well-formed with random fields, some NaN, deep, huge or not JSON."""
    r = rng.random()
    if r < 0.05:
        return "[" * rng.randrange(1, 3000) + "]" * rng.randrange(1, 3000)
    if r < 0.08:
        return bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64)))
    if r < 0.10:
        return json.dumps({"cmd": "status", "pad": "x" * rng.randrange(2000, 200_000)})
    req: dict[str, Any] = {"cmd": rng.choice(COMMANDS)}
    if req["cmd"] == "set_profile":
        req["kind"] = rng.choice(["constant", "sine", "noise", "csv", "bouc_wen", "zenoh"])
        req["amplitude_n"] = rng.choice([0.0, 100.0, 1e308, -5.0, float("nan")])
        req["freq_hz"] = rng.choice([1.0, 0.0, 1e9])
    elif req["cmd"] == "set_controller":
        req["name"] = rng.choice(["heaviside", "constant", "network_inversion", "nope"])
        req["current_a"] = rng.choice([0.5, 1.9, 3.0, -1.0])
    elif req["cmd"] == "set_hil":
        for name, values in SET_HIL_VALUES.items():
            if rng.random() < 0.6:
                req[name] = rng.choice(values)
    elif req["cmd"] == "actuator":
        req["waveform"] = rng.choice(["sine", "random", "hold", "stop", "x"])
        req["amplitude_m"] = rng.choice([0.01, 0.012, 0.04, 1.0])
        req["frequency_hz"] = rng.choice([2.0, 3.0, 100.0])
    for _ in range(rng.randrange(3)):
        req[rng.choice(["path", "x", "kind", "name"])] = random_json(rng)
    return json.dumps(req)  # NaN and Infinity as Python writes them


def junk_frame(rng: random.Random, valid_sensors: bytes, bad_sensor: bool) -> can.Message:
    """A frame the daemon must not answer: a broken RigSensors frame (`bad_sensor`), else a
    29-bit or remote frame of any ID, or an 11-bit frame of no message of the DBC."""
    if bad_sensor:
        data = bytearray(valid_sensors)
        if rng.random() < 0.5:
            data[0] ^= 1 << rng.randrange(8)  # the CRC no longer fits
        else:
            data = data[: rng.randrange(8)]  # a wrong length
        return can.Message(arbitration_id=0x110, is_extended_id=False, data=bytes(data))
    kind = rng.randrange(3)
    dlc = rng.randrange(9)
    data = bytes(rng.randrange(256) for _ in range(dlc))
    if kind == 0:
        arb = rng.choice([0x110, 0x111, 0x210, 0x211, rng.randrange(1 << 29)])
        return can.Message(arbitration_id=arb, is_extended_id=True, data=data)
    if kind == 1:
        arb = rng.choice([0x110, 0x111, rng.randrange(1 << 11)])
        return can.Message(arbitration_id=arb, is_extended_id=False, is_remote_frame=True, dlc=dlc)
    arb = rng.choice([i for i in (0x0, 0x100, 0x112, 0x212, 0x7FF) if i not in (0x210, 0x211)])
    return can.Message(arbitration_id=arb, is_extended_id=False, data=data)


CHAINS = ("amplitude", "frequency", "set_profile", "force_ref")
# what an actuator chain starts from, armed (issue 32's rig: 15 mm at 2 Hz)
BASE_MOTION = {"cmd": "actuator", "waveform": "sine", "amplitude_m": 0.015, "frequency_hz": 2.0}


def chain(kind: str, rng: random.Random) -> list:
    """A chain of CHAIN_LENGTH changes, each a small step on from the one before: actuator
    requests (amplitude or frequency) from BASE_MOTION, set_profile requests, or force_ref
    values (rising past any range, to 1e300)."""
    sign = 1 if rng.random() < 0.75 else -1  # mostly up: the unsafe way
    steps = range(1, CHAIN_LENGTH + 1)
    if kind == "amplitude":
        a0 = BASE_MOTION["amplitude_m"]
        return [
            {**BASE_MOTION, "amplitude_m": round(max(a0 + sign * k * AMPLITUDE_STEP_M, 0.0), 5)}
            for k in steps
        ]
    if kind == "frequency":
        f0 = BASE_MOTION["frequency_hz"]
        return [
            {**BASE_MOTION, "frequency_hz": round(max(f0 + sign * k * FREQUENCY_STEP_HZ, 0.1), 3)}
            for k in steps
        ]
    forces = [k * FORCE_STEP_N for k in steps]
    if kind == "set_profile":
        shape = rng.choice(["constant", "sine", "noise"])
        field = "offset_n" if shape == "constant" else "amplitude_n"
        return [
            {"cmd": "set_profile", "kind": shape, field: sign * f if shape == "constant" else f}
            for f in forces
        ]
    return [sign * 2.0 * f for f in forces] + [sign * 1e300]
