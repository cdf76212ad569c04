"""The arm lease and the re-arm cap (issue 40): a client killed while the rig is armed leaves
it disarmed and still within the lease's timeout; a client's end stops the actuator; a faulty
bus aborts a step instead of being re-armed for ever, while an isolated fault is re-armed."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from mrrig.config import ControlSection
from mrrig.loop.lease import ArmLease
from mrrig.loop.samples import RigState
from mrrig.rigio.rearm import RearmLimit
from mrrig.typed_config import ConfigError, parse
from tests.conftest import REPO, stall, start, stop
from tests.live_rig import live_rig
from tests.rig_harness import ScriptedRig

RIG = "lease"


# --- the pieces ----------------------------------------------------------------------------
def test_a_lease_is_granted_renewed_by_its_id_and_ended():
    lease = ArmLease(2.0)
    assert not lease.held and lease.deadline == math.inf
    lease_id = lease.grant(10.0)
    assert lease.held and lease.deadline == 12.0
    assert lease.grant(11.0) == lease_id  # a second arm while armed holds the same rig
    assert not lease.renew("another", 11.5) and lease.deadline == 13.0
    assert lease.renew(lease_id, 12.5) and lease.deadline == 14.5
    lease.end()
    assert not lease.renew(lease_id, 13.0) and lease.deadline == math.inf


@pytest.mark.parametrize("value", [0.0, 0.1, 61.0, -1.0])
def test_a_lease_timeout_out_of_range_is_refused_naming_the_field(value):
    with pytest.raises(ConfigError, match=r"control\.lease_timeout_s: must be in \[0\.2, 60\] s"):
        parse(ControlSection, {"lease_timeout_s": value}, "rig.toml", "control")


def test_the_rearm_cap_ends_on_a_faulty_bus_and_says_so():
    limit = RearmLimit()  # 3 in any 10 s
    for t in (0.0, 0.6, 1.2):
        assert limit.allows(t)
        limit.rearmed(t)
    assert not limit.allows(1.8)
    assert limit.refusal() == (
        "faulty bus: 4 faults in 1.8 s (re-armed at most 3 times in any 10 s)"
    )
    isolated = RearmLimit()
    for t in (0.0, 11.0, 22.0, 33.0, 44.0):  # one fault every 11 s: each re-armed
        assert isolated.allows(t)
        isolated.rearmed(t)


# --- the daemon's side, in process ---------------------------------------------------------
def _remote(rig: ScriptedRig, req: dict) -> dict:
    """A request as the telemetry process hands it over (bytes): a Zenoh client's."""
    return rig.request(json.dumps(req).encode())


def _frames_for(rig: ScriptedRig, seconds: float, renew: str = "") -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if renew:
            assert _remote(rig, {"cmd": "renew", "lease": renew})["ok"]
        for _ in range(20):
            rig.exchange()


def test_an_unrenewed_lease_lapses_to_fault_with_the_actuator_stopped(tmp_path):
    motion = {"waveform": "sine", "amplitude_m": 0.005, "frequency_hz": 1.0}
    overrides = {"control": {"lease_timeout_s": 0.5}, "actuator": motion}
    with ScriptedRig(tmp_path, overrides=overrides) as rig:
        d = rig.daemon
        assert rig.request({"cmd": "disarm"})["ok"]
        assert d.actuator.waveform != "stop"
        armed = _remote(rig, {"cmd": "arm"})
        assert armed["ok"] and armed["lease_timeout_s"] == 0.5 and armed["lease"]
        _frames_for(rig, 1.0, renew=armed["lease"])  # renewed: it stays armed
        assert d.supervisor.state is RigState.ARMED
        _frames_for(rig, 1.0)  # not renewed
        status = rig.request({"cmd": "status"})["status"]
        assert status["state"] == "FAULT" and status["fault"] == "lease_lapsed", status
        assert status["fault_reason"].startswith("lease lapsed: no renewal for")
        assert status["leases_lapsed"] == 1
        assert d.actuator.waveform == "stop"
        late = _remote(rig, {"cmd": "renew", "lease": armed["lease"]})
        assert not late["ok"] and "ended, the rig is FAULT" in late["error"]


def test_an_in_process_arm_holds_no_lease(tmp_path):
    """characterize and validate arm the daemon of their own process: it ends with them."""
    with ScriptedRig(tmp_path, overrides={"control": {"lease_timeout_s": 0.2}}) as rig:
        assert rig.request({"cmd": "disarm"})["ok"]
        reply = rig.request({"cmd": "arm"})
        assert reply["ok"] and "lease" not in reply
        _frames_for(rig, 0.6)
        assert rig.daemon.supervisor.state is RigState.ARMED


