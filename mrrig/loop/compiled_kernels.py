"""numba's `njit` (cached on disk), or, without numba, a decorator that leaves the function as
it is (`AVAILABLE` False: the daemon runs the Python path; `mrrig.loop.compiled`)."""

from __future__ import annotations

try:
    from numba import njit as _njit

    AVAILABLE = True
except ImportError:
    AVAILABLE = False


def njit(f):  # noqa: ANN001, ANN201
    """`f` compiled on its first call (or loaded from `__pycache__`) where numba is installed."""
    return _njit(cache=True)(f) if AVAILABLE else f
