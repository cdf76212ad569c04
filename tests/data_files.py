"""Writing the tidy characterization CSV that `mrrig.offline.training.load_tidy` reads, for
tests."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from mrrig.offline.datasets import TIDY_HEADER, Series


def write_tidy(path: str | Path, series: Series, current_meas_a: np.ndarray | None = None) -> None:
    """Write a Series as tidy characterization CSV (`TIDY_HEADER`), floats to 17 digits (a
    round trip is exact); absent xd/xdd/current_meas are written as nan."""
    n = len(series)
    run_id = series.run_id if series.run_id is not None else np.zeros(n, dtype=int)
    nan = np.full(n, np.nan)
    cols = [
        series.t,
        series.x,
        series.xd if series.xd is not None else nan,
        series.xdd if series.xdd is not None else nan,
        series.force,
        series.current,
        nan if current_meas_a is None else np.asarray(current_meas_a, dtype=float),
    ]
    with Path(path).open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(TIDY_HEADER)
        rows = zip(run_id.tolist(), *(c.tolist() for c in cols), strict=True)
        w.writerows([r, *(repr(v) for v in vals)] for r, *vals in rows)
