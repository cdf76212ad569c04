"""Error metrics of the paper (eqs 41-43) and the run summaries built on them."""

from __future__ import annotations

import numpy as np


def error_norm(f_des: np.ndarray, f_act: np.ndarray) -> float:
    """Et = eps_t / sigma_f: tracking error relative to the desired force's spread.

    For uniformly sampled signals the integrals of eqs 42-43 reduce to sums with the same dt,
    which cancels in the ratio.
    """
    f_des = np.asarray(f_des, dtype=float)
    f_act = np.asarray(f_act, dtype=float)
    eps_t = np.sqrt(np.sum((f_des - f_act) ** 2))  # eq. 42
    sigma_f = np.sqrt(np.sum((f_des - f_des.mean()) ** 2))  # eq. 43
    return float(eps_t / sigma_f)  # eq. 41


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Root-mean-square difference of two equally long arrays."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    return float(np.sqrt(np.mean(d * d)))


def percentiles(values: np.ndarray, qs: tuple[float, ...] = (50, 95, 99, 99.9)) -> dict[str, float]:
    """Named percentiles (`p50`, `p99.9`, ...) plus `max`; NaN when there are no values."""
    v = np.asarray(values, dtype=float)
    out = {f"p{q:g}": float(np.percentile(v, q)) if v.size else float("nan") for q in qs}
    out["max"] = float(v.max()) if v.size else float("nan")
    return out
