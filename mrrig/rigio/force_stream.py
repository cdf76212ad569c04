"""`mrrig send-force`: stream a desired-force profile to a daemon so that it cannot mislead.

Before the first sample it asks the daemon for its status: no daemon, or a daemon whose force
reference is not `zenoh` (it would ignore every sample), is a one-line error (exit 2) and
nothing is sent. With `arm`, it arms the daemon once the daemon has counted the first sample
(its `force_refs_received`), so the first armed frame has a fresh reference. The profile ends
with a ramp to 0 N and a disarm while the reference is still fresh, so a finished profile is
not a stale-reference fault (`disarm=False` leaves the daemon armed for another source, and
it faults `stale_reference` if none follows). Ctrl-C ramps down and disarms the same way.
With `arm`, the arm's lease is renewed while streaming (`mrrig.rigio.lease`) and the actuator
stopped after the disarm; with `disarm=False` the lease is released at the end: another
client must arm (take it) within `control.lease_timeout_s`, or the daemon disarms and stops
the actuator (`lease_lapsed`).
Progress goes to `out` once a second: time, the force sent, the daemon's state and fault.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import zenoh

from mrrig.errors import MrrigError
from mrrig.loop import profile_csv
from mrrig.loop.safety import TRANSPORT_FAULTS
from mrrig.rigio.client import ClientError, ZenohConfigLike, open_session, query
from mrrig.rigio.lease import Lease
from mrrig.rigio.rig_topics import JSON, keys

log = logging.getLogger(__name__)

TIME_COLUMN, FORCE_COLUMN = "t_s", "force_n"
DELIVERY_TIMEOUT_S = 2.0  # first sample -> counted by the daemon, before arming


class SendForceError(MrrigError, RuntimeError):
    """send-force cannot (or can no longer) do what was asked; nothing is left armed by it."""


def load_force_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A force profile CSV (`loop.profile_csv`, the daemon's reader): time (s) and force (N),
    t increasing, at least two rows. Any row that is not finite numbers is an error naming
    it: a dropped row would be bridged by interpolation and streamed as if it were the
    profile."""
    t_s, force_n = profile_csv.read(str(path), TIME_COLUMN, FORCE_COLUMN)
    if t_s.size < 2:
        raise ValueError(f"{path}: a force profile needs at least two rows t_s,force_n")
    return t_s, force_n


def csv_profile(path: str | Path) -> tuple[Callable[[float], float], float]:
    """The CSV as a function of time (linear interpolation) and its length (s)."""
    t_s, force_n = load_force_csv(path)
    return (lambda t: float(np.interp(t, t_s, force_n))), float(t_s[-1])


def ramp(f_from: float, ramp_s: float, rate_hz: float) -> list[float]:
    """The samples of a linear ramp from `f_from` to exactly 0 N over `ramp_s` at `rate_hz`
    (at least one sample: the final 0)."""
    n = max(1, math.ceil(ramp_s * rate_hz))
    return [f_from * (1.0 - k / n) for k in range(1, n + 1)]


def stream(
    pub: zenoh.Publisher,
    values: Callable[[int], float | None],
    rate_hz: float,
    on_put: Callable[[int, float], None] | None = None,
) -> int:
    """Put {"force_n": values(k)} at absolute deadlines k / rate_hz (no drift) until
    `values` returns None; `on_put(k, f)` after each. Returns the puts sent."""
    period_s = 1.0 / rate_hz
    t0 = time.monotonic()
    k = 0
    while (f := values(k)) is not None:
        delay_s = t0 + k * period_s - time.monotonic()
        if delay_s > 0:
            time.sleep(delay_s)
        pub.put(json.dumps({"force_n": f}))
        if on_put is not None:
            on_put(k, f)
        k += 1
    return k


class _LatestStatus:
    """Subscriber callback keeping the daemon's newest published status."""

    def __init__(self) -> None:
        self.status: dict[str, Any] | None = None

    def __call__(self, sample: zenoh.Sample) -> None:
        self.status = json.loads(sample.payload.to_bytes())


