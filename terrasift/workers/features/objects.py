"""Objects out: labelled tiles → shapely polygons with length and width in metres.

An object's polygon is the union of its tiles (holes it encloses filled, since
e.g. a hill is found by its outline), simplified by half a tile. Length and
width are those of the rectangle with the polygon's area and perimeter
(L + W = P/2, L·W = A; a compact shape whose perimeter is too short for any
rectangle is taken as a square). This keeps the seed's idea (width across,
length = area / width) but does not depend on the object's angle to the rows:
the seed's mean row-segment width overstates the width of a diagonal object by
1/cos of its angle and so understates its length by as much (§5.3.2 notes the
width is inexact).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from rasterio import Affine
from rasterio.features import shapes
from scipy import ndimage
from shapely.geometry import MultiPolygon, Polygon, shape
from shapely.ops import unary_union


@dataclass(frozen=True)
class Feature:
    """One terrain object."""

    kind: str
    geometry: Polygon | MultiPolygon
    length_m: float
    width_m: float
    tiles: int


def fill_object_holes(labels: NDArray[np.int32]) -> NDArray[np.int32]:
    """Label image with every enclosed hole given to an object bordering it."""
    mask = labels > 0
    holes = ndimage.binary_fill_holes(mask) & ~mask
    if not holes.any():
        return labels
    hole_lab, n = ndimage.label(holes)
    around = ndimage.grey_dilation(labels, footprint=ndimage.generate_binary_structure(2, 1))
    owner = ndimage.maximum(around, hole_lab, index=np.arange(1, n + 1)).astype(np.int32)
    out = labels.copy()
    out[holes] = owner[hole_lab[holes] - 1]
    return out


def rectangle_size(poly: Polygon | MultiPolygon) -> tuple[float, float]:
    """(length, width) of the rectangle with the area and outer perimeter of ``poly``."""
    parts = poly.geoms if isinstance(poly, MultiPolygon) else [poly]
    area = sum(Polygon(p.exterior).area for p in parts)
    perim = sum(p.exterior.length for p in parts)
    disc = perim * perim / 4 - 4 * area
    width = (perim / 2 - np.sqrt(disc)) / 2 if disc > 0 else np.sqrt(area)
    width = max(width, 1e-9)
    return area / width, width


def polygons(labels: NDArray[np.int32], transform: Affine, simplify: float) -> dict[int, Polygon | MultiPolygon]:
    """Polygon per label (union of its tiles), corners merged, simplified by ``simplify`` metres."""
    pieces: dict[int, list] = {}
    for geom, value in shapes(labels, mask=labels > 0, transform=transform, connectivity=8):
        pieces.setdefault(int(value), []).append(shape(geom))
    eps = abs(transform.a) * 1e-3
    out = {}
    for lab, parts in pieces.items():
        g = unary_union(parts)
        if isinstance(g, MultiPolygon):  # tiles touching only at corners
            g = g.buffer(eps, join_style="mitre").buffer(-eps, join_style="mitre")
        if simplify > 0:
            g = g.simplify(simplify, preserve_topology=True)
        out[lab] = g
    return out


def objects_from_labels(
    labels: NDArray[np.int32],
    kind: str,
    transform: Affine,
    tile_size: float,
    limits: tuple[float | None, float | None, float | None, float | None] = (None, None, None, None),
    simplify_tiles: float = 0.5,
) -> list[Feature]:
    """Features for every label whose length/width (in tiles) lie within ``limits``."""
    labels = fill_object_holes(labels.astype(np.int32))
    if labels.max() == 0:
        return []
    counts = np.bincount(labels.ravel())
    min_l, max_l, min_w, max_w = limits
    feats = []
    for lab, poly in polygons(labels, transform, simplify_tiles * tile_size).items():
        length, width = rectangle_size(poly)
        lt, wt = length / tile_size, width / tile_size
        if (min_l is not None and lt < min_l) or (max_l is not None and lt > max_l):
            continue
        if (min_w is not None and wt < min_w) or (max_w is not None and wt > max_w):
            continue
        feats.append(Feature(kind, poly, float(length), float(width), int(counts[lab])))
    return feats


def rectangle_features(rects: list[tuple[int, int, int, int]], kind: str, transform: Affine, tile_size: float) -> list[Feature]:
    """Features for rectangles (row0, col0, rows, cols) on the tile grid."""
    feats = []
    for r, c, h, w in rects:
        x0, y0 = transform * (c, r)
        x1, y1 = transform * (c + w, r + h)
        poly = Polygon([(x0, y0), (x1, y0), (x1, y1), (x0, y1)])
        feats.append(Feature(kind, poly, max(h, w) * tile_size, min(h, w) * tile_size, h * w))
    return feats
