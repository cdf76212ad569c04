"""Displacement playback (issue 41, item 6): the actuator's STREAM plays a recorded stroke (a road
stroke, a sweep, a block program) from a CSV file instead of a numerical model's, with the
feasibility check before arming.

The stroke CSV: UTF-8 text (a byte-order mark dropped), a header naming the columns
`t_s` (time, s, strictly increasing), `x_m` (displacement, m, positive = extension, 0 = stroke
centre, as the rig's Displacement) and optionally `v_m_s` (its velocity, m/s), in any order,
other columns ignored; or no header and two (t, x) or three (t, x, v) columns. Blank lines
are skipped; every other row must be finite numbers (a dropped row would be bridged by
interpolation and played as if recorded).

Resampled to the loop's period from the record's first time: with a velocity column, the cubic
Hermite interpolant through (t, x, v); without, the cubic spline through (t, x) (not-a-knot).
Velocity and acceleration are the interpolant's derivatives at each frame: what is checked is
what is played (a spline's overshoot at a sharp corner of a block program is checked too). A
monotone cubic (PCHIP) was tried and left: it flattens every extremum, so its second
derivative read a 20 Hz, 10 mm sine sampled at 2 kHz as 241 m/s^2 where it has 80. The
playback starts from rest at stroke centre: the step from 0 to the first sample in one frame
is part of the velocity check.

Pure numerics apart from `read_stroke_csv`.
"""

from __future__ import annotations

import csv
import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicHermiteSpline, CubicSpline

from mrrig.errors import MrrigError
from mrrig.loop.profile_csv import decode

COLUMNS = ("t_s", "x_m", "v_m_s")


class StrokeFileError(MrrigError, ValueError):
    """A stroke CSV that cannot be read; the message names the file, the line and the column."""


@dataclass(frozen=True)
class StrokeRecord:
    t_s: np.ndarray
    x_m: np.ndarray
    v_m_s: np.ndarray | None  # None: no velocity column

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])


@dataclass(frozen=True)
class Resampled:
    """The stroke at the loop's frames k = 0..n-1 (t = k period from the record's start)."""

    period_s: float
    x_m: np.ndarray
    v_m_s: np.ndarray
    a_m_s2: np.ndarray

    @property
    def duration_s(self) -> float:
        return (self.x_m.size - 1) * self.period_s

    def head(self, frames: int) -> Resampled:
        """Its first `frames` frames (all, if it has fewer)."""
        n = frames
        return Resampled(self.period_s, self.x_m[:n], self.v_m_s[:n], self.a_m_s2[:n])


@dataclass(frozen=True)
class ActuatorLimits:
    """What the rig's actuator can play: |x| within the STREAM's envelope (and the stroke),
    |v| within the valve's flow limit, |a| within what its force gives the moving mass."""

    stroke_m: float
    velocity_m_s: float
    acceleration_m_s2: float


def _is_numbers(cells: list[str]) -> bool:
    try:
        [float(c) for c in cells]
    except ValueError:
        return False
    return bool(cells)


def parse_stroke_csv(text: str, source: str) -> StrokeRecord:
    """The record of a stroke CSV's text; StrokeFileError naming `source`, the line and the
    column of the first thing wrong."""
    lines = [(n, line) for n, line in enumerate(text.splitlines(), 1) if line.strip()]
    if not lines:
        raise StrokeFileError(f"{source}: empty stroke file (expected columns t_s,x_m[,v_m_s])")
    first = next(csv.reader([lines[0][1]]))
    if _is_numbers(first):
        if len(first) not in (2, 3):
            raise StrokeFileError(
                f"{source}:{lines[0][0]}: without a header 2 or 3 columns (t_s,x_m[,v_m_s]), "
                f"got {len(first)}"
            )
        names = COLUMNS[: len(first)]
        cols = tuple(range(len(first)))
    else:
        header = [c.strip() for c in first]
        missing = [c for c in COLUMNS[:2] if c not in header]
        if missing:
            raise StrokeFileError(
                f"{source}:{lines[0][0]}: header {','.join(header)!r} has no column "
                f"{' or '.join(missing)} (expected t_s, x_m and optionally v_m_s)"
            )
        names = tuple(c for c in COLUMNS if c in header)
        cols = tuple(header.index(c) for c in names)
        lines = lines[1:]
    rows: list[list[float]] = []
    for number, line in lines:
        cells = next(csv.reader([line]))
        row = []
        for col, name in zip(cols, names, strict=True):
            cell = cells[col].strip() if col < len(cells) else ""
            try:
                value = float(cell)
            except ValueError:
                raise StrokeFileError(
                    f"{source}:{number}: column {name!r}: {cell!r} is not a number"
                ) from None
            if not math.isfinite(value):
                raise StrokeFileError(f"{source}:{number}: column {name!r}: {cell!r} is not finite")
            row.append(value)
        if rows and not row[0] > rows[-1][0]:
            raise StrokeFileError(
                f"{source}:{number}: t_s must be strictly increasing ({row[0]:g} after "
                f"{rows[-1][0]:g})"
            )
        rows.append(row)
    if len(rows) < 2:
        raise StrokeFileError(f"{source}: {len(rows)} sample(s): a stroke needs at least 2")
    data = np.array(rows, dtype=float)
    v = data[:, 2] if len(names) == 3 else None
    return StrokeRecord(data[:, 0], data[:, 1], v)


