"""A forward model's coverage: the envelope of the data it was trained on, and where other
data (a held-out test, the rig's frames) leaves it.

The envelope is what `mrrig train` saw: the range of each input of the present state (x, xd,
xdd and the command as given) and how the power of the force and of the velocity spreads over
frequency (`band_shares`, a few bands). A network's tanh extrapolates outside its training
range, so a frame whose state is outside the ranges is one the model was never shown: the
daemon marks each frame (`Envelope.outside`, a bit per input, a handful of comparisons) and
the summary counts them; `mrrig evaluate` gives the error inside and outside.

Pure numerics: the model file keeps the envelope in its meta (`to_meta`, `from_meta`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mrrig.loop.mlp import ModelError

ENVELOPE_INPUTS = ("x", "xd", "xdd", "command")
ENVELOPE_UNITS = ("m", "m/s", "m/s^2", "A or V")
# the bit of each input in a frame's mark (0: inside on every input)
OUTSIDE_BITS = {name: 1 << k for k, name in enumerate(ENVELOPE_INPUTS)}
# the bands' lower edges, Hz; the last band runs to the data's Nyquist frequency
BAND_EDGES_HZ = (0.0, 1.0, 3.0, 10.0, 30.0, 100.0)
BAND_SIGNALS = ("force", "xd")


def band_labels(edges: tuple[float, ...] = BAND_EDGES_HZ) -> list[str]:
    return [f"{a:g}-{b:g} Hz" for a, b in zip(edges, edges[1:], strict=False)] + [
        f"over {edges[-1]:g} Hz"
    ]


def band_power(signal: np.ndarray, pieces: list[tuple[int, int]], dt_s: float) -> np.ndarray:
    """The signal's power (its mean removed in each piece) in each band of `BAND_EDGES_HZ`,
    summed over the contiguous pieces [start, end) of the rows, by each piece's periodogram."""
    power = np.zeros(len(BAND_EDGES_HZ))
    for a, b in pieces:
        if b - a < 2:
            continue
        v = signal[a:b] - np.mean(signal[a:b])
        p = np.abs(np.fft.rfft(v)) ** 2
        f = np.fft.rfftfreq(b - a, dt_s)
        band = np.searchsorted(BAND_EDGES_HZ, f, side="right") - 1
        power += np.bincount(band[1:], p[1:], minlength=power.size)  # DC left out
    return power


def shares(power: np.ndarray) -> list[float] | None:
    """Each band's share of the power; None without power (a constant signal)."""
    total = float(np.sum(power))
    return [float(v / total) for v in power] if total > 0.0 else None


def band_shares(
    signal: np.ndarray, pieces: list[tuple[int, int]], dt_s: float
) -> list[float] | None:
    """`shares` of `band_power`."""
    return shares(band_power(signal, pieces, dt_s))


