"""A road's own edges, read on the DTM across the whole object (the filters' ``edges``).

The segments see a road one cross-section at a time, on 2 m tiles. Two kinds of level
strip pass them that a road is not, and both show only over the whole object, on the
DTM's heights (not its tiles):

- a *trough*: a level strip where two slopes meet (a hillside and a ridge's flank), its
  "walls" rising on and on. A cut's walls end: within a few metres past them the ground
  stops rising away from the road (on level ground it is level again; a cut into a
  slope falls past its downhill lip);
- a *verge*: the level ground beside another road, bounded by that road's shoulder or
  wall on one side; on the other it simply goes on at the strip's own height and tilt
  (a ditch dug in it does not make it a road). A road on an embankment or in a cut has
  its own step on both sides.
- a *slope band*: a berm or slope break on an embankment, a terrace on a hillside, only
  gentler than the slope it lies on. On 2 m tiles it reads level (a tile may rise 0.15 m
  over 1.5 m) between a rising and a falling side, as a road along the contour does; on
  the DTM its strip leans with the slope: it falls across, by more than a road's crossfall,
  toward the side the ground past both its sides falls to, and that ground falls more
  steeply.

The object is read along its long axis at stations one tile apart: at each, the strip's
samples inside the polygon (every half tile across), the strip's level (their median),
and the ground in a *near* band (one to three tiles past the strip's edge, each side)
and a *far* band (three to five tiles past it). The strip's tilt across (the slope a
level strip on a hillside keeps) is fitted over the whole object, trimmed of the quarter
of samples farthest from the fit (the shoulders a strip takes in), and taken off every
sample before the bands are compared. A side has an *edge* at a station where its near
band lies more than ``step`` (half the category flatness threshold: a shoulder lower
than the threshold does not register as a tile that is not flat) above or below the
strip's plane; it *rises on* where that band lies more than ``step`` above the strip and
the far band more than ``step`` above the highest ground up to the near band's end (its
90th percentile, noise apart: a cut's wall top, however narrow, and not a ditch dug past
it).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import NDArray
from rasterio import Affine
from scipy import ndimage
from shapely.geometry import MultiPolygon, Polygon

#: reads the DTM around bounds (x0, y0, x1, y1) in map units: heights (NaN for no
#: data) and their geotransform
Reader = Callable[[tuple[float, float, float, float]], tuple[NDArray[np.float64], Affine]]


@dataclass
class Sides:
    """Per station along the object: the near band's height over the strip's plane on
    each side (``left``, ``right``, m), and whether the ground rises on past it
    (``rise_left``, ``rise_right``)."""

    left: NDArray[np.float64]
    right: NDArray[np.float64]
    rise_left: NDArray[np.bool_]
    rise_right: NDArray[np.bool_]
    beside: NDArray[np.bool_]
    """(2, stations): the near band touches another object of the filter, per side."""
    tilt: float = 0.0
    """The strip's slope across (rise per metre toward the right side), over the object."""
    ground: float = 0.0
    """The ground's slope across past both sides (near and far bands, one plane through
    both sides' samples over the object), rise per metre toward the right side."""


def _axis(g: Polygon | MultiPolygon) -> tuple[NDArray, NDArray, float, float]:
    """Middle, unit vector along, length and width of the minimum rotated rectangle."""
    xy = np.asarray(g.minimum_rotated_rectangle.exterior.coords)[:4]
    a, b = xy[1] - xy[0], xy[2] - xy[1]
    if np.hypot(*a) < np.hypot(*b):
        a, b = b, a
    length = float(np.hypot(*a))
    return xy.mean(axis=0), a / max(length, 1e-9), length, float(np.hypot(*b))