def read_stroke_csv(path: str | Path) -> StrokeRecord:
    """`parse_stroke_csv` of a file; StrokeFileError naming it if it cannot be read."""
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise StrokeFileError(f"{path}: cannot read the stroke file: {exc.strerror}") from None
    try:
        text = decode(raw, str(path))
    except MrrigError as exc:
        raise StrokeFileError(str(exc)) from None
    return parse_stroke_csv(text, str(path))


def resample(record: StrokeRecord, period_s: float) -> Resampled:
    """The record at every `period_s` from its first time to its last (see the module)."""
    t = record.t_s - record.t_s[0]
    n = int(math.floor(t[-1] / period_s + 1e-9)) + 1
    tk = np.arange(n) * period_s
    if record.v_m_s is not None:
        f = CubicHermiteSpline(t, record.x_m, record.v_m_s)
    else:
        f = CubicSpline(t, record.x_m)
    x, v, a = f(tk), f(tk, 1), f(tk, 2)
    for series in (x, v, a):
        series.setflags(write=False)
    return Resampled(period_s, x, v, a)


@functools.lru_cache(maxsize=8)
def load_resampled(path: str, period_s: float) -> Resampled:
    """The stroke file at `path` resampled, read once per process (the daemon reads it when it
    loads its scenario, before any run; arming then reads no file)."""
    return resample(read_stroke_csv(path), period_s)


def infeasibility(stroke: Resampled, limits: ActuatorLimits, source: str) -> str | None:
    """Why the actuator cannot play `stroke`, naming the first sample it cannot (its frame,
    time, value and the limit), or None. The step from rest at 0 to the first sample in one
    frame counts as a velocity."""
    dt = stroke.period_s
    start_v = stroke.x_m[0] / dt
    checks = (
        ("|x|", np.abs(stroke.x_m), limits.stroke_m, 1e3, "mm"),
        ("|v|", np.abs(stroke.v_m_s), limits.velocity_m_s, 1.0, "m/s"),
        ("|a|", np.abs(stroke.a_m_s2), limits.acceleration_m_s2, 1.0, "m/s^2"),
    )
    first: tuple[int, str] | None = None
    if abs(start_v) > limits.velocity_m_s:
        first = (
            0,
            f"the step from rest at 0 to x {stroke.x_m[0] * 1e3:.3f} mm in one frame is "
            f"{abs(start_v):.3g} m/s, beyond the actuator's {limits.velocity_m_s:g} m/s "
            "(start the record at stroke centre)",
        )
    for what, values, limit, scale, unit in checks:
        over = np.flatnonzero(values > limit)
        if over.size and (first is None or over[0] < first[0]):
            k = int(over[0])
            first = (
                k,
                f"{what} {values[k] * scale:.4g} {unit} beyond the actuator's "
                f"{limit * scale:g} {unit}",
            )
    if first is None:
        return None
    k, why = first
    return f"{source}: not playable: frame {k} (t {k * dt:.4f} s): {why}"


class StrokePlayback:
    """The playback's 'substructure' for `HybridStep`: the resampled stroke, one frame per
    step, whatever the measured force (recorded: the run's telemetry has it). Its future is
    known, so the model compensation sends the record itself over the estimated delay."""

    def __init__(self, stroke: Resampled) -> None:
        self.stroke = stroke
        self.period_s = stroke.period_s
        self.reset()

    @property
    def steps(self) -> int:
        return self.stroke.x_m.size - 1

    def reset(self) -> None:
        self.k = 0
        self.force_n = 0.0
        self.acceleration_m_s2 = 0.0  # the record's at the frame last stepped
        self.x = np.array([self.stroke.x_m[0], self.stroke.v_m_s[0]])

    @property
    def stroke_m(self) -> float:
        return float(self.stroke.x_m[min(self.k, self.steps)])

    @property
    def stroke_velocity_m_s(self) -> float:
        return float(self.stroke.v_m_s[min(self.k, self.steps)])

    def predicted_stroke(self, lead_frames: float) -> tuple[float, float]:
        """(x, v) of the record `lead_frames` ahead (linear between frames; held at its end)."""
        at = min(self.k + lead_frames, float(self.steps))
        j = int(at)
        frac = at - j
        j1 = min(j + 1, self.steps)
        s = self.stroke
        x = (1.0 - frac) * s.x_m[j] + frac * s.x_m[j1]
        v = (1.0 - frac) * s.v_m_s[j] + frac * s.v_m_s[j1]
        return float(x), float(v)

    def step(self, force_n: float) -> None:
        """Frame k's acceleration recorded, then on to frame k + 1 (the force is not used)."""
        self.force_n = force_n
        self.acceleration_m_s2 = float(self.stroke.a_m_s2[min(self.k, self.steps)])
        self.k += 1
        self.x = np.array([self.stroke_m, self.stroke_velocity_m_s])
