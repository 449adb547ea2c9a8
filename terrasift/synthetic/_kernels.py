"""Compiled kernels of the synthetic landform generator (``landforms``), kept
apart from the numpy code that calls them so an edit there does not make numba
compile them again (its cache follows the source file).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


@numba.njit(cache=True)
def _bilinear(z: NDArray, lo: float, c: float, px: float, py: float) -> float:
    fx = (px - lo) / c
    fy = (py - lo) / c
    i = int(np.floor(fx))
    j = int(np.floor(fy))
    ny, nx = z.shape
    if i < 0 or j < 0 or i >= nx - 1 or j >= ny - 1:
        return np.nan
    tx = fx - i
    ty = fy - j
    return (
        z[j, i] * (1 - tx) * (1 - ty)
        + z[j, i + 1] * tx * (1 - ty)
        + z[j + 1, i] * (1 - tx) * ty
        + z[j + 1, i + 1] * tx * ty
    )


@numba.njit(cache=True)
def _march(
    z: NDArray,
    lo: float,
    c: float,
    start: NDArray,
    d: NDArray,
    step: float,
    top: NDArray,
    block: int,
) -> NDArray[np.float64]:
    """Ray parameter of each ray's first crossing of the height field (NaN: none).

    ``top``: per ``block`` × ``block`` cells, the highest height of the 3 × 3
    blocks around; while a ray is above it, it skips ahead by as much as keeps
    it within those blocks and above that height.
    """
    n = start.shape[0]
    out = np.full(n, np.nan)
    span = block * c
    for k in range(n):
        horiz = np.hypot(d[k, 0], d[k, 1])
        down = -d[k, 2]
        t = 0.0
        prev = 0.0
        for _ in range(1000000):
            px = start[k, 0] + t * d[k, 0]
            py = start[k, 1] + t * d[k, 1]
            pz = start[k, 2] + t * d[k, 2]
            h = _bilinear(z, lo, c, px, py)
            if np.isnan(h):
                break
            if pz <= h:
                a, b = prev, t
                for _ in range(30):
                    m = 0.5 * (a + b)
                    hm = _bilinear(z, lo, c, start[k, 0] + m * d[k, 0], start[k, 1] + m * d[k, 1])
                    if start[k, 2] + m * d[k, 2] <= hm:
                        b = m
                    else:
                        a = m
                out[k] = b
                break
            bi = int((px - lo) / span)
            bj = int((py - lo) / span)
            adv = step
            if 0 <= bi < top.shape[1] and 0 <= bj < top.shape[0]:
                gap = pz - top[bj, bi]
                if gap > 0:
                    far = gap / max(down, 1e-9)
                    if horiz > 1e-9:
                        far = min(far, span / horiz)
                    adv = max(step, far)
            prev = t
            t += adv
    return out
