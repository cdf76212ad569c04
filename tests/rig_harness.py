"""In-process rigs on python-can's virtual bus: a scripted one (frames built with the DBC packer)
and the simulator's own loop in a thread (`ThreadRig`).

The test plays the firmware frame by frame (exact control over counters, CRCs, flags and
timing) while the real `Daemon` runs its loop in a thread on the same python-can `virtual`
channel.
"""

from __future__ import annotations

import itertools
import threading
import time
from pathlib import Path

import can

from firmware_sim.config import load_config as load_sim_config
from firmware_sim.firmware import Firmware
from firmware_sim.runner import RunStats
from firmware_sim.runner import run as run_firmware
from mrrig.config import load_config
from mrrig.loop.daemon import Daemon
from mrrig.rigio.canbus.codec import Codec
from mrrig.rigio.canbus.profile import contract_profile
from mrrig.rigio.control import Pending
from mrrig.rigio.rig_session import RigSession, rig_overrides
from tests.conftest import REPO, rig_config
from tests.stall_proof import explain

_channels = itertools.count()


def write_config(
    tmp_path: Path, channel: str, timeout_periods: int, max_frame_age_s: float = 0.1
) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(
        f"""
[rig]
name = "test"
[bus]
interface = "virtual"
channel = "{channel}"
[loop]
realtime = false
arm_on_start = true
arm_settle_s = 0.0
timeout_periods = {timeout_periods}
max_frame_age_s = {max_frame_age_s}
[controller]
name = "constant"
current_a = 1.25
[reference]
kind = "constant"
offset_n = 300.0
[telemetry]
enabled = false
[recording]
enabled = false
"""
    )
    return path


class ScriptedRig:
    """The firmware's side of the bus, driven by the test."""

    def __init__(
        self,
        tmp_path: Path,
        timeout_periods: int = 50,
        config=None,
        max_frame_age_s: float = 0.1,
        overrides: dict[str, dict] | None = None,
        **daemon_kw,
    ):
        """`config(channel) -> path`: a daemon config of the test's own on that channel (else
        `write_config`'s); `overrides` ({section: {field: value}}) win over it; `daemon_kw`
        go to the `Daemon` (e.g. record_path)."""
        # a generous sensor timeout and frame age by default: the test thread plays the
        # firmware and can be slower than 2 ms per frame on a loaded machine; the timeout and
        # stall tests set the real ones
        self.channel = f"rig-harness-{next(_channels)}"
        if config is None:
            cfg_path = write_config(tmp_path, self.channel, timeout_periods, max_frame_age_s)
        else:
            cfg_path = config(self.channel)
        self.cfg = load_config(cfg_path, overrides)
        self.codec = Codec()
        self.packer = self.codec.packer("RIG")
        self.parser = self.codec.parser()
        # frames carry the timestamp the test gives them (`sensors(age_s=...)`): a frame
        # that waited in a queue, as after a stall
        self.bus = can.Bus(
            interface="virtual",
            channel=self.channel,
            receive_own_messages=False,
            preserve_timestamps=True,
        )
        self.daemon = Daemon(self.cfg, keep_batches=True, **daemon_kw)
        self.thread = threading.Thread(target=self.daemon.run, daemon=True)
        self.counter = 0
        self.unprompted_seen = 0  # SAFE commands of the daemon's own skipped by `command`

    def __enter__(self) -> ScriptedRig:
        self.thread.start()
        assert self.daemon.started.wait(timeout=10), "daemon loop did not start"
        time.sleep(0.05)  # its first ActuatorCommand
        self.drain()
        return self

    def __exit__(self, *exc) -> None:
        self.daemon.request_stop("test done")
        self.thread.join(timeout=5)
        self.bus.shutdown()
        assert not self.thread.is_alive(), "daemon did not stop"
        sent = self.daemon.counters["safe_commands_unprompted"]
        assert self.unprompted_seen <= sent, (
            f"{self.unprompted_seen} SAFE commands echoed another frame's counter, but the "
            f"daemon sent only {sent} on its own"
        )

    def drain(self) -> None:
        while self.bus.recv(timeout=0) is not None:
            pass

    def sensors(self, x=0.001, force=250.0, counter=None, crc_ok=True, age_s=0.0, **flags) -> int:
        """Send one RigSensors frame, received at the bus `age_s` ago; returns its counter."""
        values = {
            "ActuatorEnabled": 1,
            "LimitTripped": flags.get("LimitTripped", 0),
            "EStop": flags.get("EStop", 0),
            "SensorFault": flags.get("SensorFault", 0),
            "Displacement": x,
            "Force": force,
        }
        c = self.counter if counter is None else counter
        data = bytearray(self.packer.encode("RigSensors", values, counter=c))
        if not crc_ok:
            data[0] ^= 0xFF
        if counter is None:
            self.counter = (self.counter + 1) & 0xF
        self.bus.send(
            can.Message(
                arbitration_id=0x110,
                is_extended_id=False,
                data=bytes(data),
                timestamp=time.time() - age_s,
            )
        )
        return c

    def status(self, state="RUNNING", fault_code=0, timeouts=0) -> None:
        values = {
            "State": state,
            "CoilCurrent": 0.5,
            "DamperTemperature": 25.0,
            "FaultCode": fault_code,
            "CommandTimeouts": timeouts,
        }
        msg = self.packer.message("RigStatus", values)
        msg.timestamp = time.time()
        self.bus.send(msg)

    def command(self, timeout=0.5, expect: int | None = None) -> dict | None:
        """The next DamperCommand (decoded), skipping ActuatorCommands; None on timeout.

        With `expect` (the counter of the frame just sent): a SAFE command that echoes another
        counter is the daemon's own after a sensor timeout (the test thread was slower than
        the timeout between two frames) and is skipped; each one skipped must be one the
        daemon counted as sent unprompted (checked on exit). An ACTIVE one is returned."""
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            msg = self.bus.recv(timeout=left)
            if msg is None:
                return None
            if msg.arbitration_id == 0x210:
                p = self.parser.parse(msg.arbitration_id, msg.data, time.monotonic())
                assert p.ok, p.reason
                v = p.values
                if expect is not None and v["SensorCounterEcho"] != expect and v["Mode"] == 0:
                    self.unprompted_seen += 1
                    continue
                return v
        return None

    def request(self, req: dict, max_frames: int = 200) -> dict:
        """A control request, answered by the loop between frames: sensor frames stream (and
        are answered) until the reply comes, as they would on the rig."""
        pending = Pending()
        self.daemon.submit(req, pending)
        # prepared first: the loop applies it before the next frame's cycle
        end = time.monotonic() + 5.0
        while not (pending.done() or self.daemon.control.ready()) and time.monotonic() < end:
            time.sleep(0.001)
        for _ in range(max_frames):
            if pending.done():
                return pending.reply
            self.exchange()
            # its reply comes from the control thread: a moment after the frame, not a frame
            end = time.monotonic() + 0.05
            while not pending.done() and time.monotonic() < end:
                time.sleep(0.001)
        return pending.wait(1.0)

    def exchange(self, **kw) -> dict:
        """One sensor frame and the command that answers it."""
        c = self.sensors(**kw)
        cmd = self.command(expect=c)
        assert cmd is not None, f"no command for sensor frame {c}"
        assert cmd["SensorCounterEcho"] == c
        return cmd


