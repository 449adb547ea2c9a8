"""Buildings (ASPRS 6) and noise (ASPRS 7) among the non-ground points; input classes kept.

Noise: a non-ground point more than ``low_depth`` below the ground surface is
a low outlier (multipath); a point with fewer than ``noise_min`` other points
within ``noise_radius`` (3-D) is an isolated outlier (a bird, a dust return).
The radius follows the data: four point spacings at the job's density, at
least 5 m (at 2 m, 1.3 % of the lidR MixedConifer canopy returns were alone),
so a sparse survey's tree top is not taken for a bird.

Buildings: roofs are planar and large, crowns are rough and small.
For every non-ground point at least ``min_height`` above ground, a plane is
fitted to its ``neighbours`` nearest points (3-D): the point is planar when
the RMS across that plane is at most ``plane_tol`` and the neighbourhood is
spread in two directions (not a wire). Planar points whose planes agree
(normals within ``normal_tol``, each on the other's plane) are joined into
segments; a segment is a roof when it covers ``min_area`` or more (points over
the job's density) and slopes at most ``max_pitch``. Where the data has echo
information, only single and last returns can be roofs: a return with later
returns behind it went through a crown, and a roof under a crown is seen as
a plane of last returns once the crown's first returns are set aside. Roofs then grow into the points they missed (at an edge, beside a
crown, under a tree: a last return on the roof) when a point lies within
``assign_tol`` of the plane of the nearest roof point, and walls are the
points below a roof's edge within a point spacing of it. A crown over a roof
stands above its plane and stays vegetation.

Kept classes: points whose input class is in ``keep`` (water, 9, by default)
keep it in the output; they still take part in every stage (a lake's surface
stays in the DTM).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, field_validator
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from terrasift.workers.registry import StageParams, register

BUILDING, NOISE = 6, 7


class ObjectParams(StageParams):
    """Parameters of building and noise labelling, and of the kept input classes."""

    keep: list[int] = Field(default_factory=lambda: [9])
    """Input classes kept as they are (ASPRS codes; 9 water by default, e.g. 9,17 adds bridge decks)."""
    min_height: float = Field(2.0, ge=0.0, le=100.0)
    """Metres above ground from which a point can be a roof."""
    neighbours: int = Field(10, ge=4, le=100)
    """Points (with itself) in each point's local plane fit."""
    plane_tol: float = Field(0.15, gt=0.0, le=5.0)
    """Metres: RMS across the local plane up to which a point is planar
    (roofs in the town family: 1–5 cm of noise; ISPRS y is quantised to 0.5 m)."""
    normal_tol: float = Field(15.0, gt=0.0, le=90.0)
    """Degrees between the normals of two neighbouring points of one segment."""
    max_pitch: float = Field(60.0, gt=0.0, le=90.0)
    """Degrees: steeper planar segments are not roofs."""
    min_area: float = Field(10.0, gt=0.0, le=10_000.0)
    """Square metres a segment must cover to be a roof (half of the gable of a 5 m × 5 m house)."""
    assign_tol: float = Field(0.3, gt=0.0, le=5.0)
    """Metres from the plane of the nearest roof point within which a point joins the roof."""
    low_depth: float = Field(1.0, gt=0.0, le=100.0)
    """Metres below the ground surface from which a non-ground point is a low outlier."""
    noise_radius: float | None = Field(None, gt=0.0, le=100.0)
    """Metres (3-D) of the isolation test; None: four point spacings at the job's density, ≥ 5 m."""
    noise_min: int = Field(2, ge=0, le=100)
    """Fewer other points than this within ``noise_radius`` make a point isolated (0: off)."""
    buildings: bool = True
    """Label buildings (off: roofs stay with the vegetation classes, as before)."""

    @field_validator("keep", mode="before")
    @classmethod
    def _split(cls, v: object) -> object:
        if isinstance(v, str):
            v = v.strip()
            if v.lower() in ("", "none"):
                return []
            return [int(p) for p in v.replace(" ", "").split(",") if p]
        if isinstance(v, int):
            return [v]
        return v

    @field_validator("keep")
    @classmethod
    def _codes(cls, v: list[int]) -> list[int]:
        bad = [c for c in v if not 0 <= c <= 255]
        if bad:
            raise ValueError(f"classes must be 0-255, not {bad}")
        return sorted(set(v))


@dataclass(frozen=True)
class ObjectLabels:
    """Masks over the points given: ``building`` (6) and ``noise`` (7), disjoint."""

    building: NDArray[np.bool_]
    noise: NDArray[np.bool_]
    segments: int


def spacing(density: float) -> float:
    """Mean point spacing (m) at ``density`` points per m²."""
    return float(1.0 / np.sqrt(max(density, 1e-6)))