def contiguous_pieces(rows: np.ndarray, stretch: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) positions in `rows` (sorted indices) of each piece of consecutive rows
    within one stretch (stretch ids per row of `rows`)."""
    if rows.size == 0:
        return []
    cut = np.flatnonzero((np.diff(rows) != 1) | (stretch[1:] != stretch[:-1])) + 1
    return list(zip(np.r_[0, cut].tolist(), np.r_[cut, rows.size].tolist(), strict=True))


@dataclass(frozen=True)
class Envelope:
    """Ranges [lo, hi] of `ENVELOPE_INPUTS` and the band shares of `BAND_SIGNALS`."""

    lo: tuple[float, ...]
    hi: tuple[float, ...]
    bands: dict[str, list[float] | None]
    sample_period_s: float

    @classmethod
    def of_data(
        cls,
        state: np.ndarray,
        force: np.ndarray,
        xd: np.ndarray,
        pieces: list[tuple[int, int]],
        dt_s: float,
    ) -> Envelope:
        """The envelope of rows `state` (N x 4: x, xd, xdd, command), with the spectra of
        `force` and `xd` over their contiguous `pieces` (`band_shares`)."""
        state = np.asarray(state, dtype=float)
        return cls(
            lo=tuple(float(v) for v in state.min(axis=0)),
            hi=tuple(float(v) for v in state.max(axis=0)),
            bands={
                "force": band_shares(np.asarray(force, dtype=float), pieces, dt_s),
                "xd": band_shares(np.asarray(xd, dtype=float), pieces, dt_s),
            },
            sample_period_s=float(dt_s),
        )

    def to_meta(self) -> dict[str, Any]:
        return {
            "inputs": list(ENVELOPE_INPUTS),
            "units": list(ENVELOPE_UNITS),
            "lo": list(self.lo),
            "hi": list(self.hi),
            "band_edges_hz": list(BAND_EDGES_HZ),
            "band_shares": self.bands,
            "sample_period_s": self.sample_period_s,
        }

    @classmethod
    def from_meta(cls, doc: Any, where: str) -> Envelope:
        """The envelope of a model file's `meta.envelope`; a one-line ModelError naming the
        field when it is not one `to_meta` writes."""

        def bad(field: str, what: str) -> ModelError:
            return ModelError(f"{where}: field 'meta.envelope.{field}': {what}")

        if not isinstance(doc, dict):
            raise ModelError(f"{where}: field 'meta.envelope': expected an object")
        if doc.get("inputs") != list(ENVELOPE_INPUTS):
            raise bad("inputs", f"expected {list(ENVELOPE_INPUTS)}")
        bounds = []
        for field in ("lo", "hi"):
            v = doc.get(field)
            if not (
                isinstance(v, list)
                and len(v) == len(ENVELOPE_INPUTS)
                and all(_finite(e) for e in v)
            ):
                raise bad(field, f"expected {len(ENVELOPE_INPUTS)} finite numbers")
            bounds.append(tuple(float(e) for e in v))
        lo, hi = bounds
        if any(a > b for a, b in zip(lo, hi, strict=True)):
            raise bad("lo", "a lower bound above its upper bound")
        shares = doc.get("band_shares", {})
        if not isinstance(shares, dict):
            raise bad("band_shares", "expected an object")
        period = doc.get("sample_period_s")
        if not (_finite(period) and period > 0):
            raise bad("sample_period_s", "expected a number > 0")
        return cls(lo, hi, {k: shares.get(k) for k in BAND_SIGNALS}, float(period))

    def outside(self, x: float, xd: float, xdd: float, command: float) -> int:
        """One frame's mark: the bits (`OUTSIDE_BITS`) of the inputs outside their range
        (NaN is outside). A few comparisons: the daemon calls it every frame."""
        lo, hi = self.lo, self.hi
        bits = 0
        if not lo[0] <= x <= hi[0]:
            bits |= 1
        if not lo[1] <= xd <= hi[1]:
            bits |= 2
        if not lo[2] <= xdd <= hi[2]:
            bits |= 4
        if not lo[3] <= command <= hi[3]:
            bits |= 8
        return bits

    def outside_rows(self, state: np.ndarray) -> np.ndarray:
        """The marks (int) of rows `state` (N x 4: x, xd, xdd, command)."""
        state = np.asarray(state, dtype=float)
        inside = (state >= np.array(self.lo)) & (state <= np.array(self.hi))
        return ((~inside) * (1 << np.arange(len(ENVELOPE_INPUTS)))).sum(axis=1)


def _finite(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def model_envelope(meta: dict[str, Any], where: str) -> Envelope | None:
    """The envelope of a model's meta, None for a model trained before models kept one."""
    doc = meta.get("envelope")
    return None if doc is None else Envelope.from_meta(doc, where)


def controller_envelope(controller: Any) -> Envelope | None:
    """The envelope of a controller's forward model, None for a controller without a model
    or a model without an envelope (a supervised inverse's is not a forward model's)."""
    model = getattr(controller, "model", None)
    meta = getattr(model, "meta", None)
    if not isinstance(meta, dict) or "current" not in getattr(model, "input_names", ()):
        return None
    return model_envelope(meta, f"the {getattr(controller, 'name', 'controller')}'s model")


def outside_shares(marks: np.ndarray) -> dict[str, Any]:
    """The share of marked frames outside the envelope, and by input (marks: finite ones
    only; NaN marks, frames without an envelope, are not counted)."""
    m = np.asarray(marks, dtype=float)
    m = m[np.isfinite(m)].astype(np.int64)
    n = int(m.size)
    share = (lambda k: float(k) / n) if n else (lambda k: math.nan)  # noqa: E731
    return {
        "frames": n,
        "outside": int((m != 0).sum()),
        "outside_share": share((m != 0).sum()),
        "by_input": {name: share(((m & bit) != 0).sum()) for name, bit in OUTSIDE_BITS.items()},
    }
