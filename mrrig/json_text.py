"""JSON text for files and messages that other tools read: strict JSON.

Python's json writes NaN and Infinity, which are not JSON (jq, browsers and most parsers
refuse them); an undefined number (Et without an armed frame, a percentile of nothing) is
null here. numpy scalars and arrays become plain numbers and lists, paths strings.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np


def plain(obj: Any) -> Any:
    """`obj` with only JSON types: non-finite floats as None, numpy and paths converted."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def dumps(obj: Any, **kwargs: Any) -> str:
    """`json.dumps` of `plain(obj)`; raises TypeError for a type JSON has no form for."""
    return json.dumps(plain(obj), allow_nan=False, **kwargs)