def sides(
    g: Polygon | MultiPolygon,
    read: Reader,
    tile: float,
    step: float,
    others: list[Polygon | MultiPolygon] | None = None,
) -> Sides | None:
    """The edges of object ``g`` (see the module); None where fewer than three samples
    lie inside it at every station."""
    mid, u, length, width = _axis(g)
    n = np.array([-u[1], u[0]])
    reach = width / 2 + 5 * tile
    x0, y0, x1, y1 = g.bounds
    dtm, transform = read((x0 - 5 * tile, y0 - 5 * tile, x1 + 5 * tile, y1 + 5 * tile))
    offs = np.arange(-reach, reach + 1e-9, tile / 4)
    along = np.arange(-length / 2 + tile / 2, length / 2 - tile / 2 + 1e-9, tile)
    p = mid + along[:, None, None] * u + offs[None, :, None] * n
    col, row = ~transform @ (p[..., 0].ravel(), p[..., 1].ravel())
    z = ndimage.map_coordinates(
        dtm, [np.asarray(row) - 0.5, np.asarray(col) - 0.5], order=1, cval=np.nan
    ).reshape(p.shape[:2])
    inside = shapely.contains_xy(g, p[..., 0], p[..., 1]) & np.isfinite(z)
    ok = inside.sum(axis=1) >= 3
    if not ok.any():
        return None
    z, inside, p = z[ok], inside[ok], p[ok]
    t = np.broadcast_to(offs, z.shape)
    level = np.array([np.median(zr[m]) for zr, m in zip(z, inside, strict=True)])
    centre = np.array([tr[m].mean() for tr, m in zip(t, inside, strict=True)])
    dt, dz = (t - centre[:, None])[inside], (z - level[:, None])[inside]
    keep = np.ones(dt.size, dtype=bool)
    tilt = 0.0
    for _ in range(3):  # trimmed: the shoulders the strip takes in are a minority
        tilt, b = np.polyfit(dt[keep], dz[keep], 1)
        res = np.abs(dz - (b + tilt * dt))
        keep = res <= np.quantile(res, 0.75)
    flat = z - tilt * t
    top = np.array([np.median(fr[m]) for fr, m in zip(flat, inside, strict=True)])
    lo = np.array([tr[m].min() for tr, m in zip(t, inside, strict=True)])
    hi = np.array([tr[m].max() for tr, m in zip(t, inside, strict=True)])
    out = []
    beside = np.zeros((2, len(top)), dtype=bool)
    ground = _ground_slope(z, t, lo, hi, tile)
    for k, (sign, edge) in enumerate(((-1, lo), (1, hi))):
        past = sign * (t - edge[:, None])  # metres past the strip's edge, this side
        near = (past >= tile) & (past <= 3 * tile)
        far = (past > 3 * tile) & (past <= 5 * tile)
        hn = _band_median(flat, near) - top
        hf = _band_median(flat, far) - top
        # the highest ground up to the near band's end (its 90th percentile: noise
        # apart): a cut's wall top, however narrow, not a ditch dug past it
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            crest = np.nanpercentile(
                np.where((past > 0) & (past <= 3 * tile), flat, np.nan), 90, axis=1
            )
        out.append((hn, (hn > step) & (hf - (crest - top) > step)))
        if others:
            hit = np.zeros(near.shape, dtype=bool)
            for o in others:
                hit |= shapely.contains_xy(o, p[..., 0], p[..., 1])
            beside[k] = (hit & near).any(axis=1)
    (left, rl), (right, rr) = out
    return Sides(left, right, rl, rr, beside, float(tilt), ground)


def _ground_slope(
    z: NDArray[np.float64],
    t: NDArray[np.float64],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    tile: float,
) -> float:
    """The ground's slope across past both sides of the strip (every sample from one
    tile past its edges out to the far band's end), one slope for the object with a
    height of its own at every station (the slope along the object left out); 0 where
    no station has ground on both sides."""
    band = ((t <= lo[:, None] - tile) | (t >= hi[:, None] + tile)) & np.isfinite(z)
    left = np.any(band & (t < lo[:, None]), axis=1)
    right = np.any(band & (t > hi[:, None]), axis=1)
    band = band & (left & right)[:, None]
    if not band.any():
        return 0.0
    tc = np.where(band, t, np.nan)
    zc = np.where(band, z, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # stations without ground
        dt = tc - np.nanmean(tc, axis=1)[:, None]
        dz = zc - np.nanmean(zc, axis=1)[:, None]
    return float(np.sum(dt[band] * dz[band]) / max(np.sum(dt[band] ** 2), 1e-12))


def _band_median(z: NDArray[np.float64], band: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Median of ``z`` over ``band`` per station (NaN where the band has no data)."""
    v = np.where(band, z, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN band: NaN
        return np.nanmedian(v, axis=1)


def unbounded(s: Sides, step: float, tilt: float | None = None) -> str | None:
    """Why an object with these sides is not a road: ``"trough"`` (the ground rises on
    past both sides at more than half the stations), ``"verge"`` (an edge on one side
    at more than half the stations, at most half on the other, and another object of
    the filter beside the edged side at more than half), ``"slope"`` (with ``tilt``: the
    strip falls across by more than ``tilt`` m/m toward the side the ground past both
    sides falls to, and that ground falls more steeply: a band of a slope, not a level
    road cut into or built onto it), else None."""
    if np.mean(s.rise_left & s.rise_right) > 0.5:
        return "trough"
    if tilt is not None and s.tilt * s.ground > 0 and tilt < abs(s.tilt) < abs(s.ground):
        return "slope"
    edged = [
        float(np.mean(np.abs(s.left) > step)) > 0.5,
        float(np.mean(np.abs(s.right) > step)) > 0.5,
    ]
    for k in (0, 1):
        if edged[k] and not edged[1 - k] and float(np.mean(s.beside[k])) > 0.5:
            return "verge"
    return None