class ThreadRig:
    """firmware_sim's firmware and loop in a thread, on a python-can `virtual` channel, beside
    a daemon in a `RigSession` of the same process (on the virtual bus, its loop is a thread).
    `hold(s)` holds the simulator's loop up once, as a scheduler would; its RunStats measure
    that stall like any other."""

    def __init__(self) -> None:
        self.channel = f"thread-rig-{next(_channels)}"
        cfg = load_sim_config(REPO / "configs/sim.toml")
        self.firmware = Firmware(cfg, contract_profile(), ())
        self.bus = can.Bus(interface="virtual", channel=self.channel, receive_own_messages=False)
        self.stats = RunStats()
        self._stop = False
        self._hold_s = 0.0
        t = cfg.timing
        self.thread = threading.Thread(
            target=run_firmware,
            args=(self.firmware, self.bus, self.stats),
            kwargs=dict(
                lead_s=t.lead_s,
                spin_s=t.spin_s,
                send_timeout_s=cfg.bus.send_timeout_s,
                should_stop=self._should_stop,
            ),
            daemon=True,
        )

    def _should_stop(self) -> bool:
        if self._hold_s:
            hold_s, self._hold_s = self._hold_s, 0.0
            time.sleep(hold_s)
        return self._stop

    def hold(self, seconds: float) -> None:
        """The simulator's loop stops for `seconds` once, at its next period."""
        self._hold_s = seconds

    def __enter__(self) -> ThreadRig:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop = True
        self.thread.join(timeout=5)
        self.bus.shutdown()

    def explain_faults(self, session: RigSession) -> None:
        """Every fault of the session's daemon inside a stall this rig's loop measured."""
        st = self.stats.summary(self.firmware, 1.0, 0.0)
        session.check_alive()  # the events up to now
        faults = [e for e in session.events if e["kind"] == "fault"]
        explain(st, faults, session.clock_t0_s)

    def daemon_config(self, tmp_path: Path, **sections):
        # one process, two 500 Hz loops sharing the GIL: a generous sensor timeout
        path = rig_config(tmp_path, self.channel, None)
        over = rig_overrides(
            None,
            True,
            bus={"interface": "virtual"},
            loop={"realtime": False, "timeout_periods": 25, "max_frame_age_s": 0.05},
            **sections,
        )
        return load_config(path, over)
