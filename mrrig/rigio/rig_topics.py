"""The rig's topics on a Zenoh network (spec/system.md): its key expressions, the liveliness
token of each daemon and the check for a second daemon of one name (`alive_elsewhere`), and the
payloads of telemetry and force references; shared by the sidecar, the clients and the tools."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import zenoh

from mrrig.loop.samples import FIELDS, SAMPLE_DTYPE

JSON = zenoh.Encoding.APPLICATION_JSON
_FLOAT_FIELDS = tuple(f for f in FIELDS if SAMPLE_DTYPE[f].kind == "f")


def keys(rig: str) -> dict[str, str]:
    """The rig's Zenoh key expressions (spec/system.md); `alive` selects the liveliness tokens
    of every daemon of that name (`alive_token`)."""
    names = ("telemetry", "status", "events", "force_ref", "control", "runs")
    return {name: f"mrrig/{rig}/{name}" for name in names} | {"alive": f"mrrig/{rig}/alive/*"}


def alive_token(rig: str, session_id: str) -> str:
    """One daemon's liveliness token: with its session's id, so that two daemons of one name
    are two tokens (Zenoh shows two tokens of one key as one)."""
    return f"mrrig/{rig}/alive/{session_id}"


_DUPLICATE = "is already served on this Zenoh network"


def is_duplicate_text(error: str) -> bool:
    """Whether a start-up error is `duplicate_text`'s."""
    return _DUPLICATE in error


def duplicate_text(rig: str, others: list[str]) -> str:
    """The one line for a second daemon of the rig's name on the network."""
    return (
        f"rig {rig!r} {_DUPLICATE} (liveliness token"
        f" {', '.join(sorted(others))}): a second daemon of one name obeys every request"
        " meant for the first; stop one, or give this one another [rig] name"
    )


def token_session(token: str) -> str:
    """The session id an `alive_token` carries."""
    return token.rsplit("/", 1)[-1]


def replier(reply: zenoh.Reply) -> str | None:
    """The id of the session that sent a reply (None where Zenoh does not say)."""
    if reply.ok is None or reply.replier_id is None:
        return None
    return str(reply.replier_id.zid)


def alive_elsewhere(session: zenoh.Session, rig: str, timeout_s: float) -> list[str]:
    """The liveliness tokens of other daemons of the rig's name that this session reaches:
    those whose session also answers the rig's status. A token that none answers for is left
    to the running sidecar, which asks again every second (a daemon that has no status yet
    answers then)."""
    own = alive_token(rig, str(session.zid()))
    replies = session.liveliness().get(keys(rig)["alive"], timeout=timeout_s)
    tokens = [str(r.ok.key_expr) for r in replies if r.ok is not None]
    tokens = [t for t in tokens if t != own]
    if not tokens:
        return []
    status = session.get(keys(rig)["status"], target=zenoh.QueryTarget.ALL, timeout=timeout_s)
    answered = {replier(r) for r in status}
    return [t for t in tokens if token_session(t) in answered]


def telemetry_json(rig: str, batch: np.ndarray, utc_start: str | None = None) -> str:
    """Columnar telemetry message: {"rig", "fields": {name: [values]}}, and with the run's
    `utc_start` (ISO 8601: the UTC time of `t = 0`, the run identity's `started_utc`) the
    key `utc_start`, from which a client gives each sample its UTC time.

    Non-finite floats become null (JSON has no NaN/Infinity).
    """
    fields: dict[str, list[Any]] = {}
    for name in FIELDS:
        col = batch[name]
        values = col.tolist()
        if name in _FLOAT_FIELDS and not np.isfinite(col).all():
            values = [v if math.isfinite(v) else None for v in values]
        fields[name] = values
    message: dict[str, Any] = {"rig": rig, "fields": fields}
    if utc_start is not None:
        message["utc_start"] = utc_start
    return json.dumps(message, separators=(",", ":"))


def parse_force_ref(payload: bytes) -> float:
    """A force_ref payload (JSON number or {"force_n": x}) -> finite force in N.

    Raises ValueError on anything else.
    """
    value = json.loads(payload)
    if isinstance(value, dict):
        value = value.get("force_n")
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError('expected a JSON number or {"force_n": number}')
    force_n = float(value)
    if not math.isfinite(force_n):
        raise ValueError("force is not finite")
    return force_n
