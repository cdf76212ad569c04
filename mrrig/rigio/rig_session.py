"""`RigSession`: the daemon's loop driven by control requests between runs (never per frame).
`mrrig characterize` and `mrrig validate` use it.

The loop runs in a process of its own (`ProcessLoop`): the tool's offline work (files, numpy,
a recording) never holds the loop's interpreter lock, and a tool that dies takes its loop down
with it (the loop stops on the closed pipe, SAFE). A loop on python-can's `virtual` bus, which
lives inside one process, runs in a thread of this process instead (`ThreadLoop`): tests.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any, Protocol

import numpy as np

from mrrig.config import DaemonConfig
from mrrig.errors import MrrigError
from mrrig.loop import memory
from mrrig.loop.daemon import Daemon
from mrrig.loop.realtime import favour_thread
from mrrig.loop.samples import SAMPLE_DTYPE, RigState

log = logging.getLogger(__name__)

# The rig must stream sensor frames this soon after the loop starts; the daemon's start-up
# (its process's imports, mlockall, rerun's libraries being mapped) is inside it.
FIRST_FRAME_TIMEOUT_S = 20.0
# Disarmed (SAFE) time before the first arm: the loop's first few hundred ms after start-up
# can stall past the firmware's 20 ms watchdog.
WARMUP_S = 1.0
# A loop process answers a call this soon (a control request waits on the loop's next frames).
CALL_TIMEOUT_S = 10.0
# The loop's own process: its start (imports, the model, the bus) and its stop.
PROCESS_START_TIMEOUT_S = 60.0
PROCESS_STOP_TIMEOUT_S = 10.0
# the loop process's pipe server: a CFS weight of about 9x a normal process's (CI: validate's
# loop answered a frame 10.8 ms late, its own thread never on a run queue)
SERVER_NICE = -10


class RigError(MrrigError, RuntimeError):
    """The rig or the daemon cannot go on (no sensor frames, a refused request, a dead loop)."""


class RunFailed(RigError):
    """One run did not give clean data (a fault, missing samples); it may be tried again.
    `fault`: the daemon's fault event that failed it, where one did."""

    def __init__(self, message: str, fault: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.fault = fault


class Interrupted(Exception):
    """SIGINT or SIGTERM arrived: stop safely."""


@dataclass
class Snapshot:
    """The loop as a poll saw it, with what it handed over since the last poll."""

    state: RigState
    reason: str  # the supervisor's: why it is in that state
    sensor_frames_valid: int
    t0: float  # the loop's time zero on CLOCK_MONOTONIC (time.perf_counter)
    running: bool  # the loop has not ended
    error: str  # why the loop ended, where it ended
    chunks: list[np.ndarray] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)


class Loop(Protocol):
    """Where the daemon's loop runs: started, asked, polled, stopped."""

    def start(self) -> None: ...

    def request(self, req: dict[str, Any]) -> dict[str, Any]: ...

    def poll(self, n_chunks: int, n_events: int) -> Snapshot: ...

    def stalls(self) -> dict[str, Any]: ...

    def stop(self, reason: str) -> None: ...


class ThreadLoop:
    """The daemon's loop in a thread of this process."""

    def __init__(self, cfg: DaemonConfig) -> None:
        self.daemon = Daemon(cfg, keep_batches=True)
        self._thread = threading.Thread(target=self._run, name="mrrig-loop", daemon=True)
        self._error = ""

    def _run(self) -> None:
        try:
            self.daemon.run()
        except BaseException as exc:  # noqa: BLE001 - reported by the next poll
            self._error = f"{type(exc).__name__}: {exc}"

    def start(self) -> None:
        self._thread.start()

    def request(self, req: dict[str, Any]) -> dict[str, Any]:
        return self.daemon.request(req)

    def poll(self, n_chunks: int, n_events: int) -> Snapshot:
        d, thread = self.daemon, self._thread
        running = thread.is_alive() or thread.ident is None
        return Snapshot(
            d.supervisor.state,
            d.supervisor.reason,
            d.counters["sensor_frames_valid"],
            d.t0,
            running,
            "" if running else self._error or d.stop_reason or "unknown",
            d.batches.handed_over(n_chunks),
            d.events[n_events:],
        )

    def stalls(self) -> dict[str, Any]:
        return self.daemon.kernel_stalls.result()

    def stop(self, reason: str) -> None:
        if self._thread.is_alive():
            self.daemon.request_stop(reason)
            self._thread.join(timeout=PROCESS_STOP_TIMEOUT_S)
            if self._thread.is_alive():
                log.error("the daemon loop did not stop in %g s", PROCESS_STOP_TIMEOUT_S)


