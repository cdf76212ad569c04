"""Zenoh clients of a running daemon: control requests and the live watch (streaming a force
profile: `mrrig.rigio.force_stream`).

Every function opens its own session from a checked config (a path or a `zenoh.Config`) and
closes it before returning, also on errors and Ctrl-C.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import zenoh

from mrrig.errors import MrrigError
from mrrig.loop.samples import RigState
from mrrig.rigio import audit
from mrrig.rigio.rig_topics import JSON, keys
from mrrig.rigio.zenoh_config import load_zenoh_config, zenoh_error_text

ZenohConfigLike = str | Path | zenoh.Config
# 127.0.0.1, client mode, multicast scouting off
DEFAULT_CONFIG = Path("configs/zenoh-client.json5")
_WATCH_POLL_S = 0.01


class ClientError(MrrigError, ConnectionError):
    """No daemon answered, or it answered with a transport error."""


def _config(zenoh_config: ZenohConfigLike) -> zenoh.Config:
    if isinstance(zenoh_config, zenoh.Config):
        return zenoh_config
    return load_zenoh_config(zenoh_config)


@contextlib.contextmanager
def open_session(zenoh_config: ZenohConfigLike) -> Iterator[zenoh.Session]:
    """A session from a config (a file is read, one line naming it on error), closed on exit."""
    conf = _config(zenoh_config)
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        raise ClientError(
            f"cannot open a Zenoh session: {zenoh_error_text(exc)} (is the daemon running?"
            " start it: mrrig run --config ...; or give --zenoh-config of its network)"
        ) from exc
    try:
        yield session
    finally:
        session.close()


def request(
    rig: str, payload: dict[str, Any], zenoh_config: ZenohConfigLike, timeout_s: float = 2.0
) -> dict[str, Any]:
    """Send one control request (e.g. {"cmd": "status"}) and return the daemon's JSON reply.

    Raises ClientError if no daemon answers within `timeout_s`.
    """
    conf = _config(zenoh_config)
    with open_session(conf) as session:
        return query(session, rig, payload, timeout_s, audit.claims(session, conf))


def query(
    session: zenoh.Session,
    rig: str,
    payload: dict[str, Any],
    timeout_s: float = 2.0,
    claims: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """`request` on a session that is already open (`open_session`). `claims` (who this
    client says it is, for the rig's audit) default to the session's id, user and host."""
    key = keys(rig)["control"]
    attachment = json.dumps(claims or audit.claims(session, None))
    # every daemon's answer: Zenoh's default consolidation keeps one reply per key, and two
    # daemons of one name would both act on a request while the client saw one of them
    replies = session.get(
        key,
        payload=json.dumps(payload),
        encoding=JSON,
        timeout=timeout_s,
        attachment=attachment,
        consolidation=zenoh.ConsolidationMode.NONE,
    )
    answers = []
    for reply in replies:
        if reply.ok is None:
            raise ClientError(f"{key}: error reply: {reply.err.payload.to_string()}")
        answers.append(json.loads(reply.ok.payload.to_bytes()))
    if len(answers) > 1:
        raise ClientError(
            f"{len(answers)} daemons answered as rig {rig!r} on {key} (two daemons of one name"
            " on the network both obey its requests; stop one): their replies"
            f" {json.dumps(answers)[:400]}"
        )
    if answers:
        return answers[0]
    raise ClientError(
        f"no daemon answered on {key} within {timeout_s:g} s (is `mrrig run` up for rig "
        f"{rig!r}, with a matching Zenoh config, and does its access control grant you control?)"
    )


def status(rig: str, zenoh_config: ZenohConfigLike, timeout_s: float = 2.0) -> dict[str, Any]:
    return request(rig, {"cmd": "status"}, zenoh_config, timeout_s)


def arm(rig: str, zenoh_config: ZenohConfigLike, timeout_s: float = 2.0) -> dict[str, Any]:
    return request(rig, {"cmd": "arm"}, zenoh_config, timeout_s)


def reset(rig: str, zenoh_config: ZenohConfigLike, timeout_s: float = 2.0) -> dict[str, Any]:
    """Acknowledge the rig's FAULT (to IDLE): the one way out of FAULT before `arm`."""
    return request(rig, {"cmd": "reset"}, zenoh_config, timeout_s)


def disarm(rig: str, zenoh_config: ZenohConfigLike, timeout_s: float = 2.0) -> dict[str, Any]:
    return request(rig, {"cmd": "disarm"}, zenoh_config, timeout_s)


def _last(values: list[Any]) -> float:
    v = values[-1] if values else None
    return float("nan") if v is None else float(v)


def format_watch_line(samples_per_s: float, fields: dict[str, list[Any]]) -> str:
    """One line of `watch`: rate, latest f_des / f_meas / i_cmd, latency p99, state."""
    latency = np.array([v for v in fields.get("latency_us", []) if v is not None], float)
    p99 = float(np.percentile(latency, 99)) if latency.size else float("nan")
    state = fields.get("state") or []
    state_name = RigState(state[-1]).name if state else "?"
    return (
        f"rate {samples_per_s:6.1f} Hz  f_des {_last(fields.get('f_des', [])):9.1f} N  "
        f"f_meas {_last(fields.get('f_meas', [])):9.1f} N  "
        f"i_cmd {_last(fields.get('i_cmd', [])):6.3f} A  "
        f"latency p99 {p99:7.1f} us  state {state_name}"
    )


def watch(
    rig: str,
    zenoh_config: ZenohConfigLike,
    duration_s: float | None = None,
    out: TextIO = sys.stdout,
) -> int:
    """Print live numbers from `mrrig/<rig>/telemetry` once per second.

    Runs for `duration_s` (None: until Ctrl-C); returns the number of samples received.
    """
    total = 0
    quiet_s = 0
    with open_session(zenoh_config) as session:
        latest_status: list[dict[str, Any]] = []
        status_sub = session.declare_subscriber(
            keys(rig)["status"], lambda s: latest_status.append(json.loads(s.payload.to_bytes()))
        )
        sub = session.declare_subscriber(keys(rig)["telemetry"])
        t0 = time.monotonic()
        window_start = t0
        window: dict[str, list[Any]] = {}
        try:
            while duration_s is None or time.monotonic() - t0 < duration_s:
                sample = sub.try_recv()
                if sample is None:
                    time.sleep(_WATCH_POLL_S)
                else:
                    fields = json.loads(sample.payload.to_bytes())["fields"]
                    for name, values in fields.items():
                        window.setdefault(name, []).extend(values)
                now = time.monotonic()
                if now - window_start >= 1.0:
                    n = len(window.get("t", []))
                    total += n
                    quiet_s = 0 if n else quiet_s + 1
                    status = latest_status[-1] if latest_status else None
                    del latest_status[:-1]
                    if n:
                        line = format_watch_line(n / (now - window_start), window)
                        if status and status.get("state") == "FAULT":
                            line += f"  fault {status.get('fault_reason') or status.get('fault')}"
                    else:
                        line = no_telemetry_line(rig, quiet_s, status)
                    print(line, file=out, flush=True)
                    window, window_start = {}, now
        except KeyboardInterrupt:
            pass
        finally:
            sub.undeclare()
            status_sub.undeclare()
        total += len(window.get("t", []))
    return total


def no_telemetry_line(rig: str, quiet_s: int, status: dict[str, Any] | None) -> str:
    """What `watch` prints for a second without telemetry: what is known, and what to check."""
    if status is not None:
        fault = status.get("fault_reason") or status.get("fault")
        state = status.get("state", "?") + (f" (fault {fault})" if fault else "")
        return f"no telemetry for {quiet_s} s; the daemon's status says {state}"
    return (
        f"no telemetry for {quiet_s} s from mrrig/{rig}/telemetry: is the daemon up"
        f" (mrrig status --rig {rig}), with telemetry.enabled and the same Zenoh network"
        " (--zenoh-config)?"
    )
