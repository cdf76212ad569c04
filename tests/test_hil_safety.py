"""Safety of a hybrid-simulation run (issue 41; spec/hil.md, Safety): whatever ends it, the run
ends SAFE, the actuator HOLD then STOP (the firmware ramps the piston to rest), with a one-line
reason. Here: the firmware's stream faults (contract 1.1: FaultCode 7, the setpoint watchdog;
3, a setpoint clamped) reported while the firmware runs on. An in-process daemon on a
python-can virtual bus, the test playing the firmware frame by frame (`ScriptedRig`)."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from mrrig.api.hil import HilResult, judge
from mrrig.hil.reference import run_reference
from mrrig.loop.samples import SAMPLE_DTYPE, RigState
from mrrig.plans.criteria import failures, measure
from mrrig.plans.hil_step import hil_failures, hil_numbers, hil_tries, step_scenario
from mrrig.plans.plan import load_plan
from tests.conftest import REPO
from tests.rig_harness import ScriptedRig

SCENARIO = REPO / "configs/hil/quarter-car-laws.toml"
HOLD_S = 0.05
TIMEOUT_PERIODS = 250  # 0.5 s


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
        """The frames the daemon sent after its last command (its ActuatorCommand), 0.1 s
        without a sensor frame."""
        self._take(0.1)

    def mark(self) -> int:
        return len(self.seen)

    def since(self, mark: int, name: str) -> list[dict]:
        return [v for n, v in self.seen[mark:] if n == name]

    def waveforms_since(self, mark: int) -> list[str]:
        return [self.waveforms[int(v["Waveform"])] for v in self.since(mark, "ActuatorCommand")]


def _rig(tmp_path) -> ScriptedRig:
    """A `[hil]` daemon (the quarter-car plan's scenario, 2 s), armed by request; the frame
    age limit the harness's (0.1 s: the test thread plays the firmware), the sensor timeout
    0.5 s (no frames flow while the harness waits for a request's preparation: an arm's
    builds its run)."""
    hil = {"scenario": str(SCENARIO), "duration_s": 2.0, "hold_s": HOLD_S}
    overrides = {"hil": hil, "loop": {"arm_on_start": False}}
    return ScriptedRig(tmp_path, timeout_periods=TIMEOUT_PERIODS, overrides=overrides)


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


def test_an_arm_after_a_transport_fault_starts_the_scenario_from_its_first_frame(tmp_path):
    """A transport fault (here the sensor frames stop: `sensor_timeout`) ends the run at
    once, HOLD then STOP with no frame to answer (the run ended only at a next frame: until
    then the daemon repeated STREAM, and a HOLD sent then stayed: the piston held); an arm
    after the `reset` (a client's re-arm: `mrrig hil --tries`, a plan's hil step) starts a
    fresh run at the scenario's frame 0, never the old one where it stopped."""
    with _rig(tmp_path) as rig:
        d = rig.daemon
        frames = Frames(rig)
        assert rig.request({"cmd": "arm"})["ok"]
        frames.exchange(30)
        k_before = d.hil.step.substructure.k
        assert k_before >= 29
        mark = frames.mark()
        time.sleep(0.8)  # no sensor frame for longer than the timeout (0.5 s), and hold_s
        status = d.status()
        assert status["fault"] == "sensor_timeout" and not d.hil.streaming, status
        frames.settle()
        waves = [w for w, _ in itertools.groupby(frames.waveforms_since(mark))]  # repeats
        assert waves[-2:] == ["HOLD", "STOP"], waves
        assert rig.request({"cmd": "reset"})["ok"]
        frames.exchange(3)
        armed = rig.request({"cmd": "arm"})
        assert armed["ok"], armed
        frames.exchange(5)
        assert d.status()["fault"] is None and d.hil.streaming and d.hil.runs == 2
        assert d.hil.step.substructure.k <= 6 < k_before


def _hil_plan(tmp_path, faults: str):
    path = tmp_path / f"plan-{faults}.toml"
    path.write_text(
        f"""
[plan]
name = "one-law"
[[step]]
name = "skyhook"
duration_s = 2
hil = {{ scenario = "{SCENARIO}", law = "skyhook" }}
criteria = {{ agreement_pct_max = 3.0, faults = "{faults}" }}
"""
    )
    return load_plan(path).steps[0]


def _run(reference, frames: int, end: dict) -> HilResult:
    """A run's telemetry as the daemon records it over the scenario's first `frames`, from the
    reference (tracking perfectly: x_m = x_c), judged as `mrrig hil` does; `end` its status."""
    s = np.zeros(frames, SAMPLE_DTYPE)
    s["state"] = RigState.ARMED
    s["hil_k"] = np.arange(frames)
    s["hil_x_c"] = s["x"] = reference.stroke_m[:frames]
    s["hil_acc"] = reference.outputs["body_acceleration_m_s2"][:frames]
    s["hil_load_n"] = reference.outputs["tyre_load_n"][:frames]
    judged, missing, t, errors, figures = judge(s, reference)
    return HilResult(judged, missing, t, errors, figures, 0.0, end, samples=s)


def test_a_hil_step_is_judged_on_its_whole_run_whatever_faults_it_allows(tmp_path):
    """With `faults = "transport"` a hil step whose run a transport fault ended at a quarter
    of the scenario passed: the quarter agreed with the reference's same frames, and the fault
    was allowed. The step judges only a whole run: a run a transport fault ended is run again
    from the scenario's start (up to 3 runs, each fault counted), and one that did not play
    out fails the step, saying where and why it ended."""
    step = _hil_plan(tmp_path, "transport")
    reference = run_reference(step_scenario(step))
    n = reference.stroke_m.size
    cut = n // 4
    why = "no sensor frame for 120.0 ms"
    end = {
        "fault": "sensor_timeout",
        "fault_reason": why,
        "hil": {"k": cut, "steps": n, "ended": why},
    }
    run = _run(reference, cut, end)
    numbers = hil_numbers("skyhook", run)
    assert all(abs(p) < 1e-9 for p in numbers.agreement_pct().values())  # the part agrees
    reasons = failures(step.criteria, measure(run.samples, 0.0), ["sensor_timeout"])
    reasons += hil_failures(step.criteria, numbers)
    assert reasons == [f"the run ended at frame {cut} of {n}: {why}"]
    whole = _run(reference, n, {"fault": None, "hil": {"k": n, "steps": n, "ended": "played out"}})
    assert hil_failures(step.criteria, hil_numbers("skyhook", whole)) == []
    assert hil_tries(step) == 3 and hil_tries(_hil_plan(tmp_path, "none")) == 1


# ---- set_hil, hostile (the values `mrrig bench fuzz` sends) -------------------------------
def _set_hil_payloads() -> list[dict]:
    """Each of the fuzz's set_hil values alone, then 40 of its random set_hil requests."""
    import json
    import random

    from mrrig.offline.bench.fuzz_inputs import SET_HIL_VALUES, random_request

    out = [{"cmd": "set_hil", name: v} for name, vs in SET_HIL_VALUES.items() for v in vs]
    rng = random.Random(41)
    while len(out) < 80:
        raw = random_request(rng)
        req = json.loads(raw) if isinstance(raw, str) and '"set_hil"' in raw else None
        if isinstance(req, dict) and req.get("cmd") == "set_hil":
            out.append(req)
    return out


def test_a_hostile_set_hil_is_one_line_or_a_run_the_scenario_takes_and_never_while_armed(
    tmp_path,
):
    """Every set_hil value of `mrrig bench fuzz` (NaN, inf, 1e308, a wrong type, an unknown
    law, unknown fields) sent as a client's bytes to a `[hil]` daemon: refused in one line
    naming the field, or taken as a checked scenario (a duration in [period_s, 3600] s, a law
    the substructure has) whose run is built before the loop sees it; while armed, each one
    refused, and the run and scenario in force unchanged."""
    import json
    import math

    from mrrig.config import load_config
    from mrrig.hil.laws import LAWS
    from mrrig.loop.daemon import Daemon, build_controller, build_reference
    from mrrig.rigio.control import Preparer, RequestError, parse_request
    from tests.conftest import rig_config

    config = rig_config(tmp_path, "unused", None, hil={"scenario": str(SCENARIO)})
    d = Daemon(load_config(config, {"controller": {"name": "constant", "current_a": 0.5}}))
    prep = Preparer(d, build_controller, build_reference)
    payloads = _set_hil_payloads()
    taken = refused = 0
    for req in payloads:
        raw = json.dumps(req).encode()  # NaN, Infinity as Python writes them
        try:
            change = prep.prepare(parse_request(raw))
        except RequestError as exc:
            text = str(exc)
            assert "\n" not in text and len(text) < 300, text
            assert any(f"{name}:" in text for name in req if name != "cmd"), (req, text)
            refused += 1
            continue
        s = change.hil_scenario
        s.check()
        assert math.isfinite(s.duration_s) and s.period_s <= s.duration_s <= 3600.0
        assert s.law in LAWS and change.hil_run.scenario is s
        d.requests.apply(change)
        assert d.hil.scenario is s and d.hil.run_ready()
        taken += 1
    print(f"set_hil: {len(payloads)} sent, {taken} taken, {refused} refused in one line")
    assert taken and refused
    ok, why, _ = d.supervisor.arm(d.now())
    assert ok, why
    in_force = d.hil.scenario
    for req in payloads:
        try:
            parsed = parse_request(json.dumps(req).encode())
        except RequestError:
            continue  # refused as it is read (NaN, too large), before any state
        with pytest.raises(RequestError, match=r"^set_hil only when not armed"):
            prep.prepare(parsed)
    assert d.hil.scenario is in_force
