"""The forward network (paper eqs 1, 5): one hidden tanh layer, linear output, and its file.

Numpy only: the rig daemon loads and evaluates models without torch. Weights are stored in
standardised units; `predict` takes and returns physical (SI) units.

File format `mrrig-mlp/1`: a JSON object, arrays as (nested) lists of floats written with
`repr`, so that a reload is bit-exact.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mrrig.errors import MrrigError

FORMAT = "mrrig-mlp/1"
# The standardisation's scales (in_std, out_std) a model may have: the inversion divides by
# their squares, which a smaller scale takes to 0 (ZeroDivisionError) or past a float's range
MIN_SCALE, MAX_SCALE = 1e-12, 1e12
_FLOAT_MAX = sys.float_info.max


class ModelError(MrrigError, ValueError):
    """A model file or model object that cannot be used; the message is one line."""


def data_fingerprint(*arrays: np.ndarray) -> str:
    """sha256 over the shapes and float64 bytes of the arrays (the training data)."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a, dtype=np.float64)
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


@dataclass
class MLP:
    """n_in - H - 1 perceptron: f = out_mean + out_std * (W2 . tanh(W1 z + b1) + b2)."""

    input_names: list[str]
    input_units: list[str]
    output_name: str
    output_unit: str
    in_mean: np.ndarray
    in_std: np.ndarray
    out_mean: float
    out_std: float
    W1: np.ndarray
    b1: np.ndarray
    W2: np.ndarray
    b2: float
    fingerprint: str = ""
    metrics: dict[str, Any] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("in_mean", "in_std", "W1", "b1", "W2"):
            try:
                setattr(self, name, np.array(getattr(self, name), dtype=np.float64))
            except ValueError:
                raise ModelError(f"model: field '{name}': not a rectangular array") from None
        self.out_mean = float(self.out_mean)
        self.out_std = float(self.out_std)
        self.b2 = float(self.b2)
        problem = self._problem()
        if problem is not None:
            raise ModelError(f"model: field '{problem[0]}': {problem[1]}")

    @property
    def n_in(self) -> int:
        return len(self.input_names)

    @property
    def hidden(self) -> int:
        return int(self.W1.shape[0])

    @property
    def current_index(self) -> int | None:
        """Index of the input named "current", None if the model has none."""
        return self.input_names.index("current") if "current" in self.input_names else None

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Output (N,) in physical units for inputs X (N x n_in) in physical units."""
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != self.n_in:
            raise ValueError(f"predict: X must be (N, {self.n_in}), got {X.shape}")
        z = (X - self.in_mean) / self.in_std
        o = np.tanh(z @ self.W1.T + self.b1)  # eqs 5, 7
        return self.out_mean + self.out_std * (o @ self.W2 + self.b2)

    def _problem(self) -> tuple[str, str] | None:
        """(field, what is wrong) for the first inconsistent field, None if all are fine."""
        n = len(self.input_names)
        if n == 0 or not all(isinstance(s, str) for s in self.input_names):
            return "input_names", "must be a non-empty list of strings"
        if len(set(self.input_names)) != n:
            return "input_names", "names must be distinct"
        if len(self.input_units) != n or not all(isinstance(s, str) for s in self.input_units):
            return "input_units", f"must be {n} strings"
        if self.W1.ndim != 2 or self.W1.shape[1] != n or self.W1.shape[0] == 0:
            return "W1", f"must be H x {n}, got shape {self.W1.shape}"
        h = self.W1.shape[0]
        shapes = {"in_mean": (n,), "in_std": (n,), "b1": (h,), "W2": (h,)}
        for name, shape in shapes.items():
            a = getattr(self, name)
            if a.shape != shape:
                return name, f"must have shape {shape}, got {a.shape}"
        for name in ("in_mean", "in_std", "W1", "b1", "W2", "out_mean", "out_std", "b2"):
            if not np.all(np.isfinite(getattr(self, name))):
                return name, "must be finite"
        for name in ("in_std", "out_std"):
            scale = np.asarray(getattr(self, name))
            if np.any(scale <= 0.0):
                return name, "must be > 0"
            if np.any(scale < MIN_SCALE) or np.any(scale > MAX_SCALE):
                return name, (
                    f"must lie in [{MIN_SCALE:g}, {MAX_SCALE:g}] (a standardisation's scale;"
                    f" {float(scale.min()):g} overflows the network and its inversion)"
                )
        return None

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "input_names": list(self.input_names),
            "input_units": list(self.input_units),
            "output_name": self.output_name,
            "output_unit": self.output_unit,
            "hidden": self.hidden,
            "fingerprint": self.fingerprint,
            "in_mean": self.in_mean.tolist(),
            "in_std": self.in_std.tolist(),
            "out_mean": self.out_mean,
            "out_std": self.out_std,
            "W1": self.W1.tolist(),
            "b1": self.b1.tolist(),
            "W2": self.W2.tolist(),
            "b2": self.b2,
            "metrics": _plain(self.metrics),
            "meta": _plain(self.meta),
        }

    def save(self, path: str | Path) -> None:
        """Write the model as human-readable JSON (one array row per line)."""
        lines = ["{"]
        items = list(self.to_dict().items())
        for k, (key, value) in enumerate(items):
            if key == "W1":
                rows = ",\n    ".join(json.dumps(r) for r in value)
                text = f"[\n    {rows}\n  ]"
            elif key in ("metrics", "meta"):
                text = json.dumps(value, indent=2, sort_keys=True).replace("\n", "\n  ")
            else:
                text = json.dumps(value)
            lines.append(f"  {json.dumps(key)}: {text}{',' if k < len(items) - 1 else ''}")
        lines.append("}\n")
        Path(path).write_text("\n".join(lines), encoding="utf-8")

    @classmethod
    def load(cls, path: str | Path) -> MLP:
        """Read a `mrrig-mlp/1` file; any defect raises a one-line ModelError naming the field."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise ModelError(f"{path}: cannot read: {exc.strerror}") from None
        except UnicodeDecodeError as exc:
            raise ModelError(f"{path}: not a JSON model file: {exc}") from None
        return cls.from_text(text, path)

    @classmethod
    def from_text(cls, text: str, path: str | Path) -> MLP:
        """`load` of a file's content already read (`path` names it in errors)."""
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ModelError(f"{path}: not a JSON model file: {exc}".replace("\n", " ")) from None
        except RecursionError:
            raise ModelError(f"{path}: not a model file: JSON nested too deeply") from None
        except ValueError as exc:  # an integer of more digits than Python converts
            raise ModelError(f"{path}: not a JSON model file: {exc}") from None
        if not isinstance(doc, dict):
            raise ModelError(f"{path}: not a JSON object")
        huge = _huge_integer(doc)
        if huge is not None:
            raise ModelError(
                f"{path}: field '{huge[0]}': an integer of {huge[1]} digits, beyond a float's range"
            )
        if doc.get("format") != FORMAT:
            got = doc.get("format")
            raise ModelError(f"{path}: field 'format': expected {FORMAT!r}, got {got!r}")
        kwargs: dict[str, Any] = {}
        for name, kind in _FIELDS.items():
            if name not in doc:
                raise ModelError(f"{path}: field '{name}': missing")
            value = doc[name]
            if not _has_kind(value, kind):
                raise ModelError(f"{path}: field '{name}': expected {kind}")
            kwargs[name] = value
        try:
            model = cls(**kwargs)
        except ModelError as exc:
            raise ModelError(f"{path}: {str(exc).removeprefix('model: ')}") from None
        if doc.get("hidden", model.hidden) != model.hidden:
            raise ModelError(
                f"{path}: field 'hidden': {doc['hidden']!r} but W1 has {model.hidden} rows"
            )
        return model


