"""Stage 2: connect marked tiles into objects (Sjövall §2.2–2.3).

All three algorithms are written as graphs over tiles solved by connected
components, which gives the same objects as the seed's recursive searches
without their recursion-depth limit:

- ``simple``: 4-neighbours that are both marked;
- ``segment``: horizontal segments joined to overlapping segments in the rows
  below (vertical segments to the columns to the right), bridging up to
  ``gap`` missing rows/columns;
- ``edge``: neighbours (and tiles two steps away, bridging one missing
  cross-section) joined when the step follows either tile's edge (or the
  line 90° from its inclination) within 45° and the two tiles' edges agree
  within ±45°, plus tiles of one segment.

``h_and_v`` and ``find_rectangles`` are the seed's logical AND and rectangle
search; ``rectangle_cover`` keeps every window that passes instead of the first
fit, so overlapping windows of one flat area make one object.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from terrasift.workers.categories import _POINTS, NODATA, Categories

_QUARTER = np.pi / 4
# neighbour offsets (drow, dcol) and the direction angle of the step (north-up grid)
_STEPS = ((0, 1, 0.0), (-1, 1, _QUARTER), (-1, 0, 2 * _QUARTER), (-1, -1, 3 * _QUARTER))


def _components(
    shape: tuple[int, int], a: NDArray[np.int64], b: NDArray[np.int64], nodes: NDArray[np.bool_]
) -> NDArray[np.int32]:
    """Label image of the components of the graph with edges a–b over ``nodes`` (0 = not a node)."""
    n = shape[0] * shape[1]
    graph = coo_matrix((np.ones(a.size, dtype=np.int8), (a, b)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    flat = nodes.ravel()
    # renumber the components that hold nodes as 1..k
    _, labels = np.unique(comp[flat], return_inverse=True)
    out = np.zeros(n, dtype=np.int32)
    out[flat] = labels + 1
    return out.reshape(shape)


def _pairs(
    mask_a: NDArray[np.bool_], mask_b: NDArray[np.bool_], dr: int, dc: int
) -> tuple[NDArray, NDArray]:
    """Flat index pairs (t, t + (dr, dc)) where mask_a at t and mask_b at the neighbour."""
    rows, cols = mask_a.shape
    r0, r1 = max(0, -dr), rows - max(0, dr)
    c0, c1 = max(0, -dc), cols - max(0, dc)
    both = mask_a[r0:r1, c0:c1] & mask_b[r0 + dr : r1 + dr, c0 + dc : c1 + dc]
    r, c = np.nonzero(both)
    r, c = r + r0, c + c0
    return r * cols + c, (r + dr) * cols + (c + dc)


def simple(marks: NDArray[np.bool_]) -> NDArray[np.int32]:
    """Objects of 4-connected marked tiles."""
    labels, _ = ndimage.label(marks)
    return labels.astype(np.int32)


def segments(h: NDArray[np.bool_], v: NDArray[np.bool_], gap: int) -> NDArray[np.int32]:
    """Horizontal segments stacked down the rows and vertical ones along the columns, bridging ``gap`` missing lines."""
    edges_a, edges_b = [], []
    for mask, along in ((h, (0, 1)), (v, (1, 0))):
        a, b = _pairs(mask, mask, *along)  # tiles of one segment
        edges_a.append(a)
        edges_b.append(b)
        across = (1, 0) if along == (0, 1) else (0, 1)
        for d in range(1, gap + 2):
            a, b = _pairs(mask, mask, across[0] * d, across[1] * d)
            edges_a.append(a)
            edges_b.append(b)
    return _components(h.shape, np.concatenate(edges_a), np.concatenate(edges_b), h | v)


def _axis(cats: Categories) -> NDArray[np.float64]:
    """Undirected line (angle mod π) each tile's edge or inclination runs along; NaN where none.
    A flat tile that is not level (``Categories.rise``) runs along the contour of its plane:
    the bank of a ditch too shallow for its tiles to be past the flatness threshold."""
    ang = np.full(cats.shape, np.nan)
    inc = cats.inclination
    if cats.rise is not None:
        inc = np.where(inc == 0, cats.rise, inc)
    has_inc = (inc > 0) & (inc != NODATA)
    ang[has_inc] = ((inc[has_inc].astype(float) - 1) * _QUARTER + np.pi / 2) % np.pi
    lut = np.full(256, np.nan)
    for code in range(12, 89):
        a, b = divmod(code, 10)
        if a in _POINTS and b in _POINTS and a != b:
            (xa, ya), (xb, yb) = _POINTS[a], _POINTS[b]
            lut[code] = np.arctan2(yb - ya, xb - xa) % np.pi
    edge = lut[cats.orientation]
    return np.where(np.isnan(edge), ang, edge)


def _angle_diff(a: NDArray, b: NDArray | float) -> NDArray:
    d = np.abs(a - b) % np.pi
    return np.minimum(d, np.pi - d)


def edges(
    cats: Categories,
    h: NDArray[np.bool_],
    v: NDArray[np.bool_],
    marks: NDArray[np.bool_],
    reach: int = 2,
) -> NDArray[np.int32]:
    """The seed's edge-connect: follow edges and inclinations through marked tiles.

    With ``reach`` 2 a step along the edge may also jump one tile, so a single
    missing cross-section does not cut an object in two (the seed's version
    stops there; its segment-connect has the same kind of tolerance).
    """
    axis = _axis(cats)
    rows, cols = marks.shape
    edges_a, edges_b = [], []
    eps = 1e-6
    steps = [(dr * k, dc * k, phi) for k in range(1, reach + 1) for dr, dc, phi in _STEPS]
    for dr, dc, phi in steps:
        a, b = _pairs(marks, marks, dr, dc)
        if a.size:
            ta, tb = axis.ravel()[a], axis.ravel()[b]
            step = (_angle_diff(ta, phi) < _QUARTER - eps) | (_angle_diff(tb, phi) < _QUARTER - eps)
            agree = _angle_diff(ta, tb) <= _QUARTER + eps
            ok = (
                step & agree
            )  # NaN compares False: tiles without an axis only join via their segment
            edges_a.append(a[ok])
            edges_b.append(b[ok])
    for mask, (dr, dc) in ((h & marks, (0, 1)), (v & marks, (1, 0))):
        a, b = _pairs(mask, mask, dr, dc)
        edges_a.append(a)
        edges_b.append(b)
    return _components(marks.shape, np.concatenate(edges_a), np.concatenate(edges_b), marks)


def h_and_v(
    h: NDArray[np.bool_], v: NDArray[np.bool_], share: float | None = None
) -> NDArray[np.bool_]:
    """Tiles that are part of both a horizontal and a vertical segment; with ``share``,
    only groups of them (4-connected) that make at least that share of the tiles
    marked either way that they connect to."""
    both = h & v
    if share is None or not both.any():
        return both
    lab, n = ndimage.label(both)
    around, _ = ndimage.label(h | v)
    # each group of both-way tiles lies in exactly one either-way group
    first = ndimage.minimum(around, lab, index=np.arange(1, n + 1)).astype(np.int64)
    either = np.bincount(around.ravel())[first]
    count = np.bincount(lab.ravel(), minlength=n + 1)[1:]
    keep = np.concatenate([[False], count >= share * either])
    return keep[lab]


def find_rectangles(
    marks: NDArray[np.bool_], width: int, height: int, error: float
) -> list[tuple[int, int, int, int]]:
    """Rectangles (row0, col0, rows, cols) of ``height`` × ``width`` tiles with at most ``error`` % unmarked.

    Scanned left to right, top to bottom; the first fit is taken and its area is
    excluded from later rectangles, as in the seed.
    """
    rows, cols = marks.shape
    if rows < height or cols < width:
        return []
    sat = np.zeros((rows + 1, cols + 1), dtype=np.int64)
    sat[1:, 1:] = marks.astype(np.int64).cumsum(0).cumsum(1)
    count = (
        sat[height:, width:]
        - sat[:-height, width:]
        - sat[height:, :-width]
        + sat[:-height, :-width]
    )
    need = int(np.ceil(width * height * (1 - error / 100.0) - 1e-9))
    ok = count >= need
    found = []
    free = np.ones_like(ok)
    for flat in np.flatnonzero(ok):
        r, c = divmod(int(flat), ok.shape[1])
        if not free[r, c]:
            continue
        found.append((r, c, height, width))
        free[max(0, r - height + 1) : r + height, max(0, c - width + 1) : c + width] = False
    return found


def rectangle_cover(
    marks: NDArray[np.bool_], width: int, height: int, error: float
) -> NDArray[np.bool_]:
    """Tiles inside any ``height`` × ``width`` window with at most ``error`` % unmarked.

    The union of all passing windows: an area larger than the window comes out
    whole (its connected components are the objects), not as the first-fit
    squares the seed's search leaves, which cut a 150 m field into one 100 m
    square and leftovers.
    """
    rows, cols = marks.shape
    if rows < height or cols < width:
        return np.zeros_like(marks, dtype=bool)
    sat = np.zeros((rows + 1, cols + 1), dtype=np.int64)
    sat[1:, 1:] = marks.astype(np.int64).cumsum(0).cumsum(1)
    count = (
        sat[height:, width:]
        - sat[:-height, width:]
        - sat[height:, :-width]
        + sat[:-height, :-width]
    )
    need = int(np.ceil(width * height * (1 - error / 100.0) - 1e-9))
    ok = (count >= need).astype(np.int64)  # window with its top-left tile at (r, c)
    # tile (r, c) is covered when a passing window starts in [r-h+1, r] x [c-w+1, c]
    s2 = np.zeros((ok.shape[0] + 1, ok.shape[1] + 1), dtype=np.int64)
    s2[1:, 1:] = ok.cumsum(0).cumsum(1)
    r = np.arange(rows)
    c = np.arange(cols)
    r1 = np.minimum(r, ok.shape[0] - 1) + 1
    r0 = np.maximum(r - height + 1, 0)
    c1 = np.minimum(c, ok.shape[1] - 1) + 1
    c0 = np.maximum(c - width + 1, 0)
    hits = (
        s2[r1[:, None], c1[None, :]]
        - s2[r0[:, None], c1[None, :]]
        - s2[r1[:, None], c0[None, :]]
        + s2[r0[:, None], c0[None, :]]
    )
    valid = (r0[:, None] < r1[:, None]) & (c0[None, :] < c1[None, :])
    return (hits > 0) & valid
