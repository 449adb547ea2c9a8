"""Compiled per-point tests of ``ground.nist`` against a surface: mowing and the ground band.

Each is one pass over the points instead of half a dozen numpy expressions,
each of which allocates and fills a fresh array of millions of floats. The
arithmetic is the numpy code's, operation for operation, so the results are
the same bit for bit: a tolerance ``tol + k × min(slope, cap)`` (NaN slopes stay
NaN, as ``np.minimum`` keeps them) against the height ``z − surface``.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


def below_limit(
    z: NDArray[np.float64],
    surface: NDArray[np.float64],
    slope: NDArray[np.float64] | None,
    tol: float,
    per_slope: float,
    cap: float,
) -> NDArray[np.int64]:
    """Indices of the points with ``z − surface ≤ tol + per_slope × min(slope, cap)``
    (just ``tol`` when ``slope`` is None): the points mowing keeps."""
    z, surface = _f64(z), _f64(surface)
    if slope is None:
        return _below_limit(z, surface, np.zeros(0), False, float(tol), 0.0, 0.0)
    return _below_limit(z, surface, _f64(slope), True, float(tol), float(per_slope), float(cap))


def ground_band(
    z: NDArray[np.float64],
    surface: NDArray[np.float64],
    slope: NDArray[np.float64] | None,
    tol_up: float,
    tol_down: float,
    per_slope: float,
    cap: float,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Points from ``tol_down`` under to ``tol_up`` over the surface, both widened by
    ``per_slope × min(slope, cap)`` (not when ``slope`` is None), and points above that."""
    z, surface = _f64(z), _f64(surface)
    if slope is None:
        return _ground_band(z, surface, np.zeros(0), False, float(tol_up), float(tol_down), 0.0, 0.0)
    return _ground_band(z, surface, _f64(slope), True, float(tol_up), float(tol_down), float(per_slope), float(cap))


def _f64(a: NDArray) -> NDArray[np.float64]:
    return np.asarray(a, dtype=np.float64).reshape(-1)


@numba.njit(cache=True)
def _below_limit(
    z: NDArray[np.float64],
    surface: NDArray[np.float64],
    slope: NDArray[np.float64],
    has_slope: bool,
    tol: float,
    per_slope: float,
    cap: float,
) -> NDArray[np.int64]:
    """See ``below_limit``."""
    out = np.empty(z.size, dtype=np.int64)
    m = 0
    for i in range(z.size):
        h = z[i] - surface[i]
        limit = tol
        if has_slope:
            s = slope[i]
            if s > cap:  # noqa: PLR1730 (keeps a NaN slope NaN, as np.minimum does)
                s = cap
            limit = tol + per_slope * s
        out[m] = i  # branch-free: kept when m moves on
        m += h <= limit
    return out[:m].copy()


@numba.njit(cache=True)
def _ground_band(
    z: NDArray[np.float64],
    surface: NDArray[np.float64],
    slope: NDArray[np.float64],
    has_slope: bool,
    tol_up: float,
    tol_down: float,
    per_slope: float,
    cap: float,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """See ``ground_band``."""
    band = np.empty(z.size, dtype=np.bool_)
    above = np.empty(z.size, dtype=np.bool_)
    for i in range(z.size):
        h = z[i] - surface[i]
        up = tol_up
        down = tol_down
        if has_slope:
            s = slope[i]
            if s > cap:  # noqa: PLR1730 (keeps a NaN slope NaN, as np.minimum does)
                s = cap
            w = per_slope * s
            up = tol_up + w
            down = tol_down + w
        a = h > up
        above[i] = a
        band[i] = (not a) and h >= -down
    return band, above