def _serve(cfg: DaemonConfig, conn: Connection, log_level: int) -> None:
    """The loop process: the daemon's loop in a thread, this thread answering the tool's calls
    until the tool says stop or its end of the pipe closes (then the loop stops, SAFE)."""
    # the tool stops this process: a Ctrl-C at the terminal reaches the tool, which closes
    # the session (disarm, actuator stop) before this loop ends
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        loop = ThreadLoop(cfg)
    except Exception as exc:  # noqa: BLE001 - the tool reports it, one line
        conn.send(("error", f"the daemon did not start: {type(exc).__name__}: {exc}"))
        return
    # a SIGTERM to this process alone (or to the tool's process group) stops the loop SAFE
    signal.signal(signal.SIGTERM, lambda _s, _f: loop.daemon.request_stop("SIGTERM"))
    loop.start()
    # this thread unpickles the tool's calls and pickles the loop's samples, holding the GIL
    favour_thread(SERVER_NICE, "the loop process's pipe server")
    conn.send(("ok", None))
    reason = "the tool's process ended"
    while True:
        try:
            call, arg = conn.recv()
        except (EOFError, OSError):
            break
        if call == "stop":
            reason = arg
            break
        try:
            if call == "request":
                reply = loop.request(arg)
            elif call == "stalls":
                reply = loop.stalls()
            else:
                reply = loop.poll(*arg)
        except Exception as exc:  # noqa: BLE001 - the tool reports it
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
            continue
        conn.send(("ok", reply))
    loop.stop(reason)
    try:
        conn.send(("ok", None))
    except OSError:
        pass


@contextmanager
def _loop_environment() -> Iterator[None]:
    """The loop process's environment (memory.ENVIRONMENT: before its numpy loads OpenBLAS),
    this process's own left as it was."""
    saved = dict(os.environ)
    memory.set_environment()
    try:
        yield
    finally:
        os.environ.clear()
        os.environ.update(saved)


class ProcessLoop:
    """The daemon's loop in a process of its own, asked over a pipe."""

    def __init__(self, cfg: DaemonConfig) -> None:
        ctx = multiprocessing.get_context("spawn")  # a fresh interpreter: no forked threads
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_serve,
            args=(cfg, child, logging.getLogger().getEffectiveLevel()),
            name="mrrig-loop",
            daemon=True,
        )
        self._child = child
        self._lock = threading.Lock()

    def _recv(self, timeout_s: float, what: str) -> Any:
        if not self._conn.poll(timeout_s):
            raise RigError(f"the daemon's process did not answer {what} in {timeout_s:g} s")
        try:
            kind, value = self._conn.recv()
        except (EOFError, OSError):
            code = self._proc.exitcode
            raise RigError(f"the daemon's process ended (exit code {code})") from None
        if kind == "error":
            raise RigError(value)
        return value

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def start(self) -> None:
        with _loop_environment():
            self._proc.start()
        self._child.close()
        self._recv(PROCESS_START_TIMEOUT_S, "its start")
        log.info("the daemon's loop runs in process %d", self._proc.pid)

    def _call(self, call: str, arg: Any) -> Any:
        with self._lock:
            try:
                self._conn.send((call, arg))
            except (BrokenPipeError, OSError):
                code = self._proc.exitcode
                raise RigError(f"the daemon's process ended (exit code {code})") from None
            return self._recv(CALL_TIMEOUT_S, call)

    def request(self, req: dict[str, Any]) -> dict[str, Any]:
        return self._call("request", req)

    def poll(self, n_chunks: int, n_events: int) -> Snapshot:
        return self._call("poll", (n_chunks, n_events))

    def stalls(self) -> dict[str, Any]:
        return self._call("stalls", None)

    def stop(self, reason: str) -> None:
        if self._proc.is_alive():
            try:
                self._call("stop", reason)
            except RigError as exc:
                log.error("stopping the daemon's process: %s", exc)
        self._proc.join(timeout=PROCESS_STOP_TIMEOUT_S)
        if self._proc.is_alive():
            log.error("the daemon's process did not stop in %g s: killed", PROCESS_STOP_TIMEOUT_S)
            self._proc.kill()
            self._proc.join()
        self._conn.close()


