"""Loading Zenoh configs, and the rule for a rig's sidecar: secure off loopback, by default.

Any endpoint (tcp, tls, quic, ...) and mode (peer, client of a router, router) is accepted. A
config that listens or connects beyond loopback (another address, all interfaces, multicast
scouting) is refused for a sidecar or a router unless its transport authenticates the other
side (mutual TLS on every endpoint, or Zenoh user-password) and an access-control policy is on
with `default_permission: "deny"` (templates: configs/zenoh/). `--insecure` lifts the rule for
a closed lab network, with a warning that the sidecar repeats in every status and recording.
"""

from __future__ import annotations

import ipaddress
import json
import re
from pathlib import Path
from typing import Any

import zenoh

from mrrig.errors import MrrigError
from mrrig.resources import resolve

_DEFAULT_MODE = "peer"
_RUST_SOURCE = re.compile(r"\s+at \S+\.rs:\d+\.?$")
_LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe")  # no network at all
_TLS_PROTOCOLS = ("tls", "quic")
TEMPLATE = "configs/zenoh/rig.json5"
INSECURE_WARNING = (
    "insecure: Zenoh off loopback without authentication or access control (--insecure); "
    "anyone on the network may arm this rig"
)
_RUST_SOURCE_ANYWHERE = re.compile(r"\s+at \S+?\.rs:\d+\.?")


class ZenohConfigError(MrrigError, ValueError):
    """A Zenoh config that cannot be used; the message is one line naming file and key."""


def _get(conf: zenoh.Config, key: str) -> Any:
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # noqa: BLE001 - zenoh.ZError for a key the config does not have
        return None


def _endpoints_for_mode(value: Any, mode: str) -> list[str]:
    # listen/connect endpoints are either a list or a {mode: list} dict
    if value is None:
        return []
    if isinstance(value, dict):
        return list(value.get(mode) or [])
    return list(value)


def endpoint_host(endpoint: str) -> str:
    """'tcp/127.0.0.1:7447?x=y#iface=lo' -> '127.0.0.1', 'tls/[::1]:7447' -> '::1';
    '' if there is no host part."""
    _, _, address = endpoint.partition("/")
    address = address.split("?", 1)[0].split("#", 1)[0]
    host, sep, _ = address.rpartition(":")
    return host.strip("[]") if sep else ""


def is_loopback(endpoint: str) -> bool:
    """True for an endpoint that cannot leave this machine (127.0.0.0/8, ::1, localhost, a
    Unix socket)."""
    protocol = endpoint.partition("/")[0]
    if protocol in _LOCAL_PROTOCOLS:
        return True
    host = endpoint_host(endpoint)
    if host == "localhost":
        return True
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return False  # a host name or no host: it may be anywhere
    mapped = getattr(address, "ipv4_mapped", None)  # ::ffff:127.0.0.1
    return address.is_loopback or (mapped is not None and mapped.is_loopback)


def zenoh_error_text(exc: BaseException) -> str:
    """A Zenoh error's first line without the Rust source path Zenoh appends to it."""
    lines = str(exc).strip().splitlines() or [type(exc).__name__]
    return _RUST_SOURCE_ANYWHERE.sub("", lines[0]).strip()


def _one_line(exc: Exception) -> str:
    """Zenoh's multi-line parse error (' --> 1:35', '= expected ...') as one line."""
    text = _RUST_SOURCE.sub("", str(exc)).strip()
    lines = [line.strip() for line in text.splitlines()]
    where = next((line[3:].strip() for line in lines if line.startswith("-->")), None)
    what = next((line[1:].strip() for line in lines if line.startswith("=")), None)
    if where and what:
        return f"at {where}: {what}"
    return " ".join(text.split()) or type(exc).__name__


def endpoints(conf: zenoh.Config) -> list[str]:
    """The listen and connect endpoints of the config's mode."""
    mode = _get(conf, "mode") or _DEFAULT_MODE
    return [
        e
        for key in ("listen/endpoints", "connect/endpoints")
        for e in _endpoints_for_mode(_get(conf, key), mode)
    ]


