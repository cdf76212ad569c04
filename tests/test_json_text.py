"""Strict JSON for the files and messages other tools read (mrrig/json_text.py)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mrrig import json_text


def _strict_loads(text: str):
    def refuse(name: str):
        raise ValueError(f"{name} is not JSON")

    return json.loads(text, parse_constant=refuse)


def test_undefined_numbers_are_null_and_numpy_and_paths_plain():
    d = {
        "et": math.nan,
        "latency_us": {"p99": np.float64(np.inf), "n": np.int64(3)},
        "f": [np.float32(1.5), -math.inf],
        "x": np.array([[0.5, np.nan]]),
        "file": Path("runs/a.rrd"),
        "ok": True,
    }
    assert _strict_loads(json_text.dumps(d)) == {
        "et": None,
        "latency_us": {"p99": None, "n": 3},
        "f": [1.5, None],
        "x": [[0.5, None]],
        "file": "runs/a.rrd",
        "ok": True,
    }


def test_a_type_json_has_no_form_for_is_refused():
    with pytest.raises(TypeError, match="object"):
        json_text.dumps({"x": object()})
