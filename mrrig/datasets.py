"""Data sets: the paper's simulation protocol (A), the rig characterization matrix (B), and
recorded CSV files (C), all as `Series` in SI units (spec/modeling.md section 4)."""

from __future__ import annotations

import csv
import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damper.plant import BoucWenParams, simulate
from damper.signals import bandlimited_noise, sine
from mrrig.errors import MrrigError

DATASET_A_DT_S = 1e-3
DATASET_A_VMAX_V = 12.0  # the training range of data set A
DATASET_A_TRAINING_SEED = 4101
DATASET_A_VALIDATION_SEED = 4202
DATASET_A_VALIDATION_NAMES = ("1,k=1", "1,k=2", "1,k=3", "2", "3,k=1", "3,k=2", "3,k=3")
DATASET_B_SEED = 4303
# Sensor resolution of the CAN frames (spec/can-protocol.md, RigSensors scaling).
DISPLACEMENT_LSB_M = 1e-6
FORCE_LSB_N = 0.01


# The tidy characterization data file (mrrig characterize writes it, mrrig train reads it):
# x = the daemon's Kalman displacement, xd/xdd its estimates, force = the load cell.
TIDY_HEADER = (
    "run_id",
    "t_s",
    "x_m",
    "xd_m_s",
    "xdd_m_s",
    "force_n",
    "current_cmd_a",
    "current_meas_a",
)


class DataError(MrrigError, ValueError):
    """A data file that cannot be read as a Series; the message is one line."""


@dataclass
class Series:
    """Equally long 1-D series in SI units.

    `current` is the damper command: volts in data set A, amperes for the rig. `xd` and `xdd`
    are None when a recording has no such columns (the caller estimates them). `x_meas` and
    `force_meas` are the noisy, quantised sensor values where `x` and `force` are the truth.
    """

    t: np.ndarray
    x: np.ndarray
    xd: np.ndarray | None
    xdd: np.ndarray | None
    current: np.ndarray
    force: np.ndarray
    name: str = ""
    run_id: np.ndarray | None = None
    x_meas: np.ndarray | None = None
    force_meas: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = np.asarray(self.t).shape
        for field in ("t", "x", "xd", "xdd", "current", "force", "run_id", "x_meas", "force_meas"):
            value = getattr(self, field)
            if value is None:
                continue
            dtype = int if field == "run_id" else float
            arr = np.asarray(value, dtype=dtype)
            if arr.ndim != 1 or arr.shape != n:
                raise ValueError(f"Series {self.name!r}: {field} has shape {arr.shape}, want {n}")
            setattr(self, field, arr)

    def __len__(self) -> int:
        return self.t.size