def beyond_loopback(conf: zenoh.Config) -> list[str]:
    """What takes the config beyond loopback: its non-loopback endpoints, and multicast
    scouting; empty for a config that stays on this machine."""
    # an absent listen key is Zenoh's default, all interfaces ('tcp/[::]:0'): listed here
    reach = [repr(e) for e in endpoints(conf) if not is_loopback(e)]
    if _get(conf, "scouting/multicast/enabled") is not False:
        reach.append("multicast scouting")
    return reach


def _authenticated(conf: zenoh.Config) -> bool:
    """Mutual TLS on every endpoint, or Zenoh user-password (with a dictionary to check the
    other side against when it listens)."""
    eps = endpoints(conf)
    tls = _get(conf, "transport/link/tls") or {}
    mtls = (
        bool(eps)
        and all(e.partition("/")[0] in _TLS_PROTOCOLS for e in eps)
        and tls.get("enable_mtls") is True
        and bool(tls.get("root_ca_certificate") or tls.get("root_ca_certificate_base64"))
    )
    usrpwd = _get(conf, "transport/auth/usrpwd") or {}
    listens = bool(_endpoints_for_mode(_get(conf, "listen/endpoints"), _get(conf, "mode") or ""))
    pwd = (
        bool(usrpwd.get("user"))
        and bool(usrpwd.get("password"))
        and (bool(usrpwd.get("dictionary_file")) or not listens)
    )
    return mtls or pwd


def _access_controlled(conf: zenoh.Config) -> bool:
    acl = _get(conf, "access_control") or {}
    return acl.get("enabled") is True and acl.get("default_permission") == "deny"


def missing_security(conf: zenoh.Config) -> list[str]:
    """What a config that leaves loopback lacks: authentication, access control, or both."""
    missing = []
    if not _authenticated(conf):
        missing.append(
            "peer authentication (mutual TLS on every endpoint, or transport/auth/usrpwd)"
        )
    if not _access_controlled(conf):
        missing.append('access_control (enabled, default_permission "deny")')
    return missing


def check_secure(conf: zenoh.Config, source: str, insecure: bool = False) -> list[str]:
    """A sidecar's or router's rule: raise ZenohConfigError if `conf` leaves loopback without
    authentication and access control, unless `insecure`; then the warning(s) to repeat
    (empty when the config is on loopback or secure)."""
    reach = beyond_loopback(conf)
    missing = missing_security(conf) if reach else []
    if not missing:
        return []
    if insecure:
        return [f"{INSECURE_WARNING} ({source}: {', '.join(reach)})"]
    raise ZenohConfigError(
        f"{source}: reaches beyond loopback ({', '.join(reach)}) without "
        f"{' and '.join(missing)}; see {TEMPLATE}, or run with --insecure on a closed lab network"
    )


def load_zenoh_config(path: str | Path) -> zenoh.Config:
    """Read a Zenoh JSON5 config file (found as `mrrig.resources.resolve` says): one line naming
    the file on any error."""
    source = str(resolve(path))
    try:
        return zenoh.Config.from_file(source)
    except Exception as exc:  # zenoh.ZError for both missing files and JSON5 syntax
        raise ZenohConfigError(f"{source}: cannot read Zenoh config: {_one_line(exc)}") from exc


def write_loopback_configs(folder: Path, port: int) -> tuple[Path, Path]:
    """A sidecar's (a peer listening) and a client's (connecting) Zenoh config on
    127.0.0.1:`port`, multicast scouting off, written in `folder`: (sidecar's file, client's
    file). What `mrrig demo` and `mrrig test --sim` run on unless given a config, on a free
    port: a second simulated rig, or a daemon on 7447, on this machine is not reached."""
    endpoints = [f"tcp/127.0.0.1:{port}"]
    scouting = {"multicast": {"enabled": False}}
    sidecar, client = folder / "zenoh-daemon.json5", folder / "zenoh-client.json5"
    sidecar.write_text(
        json.dumps({"mode": "peer", "listen": {"endpoints": endpoints}, "scouting": scouting})
    )
    client.write_text(
        json.dumps({"mode": "client", "connect": {"endpoints": endpoints}, "scouting": scouting})
    )
    return sidecar, client


def local_config(
    mode: str, listen: list[str] | None = None, connect: list[str] | None = None
) -> zenoh.Config:
    """A config built in code (tests, tools): multicast scouting off, the given endpoints."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(listen or []))
    conf.insert_json5("connect/endpoints", json.dumps(connect or []))
    return conf
