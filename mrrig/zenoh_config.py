"""Loading Zenoh configs, refusing any that would leave 127.0.0.1.

Multicast scouting must be explicitly off and every listen/connect endpoint of the config's
mode must be on host 127.0.0.1 (Zenoh's defaults listen on all interfaces and multicast).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import zenoh

_LOCAL_HOST = "127.0.0.1"
_DEFAULT_MODE = "peer"
_RUST_SOURCE = re.compile(r"\s+at \S+\.rs:\d+\.?$")


class ZenohConfigError(ValueError):
    """A Zenoh config that cannot be used; the message is one line naming file and key."""


def _get(conf: zenoh.Config, key: str) -> Any:
    return json.loads(conf.get_json(key))


def _endpoints_for_mode(value: Any, mode: str) -> list[str]:
    # listen/connect endpoints are either a list or a {mode: list} dict
    if value is None:
        return []
    if isinstance(value, dict):
        return list(value.get(mode) or [])
    return list(value)


def endpoint_host(endpoint: str) -> str:
    """'tcp/127.0.0.1:7447?x=y#iface=lo' -> '127.0.0.1'; '' if there is no host part."""
    _, _, address = endpoint.partition("/")
    address = address.split("?", 1)[0].split("#", 1)[0]
    host, sep, _ = address.rpartition(":")
    return host if sep else ""


def _one_line(exc: Exception) -> str:
    """Zenoh's multi-line parse error (' --> 1:35', '= expected ...') as one line."""
    text = _RUST_SOURCE.sub("", str(exc)).strip()
    lines = [line.strip() for line in text.splitlines()]
    where = next((line[3:].strip() for line in lines if line.startswith("-->")), None)
    what = next((line[1:].strip() for line in lines if line.startswith("=")), None)
    if where and what:
        return f"at {where}: {what}"
    return " ".join(text.split()) or type(exc).__name__


def check_zenoh_config(conf: zenoh.Config, source: str) -> None:
    """Raise ZenohConfigError unless `conf` stays on 127.0.0.1 with multicast scouting off."""
    if _get(conf, "scouting/multicast/enabled") is not False:
        raise ZenohConfigError(
            f"{source}: scouting/multicast/enabled must be false (multicast scouting leaves "
            f"127.0.0.1)"
        )
    mode = _get(conf, "mode") or _DEFAULT_MODE
    for key in ("listen/endpoints", "connect/endpoints"):
        for endpoint in _endpoints_for_mode(_get(conf, key), mode):
            if endpoint_host(endpoint) != _LOCAL_HOST:
                raise ZenohConfigError(
                    f"{source}: {key} has {endpoint!r}; only tcp/{_LOCAL_HOST}:<port> "
                    f"endpoints are allowed"
                )


def load_zenoh_config(path: str | Path) -> zenoh.Config:
    """Read a Zenoh JSON5 config file and check it (`check_zenoh_config`)."""
    source = str(path)
    try:
        conf = zenoh.Config.from_file(source)
    except Exception as exc:  # zenoh.ZError for both missing files and JSON5 syntax
        raise ZenohConfigError(f"{source}: cannot read Zenoh config: {_one_line(exc)}") from exc
    check_zenoh_config(conf, source)
    return conf


def local_config(
    mode: str, listen: list[str] | None = None, connect: list[str] | None = None
) -> zenoh.Config:
    """A checked config built in code (tests, tools): multicast off, the given endpoints."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(listen or []))
    conf.insert_json5("connect/endpoints", json.dumps(connect or []))
    check_zenoh_config(conf, "<local_config>")
    return conf
