"""Interest-box geometry for the mixed-measurement filter: frames and angular windows."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def box_frames(P: NDArray[np.float64], roll: float) -> NDArray[np.float64]:
    """Per point a (3, 3) frame whose rows are the ray t, the width axis u and the height axis v.

    v is the vertical made orthogonal to the ray, then the pair (u, v) is turned
    by ``roll`` (radians) about the ray. A vertical ray falls back to the x axis.
    """
    t = P / np.linalg.norm(P, axis=1, keepdims=True)
    up = np.zeros_like(t)
    up[:, 2] = 1.0
    v0 = up - t[:, 2:3] * t
    norm = np.linalg.norm(v0, axis=1, keepdims=True)
    steep = norm[:, 0] < 1e-6
    if steep.any():
        v0[steep] = np.array([1.0, 0.0, 0.0]) - t[steep, 0:1] * t[steep]
        norm[steep] = np.linalg.norm(v0[steep], axis=1, keepdims=True)
    v0 /= norm
    u0 = np.cross(v0, t)
    c, s = np.cos(roll), np.sin(roll)
    u = c * u0 + s * v0
    v = -s * u0 + c * v0
    return np.stack([t, u, v], axis=1)


def window_extent(
    P: NDArray[np.float64],
    r0: NDArray[np.float64],
    frames: NDArray[np.float64],
    width: NDArray[np.float64] | float,
    height: float,
    beta: float,
    n_az: int,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Half-extent (azimuth, elevation), in angular cells, of the cell window around each box's front face."""
    # Angle between the box's height axis and the local elevation direction.
    t = frames[:, 0]
    horiz = np.hypot(t[:, 0], t[:, 1])
    e_el = (
        np.column_stack([-t[:, 2] * t[:, 0], -t[:, 2] * t[:, 1], horiz * horiz])
        / np.maximum(horiz, 1e-12)[:, None]
    )
    roll_c = np.clip(np.abs(np.einsum("ij,ij->i", frames[:, 2], e_el)), 0.0, 1.0)
    roll_s = np.sqrt(1 - roll_c**2)
    hu = roll_c * width / 2 + roll_s * height / 2
    hv = roll_s * width / 2 + roll_c * height / 2
    cos_el = np.maximum(np.hypot(P[:, 0], P[:, 1]) / r0, 0.05)
    na = np.ceil(hu / (r0 * cos_el) / beta + 0.5).astype(np.int64)
    ne = np.ceil(hv / r0 / beta + 0.5).astype(np.int64)
    return np.minimum(na, n_az // 2), ne


def window_pairs(
    r0: NDArray[np.float64],
    ia: NDArray[np.int64],
    ie: NDArray[np.int64],
    na: NDArray[np.int64],
    ne: NDArray[np.int64],
    frames: NDArray[np.float64],
    width: NDArray[np.float64],
    height: float,
    beta: float,
    n_az: int,
    n_el: int,
    occupied: NDArray[np.bool_],
    chunk: int = 4_000_000,
) -> tuple[NDArray[np.intp], NDArray[np.int64]]:
    """(box index, cell) for every occupied angular cell a box covers.

    A cell belongs to a box when the ray through the cell's centre crosses the
    box's front face (|u| ≤ width/2, |v| ≤ height/2); the box's own cell always does.
    ``na``, ``ne`` are the half-extents of the candidate window (``window_extent``).
    """
    if r0.size == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.int64)
    wa, we = 2 * na + 1, 2 * ne + 1
    counts = wa * we
    out_i: list[NDArray] = []
    out_c: list[NDArray] = []
    # Chunks over boxes keep the candidate arrays bounded in memory.
    cum = np.cumsum(counts)
    edges = np.unique(
        np.r_[0, np.searchsorted(cum, np.arange(chunk, cum[-1], chunk), side="right"), counts.size]
    )
    for start, stop in zip(edges[:-1], edges[1:], strict=True):
        sl = slice(int(start), int(stop))
        c = counts[sl]
        item = np.repeat(np.arange(sl.start, sl.stop), c)
        k = np.arange(c.sum()) - np.repeat(np.cumsum(c) - c, c)
        da = k % wa[item] - na[item]
        de = k // wa[item] - ne[item]
        ja = (ia[item] + da) % n_az
        je = ie[item] + de
        ok = (je >= 0) & (je < n_el)
        item, ja, je, da, de = item[ok], ja[ok], je[ok], da[ok], de[ok]
        cell = ja * n_el + je
        ok = occupied[cell]
        item, ja, je, cell, da, de = item[ok], ja[ok], je[ok], cell[ok], da[ok], de[ok]
        az = (ja + 0.5) * beta - np.pi
        el = (je + 0.5) * beta - np.pi / 2
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
        f = frames[item]
        s = np.einsum("ij,ij->i", d, f[:, 0])
        with np.errstate(divide="ignore", invalid="ignore"):
            u = r0[item] * np.einsum("ij,ij->i", d, f[:, 1]) / s
            v = r0[item] * np.einsum("ij,ij->i", d, f[:, 2]) / s
        keep = ((s > 0) & (np.abs(u) <= width[item] / 2) & (np.abs(v) <= height / 2)) | (
            (da == 0) & (de == 0)
        )
        out_i.append(item[keep])
        out_c.append(cell[keep])
    return np.concatenate(out_i), np.concatenate(out_c)