@dataclass
class SendResult:
    sent: int = 0  # every put, ramp included
    hold_samples: int = 0  # the first value, put while --arm waited for its delivery
    ramp_samples: int = 0
    armed_by_us: bool = False
    disarmed: bool = False
    interrupted: bool = False
    faults: list[str] = field(default_factory=list)  # "code: reason" seen while streaming


def check_daemon(session: zenoh.Session, rig: str, timeout_s: float) -> dict[str, Any]:
    """The daemon's status, if it will take a streamed profile; else SendForceError."""
    status = query(session, rig, {"cmd": "status"}, timeout_s)["status"]
    kind = status.get("reference")
    if kind != "zenoh":
        raise SendForceError(
            f"rig {rig!r}: the daemon's force reference is {kind!r}, not 'zenoh': it would"
            " ignore the profile (to take it: mrrig control --rig"
            f' {rig} \'{{"cmd": "set_profile", "kind": "zenoh", "timeout_s": 0.1}}\')'
        )
    return status


def send_force(
    rig: str,
    zenoh_config: ZenohConfigLike,
    fn: Callable[[float], float],
    duration_s: float,
    rate_hz: float = 100.0,
    *,
    arm: bool = False,
    disarm: bool = True,
    ramp_s: float = 0.5,
    timeout_s: float = 2.0,
    out: TextIO | None = None,
) -> SendResult:
    """Check the daemon, stream fn(t) for t in [0, duration_s], ramp to 0 N, disarm."""
    result = SendResult()
    n_profile = int(math.floor(duration_s * rate_hz)) + 1
    with open_session(zenoh_config) as session, contextlib.ExitStack() as stack:
        status = check_daemon(session, rig, timeout_s)
        received0 = status.get("force_refs_received", 0)
        if not arm and not status.get("armed"):
            _say(
                out,
                f"note: rig {rig!r} is {status['state']}: the profile is its desired force,"
                " but its commands stay SAFE (0 A) until armed (--arm)",
            )
        latest = _LatestStatus()
        sub = session.declare_subscriber(keys(rig)["status"], latest)
        stack.callback(sub.undeclare)
        # BLOCK: Zenoh drops puts under congestion by default on a loaded machine, and a
        # dropped sample of the ramp is a step the daemon was never asked for
        pub = session.declare_publisher(
            keys(rig)["force_ref"],
            encoding=JSON,
            express=True,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        stack.callback(pub.undeclare)
        last = [0.0]
        report = _Progress(out, duration_s, latest, result)

        def on_put(k: int, f: float) -> None:
            last[0] = f
            result.sent += 1
            report(k / rate_hz, f)

        try:
            if arm:
                reply = _hold_and_arm(
                    session, pub, rig, fn(0.0), rate_hz, received0, timeout_s, result
                )
                lease = Lease.of(functools.partial(query, session, rig), reply, rig)
                if lease is not None:  # renewed while streaming; released after the disarm
                    stack.callback(lease.release)
            stream(pub, lambda k: fn(k / rate_hz) if k < n_profile else None, rate_hz, on_put)
        except KeyboardInterrupt:
            result.interrupted = True
            _say(out, "interrupted: ramping to 0 N")
        except SendForceError:
            _finish(session, pub, rig, last[0], ramp_s, rate_hz, False, timeout_s, result)
            raise
        _finish(session, pub, rig, last[0], ramp_s, rate_hz, disarm, timeout_s, result)
    return result


def _hold_and_arm(
    session: zenoh.Session,
    pub: zenoh.Publisher,
    rig: str,
    f0: float,
    rate_hz: float,
    received0: int,
    timeout_s: float,
    result: SendResult,
) -> dict[str, Any]:
    """Put the profile's first value at `rate_hz` until the daemon has counted one (nothing is
    armed on a reference that has not arrived), then arm; the profile starts after. The
    reference stays fresh meanwhile: an armed daemon faults on one older than its timeout."""
    period_s = 1.0 / rate_hz
    deadline = time.monotonic() + DELIVERY_TIMEOUT_S
    while True:
        pub.put(json.dumps({"force_n": f0}))
        result.hold_samples += 1
        status = query(session, rig, {"cmd": "status"}, timeout_s)["status"]
        if status.get("force_refs_received", 0) > received0:
            break
        if time.monotonic() > deadline:
            raise SendForceError(
                f"rig {rig!r}: the daemon did not receive the force reference within"
                f" {DELIVERY_TIMEOUT_S:g} s; not arming"
            )
        time.sleep(period_s)
    pub.put(json.dumps({"force_n": f0}))
    result.hold_samples += 1
    if status.get("state") == "FAULT" and status.get("fault") in TRANSPORT_FAULTS:
        # the documented choice for a transport fault (a stall), made explicit: acknowledged
        # by a reset of its own (audited), then armed; any other fault is the operator's
        log.warning(
            "rig %s: acknowledging its transport fault %s (%s) with reset before arming",
            rig,
            status.get("fault"),
            status.get("fault_reason"),
        )
        reply = query(session, rig, {"cmd": "reset"}, timeout_s)
        if not reply.get("ok"):
            raise SendForceError(f"rig {rig!r}: reset refused: {reply.get('error')}")
    reply = query(session, rig, {"cmd": "arm"}, timeout_s)
    if not reply.get("ok"):
        raise SendForceError(f"rig {rig!r}: arming refused: {reply.get('error')}")
    result.armed_by_us = True
    return reply


def _finish(
    session: zenoh.Session,
    pub: zenoh.Publisher,
    rig: str,
    f_last: float,
    ramp_s: float,
    rate_hz: float,
    disarm: bool,
    timeout_s: float,
    result: SendResult,
) -> None:
    """The ramp to 0 N, then the disarm while the reference is fresh and, where this client
    armed the rig, the actuator stopped (the firmware ramps it to rest)."""
    values = ramp(f_last, ramp_s, rate_hz)
    result.ramp_samples = stream(pub, lambda k: values[k] if k < len(values) else None, rate_hz)
    result.sent += result.ramp_samples
    if disarm:
        try:
            reply = query(session, rig, {"cmd": "disarm"}, timeout_s)
        except ClientError as exc:
            raise SendForceError(f"rig {rig!r}: could not disarm after the profile: {exc}") from exc
        result.disarmed = bool(reply.get("ok"))
        if result.armed_by_us:
            try:
                query(session, rig, {"cmd": "actuator", "waveform": "stop"}, timeout_s)
            except ClientError as exc:
                log.error("rig %s: no actuator stop after the profile: %s", rig, exc)


class _Progress:
    """One line a second: time, the force sent, the daemon's state and any new fault."""

    def __init__(
        self, out: TextIO | None, duration_s: float, latest: _LatestStatus, result: SendResult
    ) -> None:
        self.out, self.duration_s, self.latest, self.result = out, duration_s, latest, result
        self.next_t = 0.0

    def __call__(self, t: float, f: float) -> None:
        st = self.latest.status
        if st and st.get("state") == "FAULT":
            # the code first: what a script can test; then the reason, for the operator
            fault = ": ".join(str(v) for v in (st.get("fault"), st.get("fault_reason")) if v)
            if fault and fault not in self.result.faults:
                self.result.faults.append(fault)
        if t < self.next_t:
            return
        self.next_t += 1.0
        state = st["state"] if st else "?"
        fault = f"  fault {st.get('fault_reason')}" if st and st.get("state") == "FAULT" else ""
        _say(
            self.out,
            f"t {t:6.1f}/{self.duration_s:g} s  force {f:9.1f} N  sent {self.result.sent}"
            f"  daemon {state}{fault}",
        )


def _say(out: TextIO | None, line: str) -> None:
    if out is not None:
        print(line, file=out, flush=True)
