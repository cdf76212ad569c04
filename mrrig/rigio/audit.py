"""Audit of control requests: who asked the rig for what, and what came of it.

Zenoh does not tell a queryable who sent a query. With mutual TLS or user-password and the
access control of configs/zenoh/ (default deny), a request that reaches the sidecar at all
came from a subject granted `query` on `control` (an operator); one that is not granted is
dropped by the Zenoh session that enforces the policy (the rig's own, or the router's) and never
reaches the daemon. Beside that, the client attaches what it says about itself (its Zenoh
session id, the user and host it runs as, the certificate name or Zenoh user of its config):
`requester` keeps those as `claimed`, with the query's source info where Zenoh gives one. Where
the claimed session is connected to the rig's session directly, its link tells what Zenoh
authenticated (`link`: the certificate's common name, and the remote address; Zenoh 1.10
names no user on a user-password link); through a router, the rig's links are the router's
(`via`). A client can claim another's session id: `link` is the authenticated identity of the
session it names.
"""

from __future__ import annotations

import getpass
import json
import logging
import socket
from typing import Any

import zenoh

from mrrig.rigio.run_identity import certificate_cn
from mrrig.safe_text import one_line

log = logging.getLogger(__name__)

MAX_REQUEST_CHARS = 2048  # an audit keeps a request's text up to this, then a mark
_RESULT_KEYS = ("ok", "error", "state", "message", "controller", "reference")


def _config_value(conf: zenoh.Config, key: str) -> Any:
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # noqa: BLE001 - zenoh.ZError: the config has no such key
        return None


def claims(session: zenoh.Session, conf: zenoh.Config | None) -> dict[str, Any]:
    """What a client says about itself: attached to its control queries."""
    out: dict[str, Any] = {"zid": str(session.info.zid())}
    try:
        out["user"] = getpass.getuser()
    except (KeyError, OSError):
        pass
    out["host"] = socket.gethostname()
    if conf is not None:
        cn = certificate_cn(_config_value(conf, "transport/link/tls/connect_certificate"))
        if cn:
            out["cert_cn"] = cn
        zenoh_user = _config_value(conf, "transport/auth/usrpwd/user")
        if zenoh_user:
            out["zenoh_user"] = zenoh_user
    return out


_MAX_VIA = 8
_MAX_CLAIMS = 16  # fields of a client's claims kept (claims() sends at most five)


def parse_claims(raw: bytes) -> dict[str, Any] | str:
    """A client's claims as the audit keeps them: each field's name and text one printable line
    of bounded length (`safe_text.one_line`), a number as it is, at most _MAX_CLAIMS fields;
    not a JSON object: a bounded excerpt. A newline in a claimed host forged a second audit
    line; a 3 MB host went into every event."""
    try:
        claimed = json.loads(raw)
    except ValueError:
        return one_line(raw[:MAX_REQUEST_CHARS].decode("utf-8", "replace"))
    if not isinstance(claimed, dict):
        return one_line(json.dumps(claimed)[:MAX_REQUEST_CHARS])
    out: dict[str, Any] = {}
    for key, value in list(claimed.items())[:_MAX_CLAIMS]:
        plain = isinstance(value, int | float | bool) or value is None
        out[one_line(key, 64)] = value if plain else one_line(value)
    if len(claimed) > _MAX_CLAIMS:
        out["more_fields"] = len(claimed) - _MAX_CLAIMS
    return out


def _links(session: zenoh.Session | None) -> list[Any]:
    if session is None:
        return []
    try:
        return list(session.info.links())
    except (AttributeError, zenoh.ZError):  # a Zenoh without links(): the claims alone
        return []


def requester(query: zenoh.Query, session: zenoh.Session | None = None) -> dict[str, Any]:
    """The requester as far as Zenoh tells: the query's source info, the client's claims, and
    the authenticated link of the claimed session (or the links it came through)."""
    out: dict[str, Any] = {}
    info = query.source_info
    if info is not None:
        out["source"] = str(info)
    if query.attachment is not None:
        out["claimed"] = parse_claims(query.attachment.to_bytes())
    links = _links(session)
    claimed = out.get("claimed")
    zid = str(claimed.get("zid")) if isinstance(claimed, dict) else None
    mine = next((link for link in links if str(link.zid) == zid), None)
    if mine is not None:
        auth = mine.auth_identifier
        out["link"] = {
            "zid": zid,
            "auth": one_line(auth) if auth else auth,
            "remote": str(mine.dst),
        }
    elif links:
        out["via"] = [
            {"zid": str(link.zid), "auth": link.auth_identifier} for link in links[:_MAX_VIA]
        ]
    return out


def _who(req: dict[str, Any]) -> str:
    link = req.get("link")
    if isinstance(link, dict) and link.get("auth"):
        return f"{link['auth']} (authenticated, zid {str(link['zid'])[:8]})"
    c = req.get("claimed")
    if not isinstance(c, dict):
        return "an unnamed client"
    name = c.get("cert_cn") or c.get("zenoh_user") or c.get("user") or "?"
    return f"{name}@{c.get('host', '?')} (zid {str(c.get('zid', '?'))[:8]})"


def event(
    t_s: float, request: dict[str, Any] | bytes, reply: dict[str, Any], who: dict[str, Any]
) -> dict[str, Any]:
    """The audit event of one control request: the request, its result, the requester."""
    if isinstance(request, bytes):
        request = {"raw": request[:MAX_REQUEST_CHARS].decode("utf-8", "replace")}
    elif len(json.dumps(request)) > MAX_REQUEST_CHARS:
        request = {"cmd": request.get("cmd"), "truncated": True}
    result = {k: reply[k] for k in _RESULT_KEYS if k in reply}
    cmd = request.get("cmd", "?")
    outcome = "accepted" if reply.get("ok") else f"refused: {reply.get('error')}"
    text = one_line(f"control {cmd} from {_who(who)}: {outcome}", MAX_REQUEST_CHARS)
    log.info("audit: %s", text)
    return {
        "t": t_s,
        "level": "info" if reply.get("ok") else "warning",
        "text": text,
        "kind": "audit",
        "request": request,
        "result": result,
        "requester": who,
    }
