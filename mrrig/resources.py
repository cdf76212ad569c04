"""The files mrrig ships (package data `mrrig.configs`) and how a path in a config is found.

A relative path is looked up, in order:
1. in the working directory (a checkout's `configs/rig.toml`, a lab's own files there);
2. beside the config file that names it (a lab's `rig.toml` and its `lab.dbc` in one folder);
3. for `configs/NAME`, the file NAME that mrrig ships (an installed wheel, run from anywhere).
A path found nowhere is returned as given, so that the error that follows names it.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

SHIPPED_PREFIX = "configs"


def shipped_dir() -> Path:
    """The folder of the shipped configs: `configs/` of a checkout (an editable install) or
    `mrrig/configs` of an installed wheel."""
    return Path(str(resources.files("mrrig.configs")))


def shipped(name: str | Path) -> Path:
    """A shipped file, e.g. `shipped("mrrig.dbc")`, `shipped("plans/smoke.toml")`."""
    return shipped_dir() / name


def resolve(path: str | Path, base: Path | None = None) -> Path:
    """`path` found as the module's docstring says; `base`: the folder of the config file
    that names it."""
    p = Path(path)
    if p.is_absolute() or p.exists():
        return p
    if base is not None and (base / p).exists():
        return base / p
    if p.parts[:1] == (SHIPPED_PREFIX,) and len(p.parts) > 1:
        candidate = shipped(Path(*p.parts[1:]))
        if candidate.exists():
            return candidate
    return p