class RigSession:
    """The daemon's loop, driven by control requests.

    Requests are applied by the loop between frames (`Daemon.request`), a few times per run;
    the samples are those the loop has already handed over (never its live buffer). The loop
    runs in a process of its own, or in a thread of this one on python-can's `virtual` bus.
    """

    def __init__(self, cfg: DaemonConfig) -> None:
        self.cfg = cfg
        self.period_s = cfg.loop.period_s
        self.loop: Loop = ThreadLoop(cfg) if cfg.bus.interface == "virtual" else ProcessLoop(cfg)
        self._started = False
        self._n_chunks = 0  # the loop's batches seen so far
        self._n_events = 0
        self._chunks: list[np.ndarray] = []  # seen, not yet taken
        self._new_events: list[dict] = []  # seen, not yet taken
        self.events: list[dict] = []  # every event of the loop so far
        self._latest_t = -math.inf  # of the last sample handed over
        self._last: Snapshot | None = None

    def __enter__(self) -> RigSession:
        self.loop.start()
        self._started = True
        try:
            self._wait_first_frame()
        except BaseException:
            self.close()
            raise
        return self

    def _wait_first_frame(self) -> None:
        end = time.monotonic() + FIRST_FRAME_TIMEOUT_S
        while self._poll().sensor_frames_valid == 0:
            if time.monotonic() > end:
                raise RigError(
                    f"no sensor frames from the rig in {FIRST_FRAME_TIMEOUT_S:g} s on "
                    f"{self.cfg.bus.interface}/{self.cfg.bus.channel} (is the firmware running?)"
                )
            time.sleep(0.02)
        end = time.monotonic() + WARMUP_S
        while time.monotonic() < end:
            self.check_alive()
            time.sleep(0.05)

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _poll(self) -> Snapshot:
        snap = self.loop.poll(self._n_chunks, self._n_events)
        self._n_chunks += len(snap.chunks)
        self._n_events += len(snap.events)
        self._chunks += snap.chunks
        if snap.chunks:
            self._latest_t = float(snap.chunks[-1]["t"][-1])
        self._new_events += snap.events
        self.events += snap.events
        self._last = snap
        if not snap.running:
            raise RigError(f"the daemon loop stopped: {snap.error}")
        return snap

    def check_alive(self) -> None:
        self._poll()

    def now(self) -> float:
        """The daemon's clock (the samples' `t`), s."""
        return time.perf_counter() - self.clock_t0_s

    def request(self, **req: Any) -> dict[str, Any]:
        """A control request; RigError when refused."""
        reply = self.ask(req)
        if not reply["ok"]:
            raise RigError(f"{req['cmd']}: {reply['error']}")
        return reply

    def ask(self, req: dict[str, Any]) -> dict[str, Any]:
        """A control request; the daemon's reply, refused or not."""
        return self.loop.request(req)

    def state(self) -> RigState:
        return self._poll().state

    def wait_until(self, t_s: float, stop: threading.Event, fail_on_fault: bool = True) -> None:
        """Sleep until daemon time `t_s`; Interrupted on `stop`, RunFailed on a daemon FAULT."""
        while (left := t_s - self.now()) > 0:
            if stop.wait(min(left, 0.05)):
                raise Interrupted
            snap = self._poll()
            if fail_on_fault and snap.state is RigState.FAULT:
                raise RunFailed(f"fault: {snap.reason}", self.last_fault())

    def last_fault(self) -> dict[str, Any] | None:
        """The daemon's latest fault event (its `t` on the daemon's clock)."""
        return next((e for e in reversed(self.events) if e["kind"] == "fault"), None)

    def kernel_stalls(self) -> dict[str, Any]:
        """The loop's own stalls so far as the kernel measured them (the daemon summary's
        `kernel_stalls`, times on the daemon's clock)."""
        return self.loop.stalls()

    @property
    def clock_t0_s(self) -> float:
        """The daemon's time zero on CLOCK_MONOTONIC: its times beside another process's (set
        when its loop starts, before the first sensor frame that `__enter__` waits for)."""
        return (self._last or self._poll()).t0

    def take(self, t0_s: float, t1_s: float) -> tuple[np.ndarray, list[dict]]:
        """Samples with t in [t0_s, t1_s) and the events since the last call.

        Older samples are dropped for good: windows come in time order.
        """
        self._poll()
        new, self._chunks = self._chunks, []
        events, self._new_events = self._new_events, []
        if not new:
            return np.zeros(0, dtype=SAMPLE_DTYPE), events
        s = np.concatenate(new)
        return s[(s["t"] >= t0_s) & (s["t"] < t1_s)], events

    def latest_t(self) -> float:
        self._poll()
        return self._latest_t

    def wait_samples(self, t_s: float, stop: threading.Event) -> None:
        """Until the loop has handed over a sample at or after `t_s` (or a short timeout)."""
        end = time.monotonic() + 1.0
        while self.latest_t() < t_s and time.monotonic() < end:
            if stop.wait(0.01):
                raise Interrupted

    def close(self) -> None:
        """SAFE, actuator STOP (the daemon's shutdown sends both), loop stopped."""
        if not self._started:
            return
        self._started = False
        try:
            if self._poll().running:
                self.ask({"cmd": "disarm"})
                self.ask({"cmd": "actuator", "waveform": "stop"})
        except RigError as exc:
            log.warning("closing the session: %s", exc)
        self.loop.stop("session closed")


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT/SIGTERM while the block runs (main thread only)."""
    stop = threading.Event()
    handler = lambda s, _f: stop.set()  # noqa: E731
    old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def rig_overrides(
    bus_channel: str | None, no_telemetry: bool, **sections: dict[str, Any]
) -> dict[str, dict[str, Any]]:
    """Overrides of the rig config for a tool: not armed at start, no time limit."""
    out: dict[str, dict[str, Any]] = {"loop": {"arm_on_start": False, "duration_s": None}}
    if bus_channel:
        out["bus"] = {"channel": bus_channel}
    if no_telemetry:
        out["telemetry"] = {"enabled": False}
    for name, values in sections.items():
        out.setdefault(name, {}).update(values)
    return out
