"""Data sets: the paper's simulation protocol (A), the rig characterization matrix (B), and
recorded CSV files (C), all as `Series` in SI units (spec/modeling.md section 4)."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
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
    current_unit: str = "A"  # the command's unit: "A" (coil current) or "V" (driver voltage)

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


# Units accepted per field, as factors to SI. The damper command is a coil current (A) or a
# current driver's input voltage (V): volts stay volts (the model's command unit says which).
CSV_UNITS: dict[str, dict[str, float]] = {
    "t": {"s": 1.0, "ms": 1e-3},
    "x": {"m": 1.0, "mm": 1e-3, "cm": 1e-2},
    "xd": {"m/s": 1.0, "mm/s": 1e-3, "cm/s": 1e-2},
    "xdd": {"m/s^2": 1.0, "mm/s^2": 1e-3, "cm/s^2": 1e-2},
    "force": {"N": 1.0, "kN": 1e3},
    "current": {"A": 1.0, "mA": 1e-3, "V": 1.0},
}
COMMAND_UNITS = {"A": "A", "mA": "A", "V": "V"}  # the command's unit in the Series
_REQUIRED = ("t", "x", "current", "force")
CSV_CHUNK_ROWS = 200_000  # rows read at a time: a large file streams in chunks (~100 MB)
# Headers `NAME_UNIT` that name a field without a column map (e.g. t_s, x_cm, force_n, command_v)
_HEADER_FIELDS = {
    "t": "t",
    "time": "t",
    "x": "x",
    "xd": "xd",
    "xdd": "xdd",
    "force": "force",
    "f": "force",
    "current": "current",
    "i": "current",
    "command": "current",
}
_HEADER_UNITS = {
    "t": {"s": "s", "ms": "ms"},
    "x": {"m": "m", "mm": "mm", "cm": "cm"},
    "xd": {"m_s": "m/s", "mm_s": "mm/s", "cm_s": "cm/s"},
    "xdd": {"m_s2": "m/s^2", "mm_s2": "mm/s^2", "cm_s2": "cm/s^2"},
    "force": {"n": "N", "kn": "kN"},
    "current": {"a": "A", "ma": "mA", "v": "V"},
}


def csv_header(path: str | Path) -> list[str]:
    """The header of a CSV (its first line that is neither blank nor a # comment), stripped;
    a one-line DataError if the file cannot be read."""
    import pandas as pd  # noqa: PLC0415 - pandas is slow to import; only CSV users pay for it

    path = Path(path)
    try:
        head = pd.read_csv(
            path,
            nrows=0,
            comment="#",
            skip_blank_lines=True,
            encoding="utf-8-sig",
            index_col=False,
        )
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise DataError(f"{path}: cannot read: {reason}".replace("\n", " ")) from exc
    return [str(h).strip() for h in head.columns]


def columns_from_header(header: list[str]) -> tuple[dict[str, str], dict[str, str]] | None:
    """(columns, units) from headers that name field and unit (`t_s`, `x_cm`, `xd_cm_s`,
    `force_n`, `command_v`, `current_a`), or None when t, x, force and a command are not all
    named so. Unrecognised headers are ignored."""
    columns: dict[str, str] = {}
    units: dict[str, str] = {}
    for h in header:
        name, _, unit = h.lower().partition("_")
        field = _HEADER_FIELDS.get(name)
        if field is None or field in columns or unit not in _HEADER_UNITS[field]:
            continue
        columns[field] = h
        units[field] = _HEADER_UNITS[field][unit]
    if not all(f in columns for f in _REQUIRED):
        return None
    return columns, units


def _file_line(path: Path, data_row: int) -> int:
    """The file line (1-based) of data row `data_row` (0-based), blank and comment lines
    skipped as the reader skips them: only for an error message."""
    seen_header = False
    row = -1
    with path.open(encoding="utf-8-sig", errors="replace") as fh:
        for number, line in enumerate(fh, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            if not seen_header:
                seen_header = True
                continue
            row += 1
            if row == data_row:
                return number
    return -1


def _csv_scales(path: Path, columns: dict[str, str], units: dict[str, str]) -> dict[str, float]:
    """Each mapped field's factor to SI; a one-line DataError for an unknown field or unit, a
    required field without a column or a column the header lacks."""
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
    header = csv_header(path)
    for field, col in columns.items():
        if col not in header:
            raise DataError(f"{path}: field {field!r}: no column {col!r} in the header")
    return scale


def iter_csv(
    path: str | Path,
    columns: dict[str, str],
    units: dict[str, str] | None = None,
    chunk_rows: int = CSV_CHUNK_ROWS,
) -> Iterator[dict[str, np.ndarray]]:
    """The CSV's mapped fields in SI units, `chunk_rows` rows at a time (memory bounded by
    the chunk, whatever the file's size): what `load_csv` reads, as it reads it."""
    import pandas as pd  # noqa: PLC0415 - see csv_header

    path = Path(path)
    scale = _csv_scales(path, columns, units or {})
    fields = list(columns)
    wanted = [columns[f] for f in fields]
    done = 0
    try:
        reader = pd.read_csv(
            path,
            usecols=lambda h: str(h).strip() in wanted,
            dtype=str,
            comment="#",
            skip_blank_lines=True,
            encoding="utf-8-sig",
            index_col=False,
            chunksize=chunk_rows,
            keep_default_na=False,
            skipinitialspace=True,
        )
        for chunk in reader:
            chunk.columns = [str(h).strip() for h in chunk.columns]
            out = {}
            for field, col in zip(fields, wanted, strict=True):
                values = pd.to_numeric(chunk[col].str.strip(), errors="coerce").to_numpy(
                    dtype=float, na_value=np.nan
                )
                bad = ~np.isfinite(values)
                if bad.any():
                    r = int(np.flatnonzero(bad)[0])
                    line = _file_line(path, done + r)
                    raise DataError(
                        f"{path}: line {line}: column {col!r} (field {field!r}): "
                        f"not a finite number: {chunk[col].iloc[r]!r}"
                    )
                out[field] = values * scale[field]
            done += len(chunk)
            yield out
    except (OSError, UnicodeDecodeError, ValueError, pd.errors.ParserError) as exc:
        if isinstance(exc, DataError):
            raise
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise DataError(f"{path}: cannot read: {reason}".replace("\n", " ")) from exc
    if done == 0:
        raise DataError(f"{path}: no data rows")


def load_csv(
    path: str | Path, columns: dict[str, str], units: dict[str, str] | None = None
) -> Series:
    """Read a CSV into a Series in SI units (the command in A, or in V for a driver voltage).

    `columns` maps our fields (t, x, current, force; optional xd, xdd) to CSV headers, `units`
    gives each field's unit (SI where absent: s, m, m/s, m/s^2, N, A). Absent xd/xdd are None.
    Read by pandas in chunks of `CSV_CHUNK_ROWS` (`iter_csv`): blank lines, # comment lines,
    a BOM, quoted headers and a trailing comma are fine. Any problem raises DataError with a
    one-line message naming the file, and the line and field of a bad value.
    """
    path = Path(path)
    units = units or {}
    parts: dict[str, list[np.ndarray]] = {f: [] for f in columns}
    for chunk in iter_csv(path, columns, units):
        for field, values in chunk.items():
            parts[field].append(values)
    data = {f: np.concatenate(parts[f]) for f in columns}
    return Series(
        t=data["t"],
        x=data["x"],
        xd=data.get("xd"),
        xdd=data.get("xdd"),
        current=data["current"],
        force=data["force"],
        name=path.stem,
        current_unit=COMMAND_UNITS[units.get("current", "A")],
    )