@register("objects", ObjectParams, "buildings (6) and isolated or low outliers (7); kept classes")
def label_objects(
    xyz: NDArray[np.float64],
    is_ground: NDArray[np.bool_],
    height: NDArray[np.float64],
    params: ObjectParams,
    density: float,
    return_number: NDArray | None = None,
    number_of_returns: NDArray | None = None,
) -> ObjectLabels:
    """Building and noise masks for the points ``xyz``.

    ``height`` is each point's height above the ground surface (NaN where
    unknown), ``density`` the job's points per m² (it sets the noise radius,
    the roof reach and the area of a segment). Returns are optional: without
    them (or with every pulse a single return) the echo test is skipped.
    """
    xyz = np.asarray(xyz, np.float64)
    n = xyz.shape[0]
    is_ground = np.asarray(is_ground, bool)
    h = np.asarray(height, np.float64)
    noise = np.zeros(n, bool)
    building = np.zeros(n, bool)
    if n == 0:
        return ObjectLabels(building, noise, 0)
    s = spacing(density)

    # Noise: low outliers, then isolated points of any height.
    with np.errstate(invalid="ignore"):
        noise |= ~is_ground & (h < -params.low_depth)
    if params.noise_min > 0 and n > params.noise_min:
        radius = params.noise_radius or max(5.0, 4.0 * s)
        cand = np.flatnonzero(~is_ground & ~noise)
        if cand.size:
            d, _ = cKDTree(xyz).query(
                xyz[cand], k=params.noise_min + 1, distance_upper_bound=radius
            )
            d = d.reshape(cand.size, -1)
            noise[cand[~np.isfinite(d[:, -1])]] = True

    if not params.buildings:
        return ObjectLabels(building, noise, 0)
    layered = None
    if return_number is not None and number_of_returns is not None:
        rn = np.asarray(return_number, np.int64)
        nr = np.asarray(number_of_returns, np.int64)
        if nr.max(initial=0) > 1:
            layered = rn < nr

    # A return with later returns behind it went through something: a crown,
    # not a roof. Roofs are sought among the single and last returns only, so a
    # roof under a crown (its last returns) is a plane of its own.
    with np.errstate(invalid="ignore"):
        seeds = ~is_ground & ~noise & (h >= params.min_height)
    if layered is not None:
        seeds &= ~layered
    cand = np.flatnonzero(seeds)
    k = params.neighbours
    if cand.size <= k:
        return ObjectLabels(building, noise, 0)
    pts = xyz[cand] - xyz[cand].mean(axis=0)
    _, nb = cKDTree(pts).query(pts, k=k)
    normal, rms, spread = _local_planes(pts, nb)
    cos_pitch = np.cos(np.radians(params.max_pitch))
    planar = (rms <= params.plane_tol) & (spread >= 3.0 * rms) & (np.abs(normal[:, 2]) >= cos_pitch)

    # Segments: planar neighbours on each other's planes with agreeing normals.
    i = np.repeat(np.arange(cand.size), k - 1)
    j = nb[:, 1:].ravel()
    ok = planar[i] & planar[j]
    i, j = i[ok], j[ok]
    cos_n = np.abs(np.einsum("ij,ij->i", normal[i], normal[j]))
    off_i = np.abs(np.einsum("ij,ij->i", pts[j] - pts[i], normal[i]))
    off_j = np.abs(np.einsum("ij,ij->i", pts[i] - pts[j], normal[j]))
    tol = 2.0 * params.plane_tol
    join = (cos_n >= np.cos(np.radians(params.normal_tol))) & (off_i <= tol) & (off_j <= tol)
    graph = coo_matrix(
        (np.ones(int(join.sum()), np.int8), (i[join], j[join])), shape=(cand.size, cand.size)
    )
    _, seg = connected_components(graph, directed=False)
    seg = np.where(planar, seg, -1)
    valid = seg >= 0
    if not valid.any():
        return ObjectLabels(building, noise, 0)
    sizes = np.bincount(seg[valid], minlength=int(seg.max(initial=-1)) + 1)
    roof_seg = sizes / max(density, 1e-6) >= params.min_area
    roof = valid & roof_seg[np.maximum(seg, 0)]
    n_segments = int(np.count_nonzero(roof_seg))
    if not roof.any():
        return ObjectLabels(building, noise, 0)

    # Grow each roof into the candidates it missed, a point spacing at a time.
    reach = max(1.0, 2.0 * s)
    for _ in range(3):
        rest = np.flatnonzero(~roof)
        if rest.size == 0:
            break
        src = np.flatnonzero(roof)
        d, near = cKDTree(pts[src, :2]).query(pts[rest, :2], distance_upper_bound=reach)
        hit = np.isfinite(d)
        q = src[near[hit]]
        r = rest[hit]
        off = np.abs(np.einsum("ij,ij->i", pts[r] - pts[q], normal[q]))
        on = off <= params.assign_tol
        if not on.any():
            break
        roof[r[on]] = True
        normal[r[on]] = normal[q[on]]
    building[cand[roof]] = True

    # Walls: single or last returns below a roof, within a point spacing of its points.
    with np.errstate(invalid="ignore"):
        low = np.flatnonzero(~is_ground & ~noise & ~building & (h >= 0.3))
    if low.size:
        bpts = np.flatnonzero(building)
        d, near = cKDTree(xyz[bpts, :2]).query(xyz[low, :2], distance_upper_bound=max(0.5, s))
        hit = np.isfinite(d)
        w = low[hit]
        below = xyz[w, 2] < xyz[bpts[near[hit]], 2] - params.assign_tol
        if layered is not None:
            below &= ~layered[w]
        building[w[below]] = True
    return ObjectLabels(building, noise & ~building, n_segments)


def _local_planes(
    pts: NDArray[np.float64], nb: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Unit normal, RMS across the plane and RMS along its second axis of each
    point's neighbourhood (rows of ``nb`` index ``pts``)."""
    q = pts[nb]
    q = q - q.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", q, q) / nb.shape[1]
    w, v = np.linalg.eigh(cov)
    normal = v[:, :, 0]
    normal = normal * np.where(normal[:, 2:3] < 0, -1.0, 1.0)
    return normal, np.sqrt(np.maximum(w[:, 0], 0)), np.sqrt(np.maximum(w[:, 1], 0))
