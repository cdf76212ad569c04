"""The plant file: a modified Bouc-Wen damper (eqs 30-36) as JSON, the twin of a measured
damper that `mrrig identify` writes and `firmware_sim` runs (`[plant] file = ...`).

    {"format": "mrrig-plant", "version": 1, "model": "modified-bouc-wen",
     "params": {"c0a": ..., ..., "eta": ...}, "offset_n": 12.5, "command_unit": "V",
     "identified": {...what it was fitted to and how well: free-form, for people}}

The force is eq. 30 plus `offset_n` (the load cell's zero and the accumulator, as measured);
the command (eq. 36's v) is in `command_unit`, the unit of the data it was fitted to. A bad
file is one `ValueError` line naming the file and the field.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from damper.plant import BoucWenParams

FORMAT = "mrrig-plant"
VERSION = 1
MODEL = "modified-bouc-wen"
COMMAND_UNITS = ("A", "V")
# parameters that must be > 0 (the others, c0b c1b alpha_b x0, may be 0 or of either sign)
POSITIVE = ("c0a", "k0", "c1a", "gamma", "A", "n", "eta")
PARAM_NAMES = tuple(f.name for f in fields(BoucWenParams))


@dataclass(frozen=True)
class Plant:
    """A damper to simulate: the Bouc-Wen parameters, the force offset and the command's unit."""

    params: BoucWenParams
    offset_n: float = 0.0
    command_unit: str = "V"
    identified: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "model": MODEL,
            "params": asdict(self.params),
            "offset_n": self.offset_n,
            "command_unit": self.command_unit,
            "identified": self.identified,
        }


def _number(path: Path, name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{path}: {name}: expected a finite number, got {value!r}")
    return float(value)


def parse_plant(doc: Any, path: Path) -> Plant:
    """A Plant from a parsed plant file; ValueError naming the field that is wrong."""
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: not a plant file (expected a JSON object)")
    if doc.get("format") != FORMAT:
        raise ValueError(f"{path}: format: expected {FORMAT!r}, got {doc.get('format')!r}")
    if doc.get("version") != VERSION:
        raise ValueError(f"{path}: version: expected {VERSION}, got {doc.get('version')!r}")
    if doc.get("model") != MODEL:
        raise ValueError(f"{path}: model: expected {MODEL!r}, got {doc.get('model')!r}")
    raw = doc.get("params")
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: params: expected an object of {len(PARAM_NAMES)} numbers")
    unknown = sorted(set(raw) - set(PARAM_NAMES))
    if unknown:
        raise ValueError(f"{path}: params.{unknown[0]}: unknown parameter")
    values = {}
    for name in PARAM_NAMES:
        if name not in raw:
            raise ValueError(f"{path}: params.{name}: missing")
        values[name] = _number(path, f"params.{name}", raw[name])
        if name in POSITIVE and not values[name] > 0.0:
            raise ValueError(f"{path}: params.{name}: must be > 0, got {values[name]!r}")
    unit = doc.get("command_unit")
    if unit not in COMMAND_UNITS:
        raise ValueError(
            f"{path}: command_unit: expected one of {', '.join(COMMAND_UNITS)}, got {unit!r}"
        )
    identified = doc.get("identified", {})
    if not isinstance(identified, dict):
        raise ValueError(f"{path}: identified: expected an object")
    return Plant(
        BoucWenParams(**values),
        _number(path, "offset_n", doc.get("offset_n", 0.0)),
        unit,
        identified,
    )


def load_plant(path: str | Path) -> Plant:
    """Read a plant file; one ValueError line for a missing, unreadable or wrong file."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not JSON: {exc}".replace("\n", " ")) from None
    return parse_plant(doc, path)


def save_plant(plant: Plant, path: str | Path) -> None:
    """Write a plant file (strict JSON: no NaN)."""
    text = json.dumps(plant.to_json(), indent=1, allow_nan=False)
    Path(path).write_text(text + "\n", encoding="utf-8")
