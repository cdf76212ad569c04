"""Force profile CSVs (time and desired force), one reader for every tool that takes one: the
daemon's `csv` reference (at start-up and by `set_profile`) and `mrrig send-force`.

The file is UTF-8 text; a byte-order mark is dropped (as `mrrig train`'s CSV reader drops it).
With a header the columns are found by name (`t_s`, `force_n` by default, any order, other
columns ignored); without one, the first two columns are time and force. Blank lines are
skipped. Any row that is not two finite numbers is an error naming the file, the line and
the column: a dropped row would be bridged by interpolation and streamed as if it were the
profile. Time must increase strictly.
"""

from __future__ import annotations

import csv
import math

import numpy as np

from mrrig.errors import MrrigError

BOM = "\ufeff"


class ProfileError(MrrigError, ValueError):
    """A force profile that cannot be read; the message names the file and the line."""


def decode(raw: bytes, source: str) -> str:
    """A profile file's bytes as text (UTF-8, a BOM dropped); a ProfileError naming `source`
    and the first byte that is not UTF-8."""
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ProfileError(
            f"{source}: not UTF-8 text: byte 0x{raw[exc.start]:02x} at offset {exc.start}"
            " (save the profile as UTF-8 CSV)"
        ) from None


def read(path: str, time_column: str = "t_s", force_column: str = "force_n"):
    """`parse` of a file read here; a ProfileError naming it if it cannot be read."""
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except OSError as exc:
        raise ProfileError(f"{path}: cannot read force profile: {exc.strerror}") from None
    return parse(decode(raw, str(path)), str(path), time_column, force_column)


def parse(
    text: str, source: str, time_column: str = "t_s", force_column: str = "force_n"
) -> tuple[np.ndarray, np.ndarray]:
    """(time s, force N) of a profile's text; a ProfileError naming `source`, the line and
    the column of the first thing wrong."""
    text = text.removeprefix(BOM)
    lines = [(n, line) for n, line in enumerate(text.splitlines(), 1) if line.strip()]
    names = f"{time_column},{force_column}"
    if not lines:
        raise ProfileError(f"{source}: empty force profile (expected columns {names})")
    first = next(csv.reader([lines[0][1]]))
    cols = (0, 1)
    if not _numbers(first):
        header = [c.strip() for c in first]
        missing = [c for c in (time_column, force_column) if c not in header]
        if missing:
            raise ProfileError(
                f"{source}:{lines[0][0]}: header {','.join(header)!r} has no column"
                f" {' or '.join(missing)} (expected {time_column} and {force_column})"
            )
        cols = (header.index(time_column), header.index(force_column))
        lines = lines[1:]
    rows = []
    for number, line in lines:
        cells = next(csv.reader([line]))
        row = []
        for col, name in zip(cols, (time_column, force_column), strict=True):
            if col >= len(cells) or not cells[col].strip():
                raise ProfileError(
                    f"{source}:{number}: expected {names} numbers, got {line!r}"
                    f" (column {name!r} missing)"
                )
            try:
                row.append(float(cells[col]))
            except ValueError:
                raise ProfileError(
                    f"{source}:{number}: expected {names} numbers, got {line!r}"
                    f" (column {name!r}: {cells[col].strip()!r} is not a number)"
                ) from None
        if not all(map(math.isfinite, row)):
            raise ProfileError(
                f"{source}:{number}: {time_column} and {force_column} must be finite, got {line!r}"
            )
        if rows and not row[0] > rows[-1][0]:
            raise ProfileError(
                f"{source}:{number}: {time_column} must be strictly increasing"
                f" ({row[0]:g} after {rows[-1][0]:g})"
            )
        rows.append(row)
    if not rows:
        raise ProfileError(f"{source}: force profile has a header and no rows")
    data = np.array(rows, dtype=float)
    return data[:, 0], data[:, 1]


def _numbers(cells: list[str]) -> bool:
    try:
        [float(c) for c in cells]
    except ValueError:
        return False
    return bool(cells)