_FIELDS: dict[str, str] = {
    "input_names": "list of strings",
    "input_units": "list of strings",
    "output_name": "string",
    "output_unit": "string",
    "fingerprint": "string",
    "in_mean": "list of numbers",
    "in_std": "list of numbers",
    "out_mean": "number",
    "out_std": "number",
    "W1": "list of lists of numbers",
    "b1": "list of numbers",
    "W2": "list of numbers",
    "b2": "number",
    "metrics": "object",
    "meta": "object",
}


def _huge_integer(doc: Any) -> tuple[str, int] | None:
    """(dotted field, about how many digits) of an integer in a decoded JSON document that no
    float can hold (`float()` of it raises OverflowError), None if there is none."""
    stack: list[tuple[str, Any]] = [("", doc)]
    while stack:
        where, value = stack.pop()
        if isinstance(value, int) and not isinstance(value, bool) and abs(value) > _FLOAT_MAX:
            return where, int(value.bit_length() * math.log10(2)) + 1
        if isinstance(value, dict):
            stack += [(f"{where}.{k}" if where else str(k), v) for k, v in value.items()]
        elif isinstance(value, list):
            stack += [(f"{where}.{k}", v) for k, v in enumerate(value)]
    return None


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _has_kind(value: Any, kind: str) -> bool:
    match kind:
        case "string":
            return isinstance(value, str)
        case "number":
            return _is_number(value)
        case "object":
            return isinstance(value, dict)
        case "list of strings":
            return isinstance(value, list) and all(isinstance(v, str) for v in value)
        case "list of numbers":
            return isinstance(value, list) and all(_is_number(v) for v in value)
        case "list of lists of numbers":
            return isinstance(value, list) and all(_has_kind(r, "list of numbers") for r in value)
    raise AssertionError(kind)


def _plain(value: Any) -> Any:
    """JSON-ready copy of metrics/meta: numpy scalars and arrays to Python, non-finite to None."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