def _voltage_schedule_a(t_s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Data set A training voltage (paper Table 4 as the spec reads it), clipped at 0."""
    v = np.empty_like(t_s)
    noisy = t_s < 60.0
    v[noisy] = bandlimited_noise(int(noisy.sum()), DATASET_A_DT_S, 4.0, 6.0, rng)[0] + 6.0
    v[(t_s >= 60.0) & (t_s < 70.0)] = 12.0
    v[(t_s >= 70.0) & (t_s < 80.0)] = 6.0
    v[(t_s >= 80.0) & (t_s < 90.0)] = 0.0
    late = t_s >= 90.0
    v[late] = 6.0 * np.sin(4.0 * np.pi * t_s[late]) + 6.0
    return np.maximum(v, 0.0)


def dataset_a_training(seed: int = DATASET_A_TRAINING_SEED, substep_s: float = 1e-4) -> Series:
    """Data set A training, 100 s at 1 ms: displacement noise 0-3 Hz, peak 2.5 cm; voltage
    per the schedule; force from the plant (preset paper-volt), open loop."""
    rng = np.random.default_rng(seed)
    n = round(100.0 / DATASET_A_DT_S)
    t = np.arange(n) * DATASET_A_DT_S
    x, xd, xdd = bandlimited_noise(n, DATASET_A_DT_S, 3.0, 0.025, rng)
    v = _voltage_schedule_a(t, rng)
    f = simulate(BoucWenParams.preset("paper-volt"), t, x, xd, v, substep_s)
    return Series(t=t, x=x, xd=xd, xdd=xdd, current=v, force=f, name="A-training")


def dataset_a_validation(
    seed: int = DATASET_A_VALIDATION_SEED, substep_s: float = 1e-4
) -> list[Series]:
    """The 7 validation cases of data set A (6 s each, Table 6 column order); force is the
    plant's open-loop force, the desired force of the tracking benchmark."""
    rng = np.random.default_rng(seed)
    n = round(6.0 / DATASET_A_DT_S)
    t = np.arange(n) * DATASET_A_DT_S
    noise_x = bandlimited_noise(n, DATASET_A_DT_S, 2.0, 0.02, rng)
    noise_v = np.maximum(bandlimited_noise(n, DATASET_A_DT_S, 2.0, 2.0, rng)[0] + 2.0, 0.0)
    cases = [(sine(t, 0.01, k), np.full(n, 1.5)) for k in (1, 2, 3)]
    cases.append((noise_x, noise_v))
    cases += [(noise_x, 1.5 + 0.75 * np.sin(2.0 * k * np.pi * t)) for k in (1, 2, 3)]
    x = np.stack([c[0][0] for c in cases])
    xd = np.stack([c[0][1] for c in cases])
    v = np.stack([c[1] for c in cases])
    f = simulate(BoucWenParams.preset("paper-volt"), t, x, xd, v, substep_s)
    return [
        Series(t=t, x=x[i], xd=xd[i], xdd=c[0][2], current=v[i], force=f[i], name=name)
        for i, (c, name) in enumerate(zip(cases, DATASET_A_VALIDATION_NAMES, strict=True))
    ]


def dataset_b_conditions(
    amplitudes_m: tuple[float, ...], freqs_hz: tuple[float, ...], currents_a: tuple[float, ...]
) -> np.ndarray:
    """Rows [amplitude_m, freq_hz, current_a] per run; the row index is the run id
    (current outermost, then frequency, then amplitude, as paper Table 1 lists them)."""
    rows = [(a, f, i) for i, f, a in itertools.product(currents_a, freqs_hz, amplitudes_m)]
    return np.array(rows, dtype=float).reshape(-1, 3)


def dataset_b(
    amplitudes_m: tuple[float, ...] = (0.010, 0.015, 0.020),
    freqs_hz: tuple[float, ...] = (2.0, 3.0, 4.0, 5.0, 6.0),
    currents_a: tuple[float, ...] = tuple(round(0.2 * k, 1) for k in range(10)),
    duration_s: float = 1.0,
    settle_s: float = 0.5,
    fs_hz: float = 500.0,
    displacement_noise_m: float = 1e-5,
    force_noise_n: float = 2.0,
    seed: int = DATASET_B_SEED,
    substep_s: float = 1e-4,
) -> Series:
    """The rig characterization matrix (paper Table 1), simulated with preset rig-current.

    Each run is a stroke-centred sine at constant current, simulated for settle_s + duration_s
    (all runs in one numpy batch); the first settle_s is dropped and `t` restarts at 0 in each
    run. `x_meas`/`force_meas` carry Gaussian sensor noise (standard deviations given) and the
    CAN quantisation (1e-6 m, 0.01 N); `x`, `xd`, `xdd`, `force` are the truth.
    """
    cond = dataset_b_conditions(amplitudes_m, freqs_hz, currents_a)
    n_runs = cond.shape[0]
    dt_s = 1.0 / fs_hz
    n_settle = round(settle_s * fs_hz)
    n_keep = round(duration_s * fs_hz)
    t = np.arange(n_settle + n_keep) * dt_s
    amp, freq, cur = (cond[:, j : j + 1] for j in range(3))
    x, xd, xdd = sine(t[None, :], amp, freq)
    current = np.broadcast_to(cur, x.shape)
    f = simulate(BoucWenParams.preset("rig-current"), t, x, xd, current, substep_s)
    keep = slice(n_settle, None)
    x, xd, xdd, current, f = (a[:, keep].ravel() for a in (x, xd, xdd, current, f))
    rng = np.random.default_rng(seed)
    x_meas = np.round((x + rng.normal(0.0, displacement_noise_m, x.shape)) / DISPLACEMENT_LSB_M)
    f_meas = np.round((f + rng.normal(0.0, force_noise_n, f.shape)) / FORCE_LSB_N)
    return Series(
        t=np.tile(t[keep] - t[n_settle], n_runs),
        x=x,
        xd=xd,
        xdd=xdd,
        current=current,
        force=f,
        name="B",
        run_id=np.repeat(np.arange(n_runs), n_keep),
        x_meas=x_meas * DISPLACEMENT_LSB_M,
        force_meas=f_meas * FORCE_LSB_N,
    )


# Units accepted per field, as factors to SI.
CSV_UNITS: dict[str, dict[str, float]] = {
    "t": {"s": 1.0, "ms": 1e-3},
    "x": {"m": 1.0, "mm": 1e-3, "cm": 1e-2},
    "xd": {"m/s": 1.0, "mm/s": 1e-3, "cm/s": 1e-2},
    "xdd": {"m/s^2": 1.0, "mm/s^2": 1e-3, "cm/s^2": 1e-2},
    "force": {"N": 1.0, "kN": 1e3},
    "current": {"A": 1.0, "mA": 1e-3},
}
_REQUIRED = ("t", "x", "current", "force")


def load_csv(
    path: str | Path, columns: dict[str, str], units: dict[str, str] | None = None
) -> Series:
    """Read a CSV into a Series in SI units.

    `columns` maps our fields (t, x, current, force; optional xd, xdd) to CSV headers, `units`
    gives each field's unit (SI where absent: s, m, m/s, m/s^2, N, A). Absent xd/xdd are None.
    Any problem raises DataError with a one-line message naming the file and the field.
    """
    path = Path(path)
    units = units or {}
    for field in itertools.chain(columns, units):
        if field not in CSV_UNITS:
            raise DataError(f"{path}: unknown field {field!r} (known: {', '.join(CSV_UNITS)})")
    for field in _REQUIRED:
        if field not in columns:
            raise DataError(f"{path}: no column given for field {field!r}")
    scale = {}
    for field in columns:
        unit = units.get(field, next(iter(CSV_UNITS[field])))
        if unit not in CSV_UNITS[field]:
            known = ", ".join(CSV_UNITS[field])
            raise DataError(f"{path}: field {field!r}: unknown unit {unit!r} (known: {known})")
        scale[field] = CSV_UNITS[field][unit]
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise DataError(f"{path}: cannot read: {reason}".replace("\n", " ")) from exc
    if not rows:
        raise DataError(f"{path}: no data rows")
    data: dict[str, np.ndarray] = {}
    for field, col in columns.items():
        if col not in header:
            raise DataError(f"{path}: field {field!r}: no column {col!r} in the header")
        j = header.index(col)
        values = np.empty(len(rows))
        for r, row in enumerate(rows):
            text = row[j] if j < len(row) else ""
            try:
                value = float(text)
            except ValueError:
                value = math.nan
            if not math.isfinite(value):
                raise DataError(
                    f"{path}: column {col!r} (field {field!r}), data row {r + 1}: "
                    f"not a finite number: {text!r}"
                )
            values[r] = value
        data[field] = values * scale[field]
    return Series(
        t=data["t"],
        x=data["x"],
        xd=data.get("xd"),
        xdd=data.get("xdd"),
        current=data["current"],
        force=data["force"],
        name=path.stem,
    )