# --- clients as processes against firmware_sim and a daemon -------------------------------
def _plan(tmp_path: Path, duration_s: float, name: str = "held") -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(
        textwrap.dedent(
            f"""
            [plan]
            name = "{name}"
            [[step]]
            name = "{name}"
            duration_s = {duration_s}
            settle_s = 0.5
            actuator = {{ waveform = "sine", amplitude_m = 0.005, frequency_hz = 1.0 }}
            controller = {{ name = "constant", current_a = 0.5 }}
            reference = {{ kind = "constant" }}
            criteria = {{ faults = "transport" }}
            """
        )
    )
    return path


class ActuatorWatch:
    """Every ActuatorCommand on the bus (a bus client sees the daemon's frames): its waveform."""

    def __init__(self, channel: str) -> None:
        from mrrig.rigio.canbus.bus import open_bus
        from mrrig.rigio.canbus.codec import Codec

        self.bus = open_bus("remote", channel)
        codec = Codec()
        self.parser = codec.parser()
        self.frame_id = codec.layout("ActuatorCommand").frame_id
        self.waveforms = codec.choices("ActuatorCommand", "Waveform")
        self.seen: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(timeout=0.1)
            if msg is not None and msg.arbitration_id == self.frame_id:
                p = self.parser.parse_message(msg)
                if p.ok:
                    wave = self.waveforms[int(p.values["Waveform"])]
                    self.seen.append((time.monotonic(), wave))

    def last(self) -> str | None:
        return self.seen[-1][1] if self.seen else None

    def wait_for(self, wave: str, timeout_s: float) -> float | None:
        """When `wave` became the latest waveform (monotonic), waiting up to `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            seen = list(self.seen)
            if seen and seen[-1][1] == wave:
                i = len(seen) - 1
                while i > 0 and seen[i - 1][1] == wave:
                    i -= 1
                return seen[i][0]
            time.sleep(0.02)
        return None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.bus.shutdown()


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("lease")
    with live_rig(tmp, RIG, rate_hz=50.0, daemon_args=("--no-record",)) as rig:
        yield rig


def _sim_pid() -> int:
    """firmware_sim among this process's children (live_rig started it)."""
    for task in Path(f"/proc/{os.getpid()}/task").iterdir():
        for pid in (task / "children").read_text().split():
            if b"firmware_sim" in Path(f"/proc/{pid}/cmdline").read_bytes():
                return int(pid)
    raise AssertionError("no firmware_sim among this process's children")


def _wait_state(rig, state: str, timeout_s: float) -> dict:
    deadline = time.monotonic() + timeout_s
    while (status := rig.status())["state"] != state:
        assert time.monotonic() < deadline, f"the rig is {status['state']}, not {state}: {status}"
        time.sleep(0.05)
    return status


def _mrrig_test(live, plan: Path, junit: Path) -> subprocess.Popen:
    args = ["--rig", RIG, "--zenoh-config", str(live.client_z), "--junit", str(junit)]
    return start(["-m", "mrrig", "test", str(plan), *args], stdout=subprocess.PIPE, text=True)


@pytest.mark.process
def test_a_plan_killed_mid_step_leaves_the_rig_disarmed_and_still(live, tmp_path):
    """SIGKILL of `mrrig test` while its step holds the rig armed (0.5 A, stroking): the
    lease lapses, the daemon faults `lease_lapsed` (SAFE) and stops the actuator."""
    from mrrig.api import Rig
    from mrrig.rigio.client import open_session
    from mrrig.rigio.rig_topics import keys

    watch = ActuatorWatch(live.channel)
    proc = _mrrig_test(live, _plan(tmp_path, 60), tmp_path / "r.xml")
    try:
        with Rig(RIG, zenoh_config=live.client_z) as r, open_session(live.client_z) as s:
            events = s.declare_subscriber(keys(RIG)["events"])
            _wait_state(r, "ARMED", 60.0)
            time.sleep(1.5)  # renewed past its timeout (2 s) while the plan lives
            assert r.status()["state"] == "ARMED"
            assert watch.last() == "SINE"
            proc.kill()
            t_kill = time.monotonic()
            status = _wait_state(r, "FAULT", 30.0)
            t_fault = time.monotonic()
            assert status["fault"] == "lease_lapsed", status
            assert "lease lapsed" in status["fault_reason"]
            t_stop = watch.wait_for("STOP", 10.0)
            assert t_stop is not None, watch.seen[-5:]
            reasons = []
            while (sample := events.try_recv()) is not None:
                reasons.append(json.loads(sample.payload.to_bytes()).get("reason", ""))
            events.undeclare()
            assert any(r.startswith("lease lapsed: no renewal for") for r in reasons), reasons
            print(
                f"SIGKILL -> FAULT lease_lapsed seen {t_fault - t_kill:.2f} s, actuator STOP on"
                f" the bus {t_stop - t_kill:.2f} s after (lease timeout 2 s):"
                f" {status['fault_reason']}"
            )
            r.reset()  # for the next test
    finally:
        stop(proc)
        watch.close()


