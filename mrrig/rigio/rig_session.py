"""`RigSession`: the daemon's loop in a thread of this process, driven by control requests
between runs (never per frame). `mrrig characterize` and `mrrig validate` use it."""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from mrrig.config import DaemonConfig
from mrrig.errors import MrrigError
from mrrig.loop.daemon import Daemon
from mrrig.loop.samples import SAMPLE_DTYPE, RigState

log = logging.getLogger(__name__)

# The rig must stream sensor frames this soon after the loop starts; the daemon's start-up
# (mlockall of this process, rerun's libraries being mapped) is inside it.
FIRST_FRAME_TIMEOUT_S = 10.0
# Disarmed (SAFE) time before the first arm: the loop's first few hundred ms after start-up
# can stall past the firmware's 20 ms watchdog.
WARMUP_S = 1.0


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


class RigSession:
    """The daemon's loop in a background thread, driven by control requests.

    Requests go through the daemon's control thread and are applied by the loop between
    frames (`Daemon.request`), a few times per run; the samples are read from the batches
    the loop has already handed over (never from its live buffer).
    """

    def __init__(self, cfg: DaemonConfig) -> None:
        self.daemon = Daemon(cfg, keep_batches=True)
        self.period_s = cfg.loop.period_s
        self._thread = threading.Thread(target=self._run, name="mrrig-loop", daemon=True)
        self._error: BaseException | None = None
        self._seen_chunks = 0
        self._seen_events = 0

    def _run(self) -> None:
        try:
            self.daemon.run()
        except BaseException as exc:  # noqa: BLE001 - reported by check_alive in the caller
            self._error = exc

    def __enter__(self) -> RigSession:
        self._thread.start()
        end = time.monotonic() + FIRST_FRAME_TIMEOUT_S
        while self.daemon.counters["sensor_frames_valid"] == 0:
            self.check_alive()
            if time.monotonic() > end:
                self.close()
                cfg = self.daemon.cfg
                raise RigError(
                    f"no sensor frames from the rig in {FIRST_FRAME_TIMEOUT_S:g} s on "
                    f"{cfg.bus.interface}/{cfg.bus.channel} (is the firmware running?)"
                )
            time.sleep(0.02)
        end = time.monotonic() + WARMUP_S
        while time.monotonic() < end:
            self.check_alive()
            time.sleep(0.05)
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def check_alive(self) -> None:
        if self._error is not None:
            raise RigError(f"the daemon loop stopped: {self._error}") from self._error
        if not self._thread.is_alive() and self._thread.ident is not None:
            raise RigError(f"the daemon loop stopped: {self.daemon.stop_reason or 'unknown'}")

    def now(self) -> float:
        """The daemon's clock (the samples' `t`), s."""
        return self.daemon.now()

    def request(self, **req: Any) -> dict[str, Any]:
        reply = self.daemon.request(req)
        if not reply["ok"]:
            raise RigError(f"{req['cmd']}: {reply['error']}")
        return reply

    def state(self) -> RigState:
        return self.daemon.supervisor.state

    def fault_reason(self) -> str:
        return self.daemon.supervisor.reason

    def wait_until(self, t_s: float, stop: threading.Event, fail_on_fault: bool = True) -> None:
        """Sleep until daemon time `t_s`; Interrupted on `stop`, RunFailed on a daemon FAULT."""
        while (left := t_s - self.now()) > 0:
            if stop.wait(min(left, 0.05)):
                raise Interrupted
            self.check_alive()
            if fail_on_fault and self.state() is RigState.FAULT:
                raise RunFailed(f"fault: {self.fault_reason()}", self.last_fault())

    def last_fault(self) -> dict[str, Any] | None:
        """The daemon's latest fault event (its `t` on the daemon's clock)."""
        return next((e for e in reversed(self.daemon.events) if e["kind"] == "fault"), None)

    @property
    def clock_t0_s(self) -> float:
        """The daemon's time zero on CLOCK_MONOTONIC: its times beside another process's."""
        return self.daemon.t0

    def take(self, t0_s: float, t1_s: float) -> tuple[np.ndarray, list[dict]]:
        """Samples with t in [t0_s, t1_s) and the events since the last call.

        Older samples are dropped for good: windows come in time order.
        """
        new = self.daemon.handed_over(self._seen_chunks)
        self._seen_chunks += len(new)
        events = self.daemon.events[self._seen_events :]
        self._seen_events += len(events)
        if not new:
            return np.zeros(0, dtype=SAMPLE_DTYPE), events
        s = np.concatenate(new)
        return s[(s["t"] >= t0_s) & (s["t"] < t1_s)], events

    def latest_t(self) -> float:
        chunks = self.daemon.handed_over(max(self._seen_chunks - 1, 0))
        return float(chunks[-1]["t"][-1]) if chunks else -math.inf

    def wait_samples(self, t_s: float, stop: threading.Event) -> None:
        """Until the loop has handed over a sample at or after `t_s` (or a short timeout)."""
        end = time.monotonic() + 1.0
        while self.latest_t() < t_s and time.monotonic() < end:
            if stop.wait(0.01):
                raise Interrupted
            self.check_alive()

    def close(self) -> None:
        """SAFE, actuator STOP (the daemon's shutdown sends both), loop stopped."""
        if self._thread.is_alive():
            self.daemon.request({"cmd": "disarm"})
            self.daemon.request({"cmd": "actuator", "waveform": "stop"})
            self.daemon.request_stop("session closed")
            self._thread.join(timeout=10)
            if self._thread.is_alive():
                log.error("the daemon loop did not stop in 10 s")


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
