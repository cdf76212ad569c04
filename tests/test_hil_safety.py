"""Safety of a hybrid-simulation run (issue 41; spec/hil.md, Safety): whatever ends it, the run
ends SAFE, the actuator HOLD then STOP (the firmware ramps the piston to rest), with a one-line
reason. Here: the firmware's stream faults (contract 1.1: FaultCode 7, the setpoint watchdog;
3, a setpoint clamped) reported while the firmware runs on. An in-process daemon on a
python-can virtual bus, the test playing the firmware frame by frame (`ScriptedRig`)."""

from __future__ import annotations

import time

import pytest

from mrrig.loop.samples import RigState
from tests.conftest import REPO
from tests.rig_harness import ScriptedRig

SCENARIO = REPO / "configs/hil/quarter-car-laws.toml"
HOLD_S = 0.05


class Frames:
    """The daemon's frames the scripted firmware receives, decoded in order: (name, values)."""

    def __init__(self, rig: ScriptedRig) -> None:
        self.rig = rig
        self.seen: list[tuple[str, dict]] = []
        self.waveforms = rig.codec.choices("ActuatorCommand", "Waveform")

    def _take(self, timeout_s: float, until_echo: int | None = None) -> dict | None:
        end = time.monotonic() + timeout_s
        while (left := end - time.monotonic()) > 0:
            msg = self.rig.bus.recv(timeout=left)
            if msg is None:
                return None
            p = self.rig.parser.parse(msg.arbitration_id, msg.data, time.monotonic())
            assert p.ok, p.reason
            self.seen.append((p.name, p.values))
            if p.name == "DamperCommand" and p.values["SensorCounterEcho"] == until_echo:
                return p.values
        return None

    def exchange(self, n: int = 1, x: float = 0.0) -> dict:
        """`n` sensor frames (x m, 100 N), each answered; the last DamperCommand."""
        for _ in range(n):
            c = self.rig.sensors(x=x, force=100.0)
            cmd = self._take(2.0, until_echo=c)
            assert cmd is not None, f"no command for sensor frame {c}"
        return cmd

    def settle(self) -> None:
        """The frames the daemon sent after its last command (its ActuatorCommand); only
        where the rig is not armed (no frame for 0.1 s: an armed one faults sensor_timeout)."""
        self._take(0.1)

    def mark(self) -> int:
        return len(self.seen)

    def since(self, mark: int, name: str) -> list[dict]:
        return [v for n, v in self.seen[mark:] if n == name]

    def waveforms_since(self, mark: int) -> list[str]:
        return [self.waveforms[int(v["Waveform"])] for v in self.since(mark, "ActuatorCommand")]


def _rig(tmp_path) -> ScriptedRig:
    """A `[hil]` daemon (the quarter-car plan's scenario, 2 s), armed by request; the frame
    age limit the harness's (0.1 s: the test thread plays the firmware)."""
    hil = {"scenario": str(SCENARIO), "duration_s": 2.0, "hold_s": HOLD_S}
    return ScriptedRig(tmp_path, overrides={"hil": hil, "loop": {"arm_on_start": False}})


@pytest.mark.parametrize(
    ("code", "label", "what"),
    [
        (7, "ACTUATOR_SETPOINT_TIMEOUT", "no valid ActuatorSetpoint for 20 ms"),
        (3, "STROKE_LIMIT", "it clamped a setpoint"),
    ],
)
def test_a_stream_fault_of_the_firmware_ends_the_run_safe_hold_then_stop(
    tmp_path, code, label, what
):
    """The firmware reports its stream fault in RigStatus with State RUNNING (it runs on,
    holding or clamping the piston): the run no longer follows the model, so the daemon faults
    `hil_safety` at that status, answers SAFE, sends no more setpoints, HOLD and, `hold_s`
    later, STOP. The same code while no run streams is no fault."""
    with _rig(tmp_path) as rig:
        d = rig.daemon
        frames = Frames(rig)
        rig.status(fault_code=code)  # no run streams: nothing to end
        frames.exchange(5)
        assert d.supervisor.state is RigState.IDLE and not d.hil.streaming
        assert rig.request({"cmd": "arm"})["ok"]
        assert frames.exchange(20)["Mode"] == 1  # ACTIVE
        assert d.hil.streaming and d.hil.setpoints_sent >= 19
        assert "STREAM" in frames.waveforms_since(0)
        rig.status(fault_code=code)
        mark = frames.mark()
        cmd = frames.exchange()
        status = d.status()
        assert status["state"] == "FAULT" and status["fault"] == "hil_safety", status
        reason = status["fault_reason"]
        assert reason.startswith(f"hil: the firmware reports FaultCode {code} ({label})")
        assert what in reason and "\n" not in reason
        assert cmd["Mode"] == 0 and cmd["CurrentSetpoint"] == 0.0  # SAFE 0 A
        assert not d.hil.streaming and d.hil.last_end in reason
        frames.exchange()  # the frames stream on (the next brings the pass's ActuatorCommand)
        assert frames.waveforms_since(mark) == ["HOLD"]
        sent = d.hil.setpoints_sent
        time.sleep(HOLD_S)
        frames.exchange(3)
        frames.settle()
        assert frames.waveforms_since(mark)[-1] == "STOP"  # the firmware ramps to rest
        # none for the frame of the fault or any after (the one before's may come after mark)
        after = {c["SensorCounterEcho"] for c in frames.since(mark, "DamperCommand")}
        assert not [
            s for s in frames.since(mark, "ActuatorSetpoint") if s["SensorCounterEcho"] in after
        ]
        assert d.hil.setpoints_sent == sent


def test_a_run_is_built_off_the_loop_so_its_first_frame_is_answered_in_time(tmp_path):
    """A run's excitation record takes 10 ms (a 20 s road) to seconds (an hour's, a building's)
    to compute, the first in a process half a second more (imports): built at the run's first
    frame, in the loop, it held that frame up past any frame age limit (the first run after
    start faulted `stale_frame` here, 1.5 s old) and, on a rig, past the firmware's 20 ms
    watchdog. It is built off the loop: at start, and by `set_hil` and `arm`'s preparation in
    the control thread. Here a 600 s road (0.2-0.4 s to build on this VM) set by `set_hil`:
    its run's first frames are answered ACTIVE, no fault."""
    with _rig(tmp_path) as rig:
        d = rig.daemon
        frames = Frames(rig)
        frames.exchange(5)
        reply = rig.request({"cmd": "set_hil", "duration_s": 600.0})
        assert reply["ok"] and reply["hil"]["duration_s"] == 600.0, reply
        assert rig.request({"cmd": "arm"})["ok"]
        cmd = frames.exchange(10)
        status = d.status()
        assert status["fault"] is None, status["fault_reason"]
        assert cmd["Mode"] == 1 and d.hil.streaming
        assert d.hil.step.scenario.duration_s == 600.0