@pytest.mark.process
@pytest.mark.parametrize("end", ["normal", "ctrl-c"])
def test_a_plans_end_stops_the_actuator(live, tmp_path, end):
    from mrrig.api import Rig

    watch = ActuatorWatch(live.channel)
    proc = _mrrig_test(live, _plan(tmp_path, 2 if end == "normal" else 60), tmp_path / "r.xml")
    try:
        with Rig(RIG, zenoh_config=live.client_z) as r:
            if end == "ctrl-c":
                _wait_state(r, "ARMED", 60.0)
                time.sleep(1.0)
                proc.send_signal(signal.SIGINT)
            else:
                while proc.poll() is None and r.status()["state"] != "ARMED":
                    time.sleep(0.05)
            assert watch.wait_for("SINE", 30.0) is not None, watch.seen[-5:]
            out, _ = proc.communicate(timeout=60)
            t_end = time.monotonic()
            assert watch.wait_for("STOP", 5.0) is not None, (watch.seen[-5:], out)
            time.sleep(ACTUATOR_REPEAT_S)  # the daemon repeats its actuator command: still STOP
            assert watch.last() == "STOP", watch.seen[-5:]
            assert r.status()["state"] != "ARMED"
            print(f"{end}: the last ActuatorCommand STOP, {time.monotonic() - t_end:.2f} s on")
    finally:
        stop(proc)
        watch.close()


ACTUATOR_REPEAT_S = 0.5  # longer than the daemon's period of ActuatorCommands


@pytest.mark.process
@pytest.mark.parametrize("faulty", [True, False])
def test_a_faulty_bus_aborts_the_step_an_isolated_fault_is_rearmed(live, tmp_path, faulty):
    """The simulator held up 0.1 s (a sensor timeout: a transport fault) every 0.6 s: the step
    is aborted `faulty bus` at the fourth fault; once: re-armed, and the step passes."""
    from mrrig.api import Rig

    junit = tmp_path / "r.xml"
    proc = _mrrig_test(live, _plan(tmp_path, 8, "faulty" if faulty else "isolated"), junit)
    sim = _sim_pid()
    stalls = 0
    try:
        with Rig(RIG, zenoh_config=live.client_z) as r:
            _wait_state(r, "ARMED", 60.0)
            time.sleep(1.0)
            while proc.poll() is None and stalls < (30 if faulty else 1):
                stall(sim, 0.1)
                stalls += 1
                time.sleep(0.5)
            out, _ = proc.communicate(timeout=60)
    finally:
        stop(proc)
    from tests.test_plans import case_properties, junit_cases

    (case,) = junit_cases(junit).values()
    props = case_properties(case)
    print(f"{stalls} stalls: {out.strip().splitlines()[-3:]} faults {props['faults']}")
    if faulty:
        assert props["verdict"] == "aborted", out
        assert "faulty bus: 4 faults in" in case.result[0].message, case.result[0].message
        assert len(props["faults"].split(",")) == 4, props
    else:
        assert props["verdict"] == "passed", out
        assert props["faults"], "the stall caused no transport fault"


@pytest.mark.process
def test_mrrig_arm_says_it_arms_for_one_lease_and_hold_keeps_the_rig_until_ctrl_c(live):
    from mrrig.api import Rig

    z = ["--rig", RIG, "--zenoh-config", str(live.client_z)]
    with Rig(RIG, zenoh_config=live.client_z) as r:
        r.reset()  # whatever an earlier test left
        once = subprocess.run(
            [sys.executable, "-m", "mrrig", "arm", *z], capture_output=True, text=True,
            timeout=60, cwd=REPO,
        )  # fmt: skip
        assert once.returncode == 0, once.stderr
        assert "armed for the lease only" in once.stderr and "--hold" in once.stderr
        status = _wait_state(r, "FAULT", 30.0)
        assert status["fault"] == "lease_lapsed", status
        r.reset()
        watch = ActuatorWatch(live.channel)
        held = start(["-m", "mrrig", "arm", "--hold", *z], stderr=subprocess.PIPE, text=True)
        try:
            _wait_state(r, "ARMED", 60.0)
            time.sleep(3.0)  # past the lease's timeout: renewed
            assert r.status()["state"] == "ARMED"
            held.send_signal(signal.SIGINT)
            assert held.wait(timeout=30) == 0, held.stderr.read()
            _wait_state(r, "IDLE", 10.0)
            assert watch.wait_for("STOP", 5.0) is not None, watch.seen[-5:]
        finally:
            stop(held)
            watch.close()
