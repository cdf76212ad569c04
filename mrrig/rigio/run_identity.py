"""A run's identity (spec/system.md, "Runs, plans and the catalog"): made once at the daemon's
start-up, before the loop, written into the recording by the sidecar at its start and into the
run catalog with the summary's numbers at its end.

Plain JSON values only: the sidecar gets it on its command line. Nothing here runs on the loop
thread, and nothing here opens a database (`mrrig.catalog` does, in the sidecar).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import getpass
import hashlib
import json
import os
import socket
import uuid
from importlib import metadata
from pathlib import Path
from typing import Any

from mrrig.config import ControllerSection, DaemonConfig

# the catalog of a run whose config names none: beside the recordings
DEFAULT_CATALOG_NAME = "catalog.sqlite"
CATALOG_ENV = "MRRIG_CATALOG"  # the catalog of runs whose config names none


def file_sha256(path: str | Path) -> str | None:
    """The file's sha256 (hex), or None where it cannot be read."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                h.update(chunk)
    except OSError:
        return None
    return h.hexdigest()


def certificate_cn(path: str | Path | None) -> str | None:
    """The common name of the PEM certificate at `path`, or None (no file, no CN)."""
    if not path:
        return None
    try:
        from cryptography import x509
        from cryptography.x509.oid import NameOID

        cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
        names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
        return str(names[0].value) if names else None
    except (OSError, ValueError):
        return None


def _zenoh_value(conf: Any, key: str) -> Any:
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # noqa: BLE001 - zenoh.ZError: the config has no such key
        return None


def operator_of(conf: Any) -> str:
    """Who runs a run whose Zenoh session is opened with `conf` (a `zenoh.Config`, or None
    where there is no Zenoh): the common name of its certificate where it authenticates with
    mutual TLS, else its user where it authenticates by user and password, else the local
    user ("" where this process has no user name). Duck-typed: the loop, which imports this
    module, never imports Zenoh."""
    if conf is not None:
        tls = _zenoh_value(conf, "transport/link/tls") or {}
        if tls.get("enable_mtls") is True:
            cn = certificate_cn(tls.get("connect_certificate")) or certificate_cn(
                tls.get("listen_certificate")
            )
            if cn:
                return cn
        user = (_zenoh_value(conf, "transport/auth/usrpwd") or {}).get("user")
        if user:
            return str(user)
    try:
        return getpass.getuser()
    except (OSError, KeyError):
        return ""


def _version() -> str:
    try:
        return metadata.version("mrrig")
    except metadata.PackageNotFoundError:
        return "unknown"


def _json_value(v: Any) -> Any:
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, tuple):
        return [_json_value(x) for x in v]
    return v


def catalog_urls(cfg: DaemonConfig) -> tuple[str, str | None]:
    """(the catalog the run goes to, the local one it is spooled to where that one cannot be
    reached): `[catalog] url`, else `$MRRIG_CATALOG` (as `mrrig runs` reads it), else
    `<recording.directory>/catalog.sqlite`; a remote catalog spools to `[catalog] spool`, by
    default that local file."""
    local = str(cfg.recording.directory / DEFAULT_CATALOG_NAME)
    url = cfg.catalog.url or os.environ.get(CATALOG_ENV) or local
    if url == local or "://" not in url:
        return url, None
    return url, str(cfg.catalog.spool) if cfg.catalog.spool else local


# what the daemon's status carries of its run's identity, and what `set_controller` /
# `set_model` change in it (a plan step registers the identity as in force at its start)
STATUS_IDENTITY = ("run_id", "specimen", "operator", "config_sha256", "dbc_sha256", "mrrig_version")
IN_FORCE = ("controller", "controller_params", "model_path", "model_sha256")


def controller_in_force(c: ControllerSection) -> dict[str, Any]:
    """The controller, its parameters and its model (path and sha256, read now) as in force:
    at start, and after every `set_controller` / `set_model`."""
    model = str(c.model) if c.model is not None and c.name != "constant" else None
    return {
        "controller": c.name,
        "controller_params": {
            k: _json_value(v) for k, v in dataclasses.asdict(c).items() if k not in ("name",)
        },
        "model_path": model,
        "model_sha256": file_sha256(model) if model else None,
    }


def run_identity(cfg: DaemonConfig, dbc_path: Path) -> dict[str, Any]:
    """Who runs what, where, when and with which software: the run's identity (JSON values)."""
    url, spool = catalog_urls(cfg)
    return {
        "run_id": str(uuid.uuid4()),
        "rig": cfg.rig.name,
        "host": socket.gethostname(),
        "specimen": cfg.rig.specimen,
        # the config's, else the sidecar's Zenoh identity (`operator_of`), filled in there
        "operator": cfg.rig.operator,
        "tags": list(cfg.rig.tags),
        "started_utc": dt.datetime.now(dt.UTC).isoformat(),
        **controller_in_force(cfg.controller),
        "config_sha256": file_sha256(cfg.source) if Path(cfg.source).is_file() else None,
        "dbc_sha256": file_sha256(dbc_path),
        "mrrig_version": _version(),
        "catalog": url if cfg.catalog.enabled else None,
        "catalog_spool": spool if cfg.catalog.enabled else None,
    }
