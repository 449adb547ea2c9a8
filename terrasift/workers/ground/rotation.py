"""Steep blocks and rotated classification (DESIGN §5.3, after Pack, Blonquist & Carter).

A 2.5-D ground filter fails on cliffs: seen from above a vertical face looks
like the side of a tree, and an overhang hides ground under ground. The block
is tested cheaply for steep terrain (lowest point per coarse cell, TIN, share
of facets steeper than ``facet_angle``). A steep block is classified once as it
is and once per compass direction with the cloud tipped by ``angle`` about its
centroid, each run with the ground method's conservative parameters; a point is
ground if any run says so. A 30° tip turns a 90° face into 60° and a 100°
overhang into 70°, which a TIN filter can follow. Those are the seed's
settings; a ground method may have its own (``RotationParams.presets``:
ground.nist tips by 30° and again by 45° and keeps the block's default labels).

Direction k (k = 0 … ``directions``−1, compass azimuth 360·k/``directions``,
0 = north, 90 = east) tips the cloud so that faces looking toward that azimuth
turn toward the sky. Rotated clouds live one at a time and are dropped after
their run: memory is one extra copy of the block.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.spatial import Delaunay, QhullError

from terrasift.workers.bins import Grid, lowest_per_bin
from terrasift.workers.registry import Stage, StageParams, register

GroundFn = Callable[[NDArray[np.float64]], NDArray[np.bool_]]
SeededFn = Callable[[NDArray[np.float64], NDArray[np.bool_]], NDArray[np.bool_]]


class SteepParams(StageParams):
    """Parameters of the per-block steepness test (seed step 2)."""

    cell: float = Field(7.5, ge=1.0, le=1000.0)
    """Metres: cell of the lowest-point TIN. A face shows as a facet steeper than
    ``facet_angle`` only when it rises more than cell × tan(facet_angle): 13 m at
    7.5 m cells, 26 m at the seed's 15 m, which misses lower cliff bands."""
    facet_angle: float = Field(60.0, gt=0.0, lt=90.0)
    """Degrees: a facet steeper than this counts as steep."""
    steep_share: float = Field(0.01, ge=0.0, le=1.0)
    """A block is steep when more than this share of its facets are steep."""
    min_rise: float = Field(2.0, ge=0.0, le=100.0)
    """Metres: a steep facet must also rise this much, so a low outlier or a kerb
    next to a cell border (two lowest points a metre apart) is not a cliff."""
    support: int = Field(2, ge=0, le=100)
    """A steep facet counts only if its lowest vertex has this many other points
    of the tested cloud within ``support_radius`` (x, y) and ``support_gap`` (z).
    A cliff's foot is a floor of many points at one height; a lone low outlier
    (multipath) that the ground filter took is no terrain, and its cell is
    dropped from the TIN. 0: no check (the seed's plain test)."""
    thin_facet: float = Field(0.1, ge=0.0, le=1.0)
    """Cells: a facet whose plan height onto its longest side is below this
    (nearly collinear lowest points along cell borders or the data's edge) is
    judged by its steepest side, not its normal, which tilts with any small
    height difference across it. 0: every facet by its normal."""
    support_radius: float = Field(2.0, gt=0.0, le=100.0)
    """Metres: horizontal radius of the support check."""
    support_gap: float = Field(1.0, gt=0.0, le=100.0)
    """Metres: height band above the vertex that counts as the same surface."""


class RotationParams(StageParams):
    """Parameters of rotated classification (seed steps 3–5)."""

    angle: float = Field(30.0, gt=0.0, le=80.0)
    """Degrees each rotated cloud is tipped by."""
    directions: int = Field(8, ge=1, le=64)
    """Number of compass directions, evenly spaced from north."""
    second_angle: float | None = Field(None, gt=0.0, le=80.0)
    """Degrees: every direction is also run tipped by this much (after all runs
    tipped by ``angle``). One tip trades faces against the ground beside them for
    a method that follows slopes only up to a cap: it must be large for the
    faces to come under the cap, small for their rims and feet not to go over
    it. None: one tip, as the seed."""
    edge_margin: float | None = Field(None, ge=0.0, le=1000.0)
    """Metres: a rotated run's labels count only this far inside the rotated
    block's footprint. None (default): per point instead. Tipping moves a point
    sideways by its own height above the local ground × sin(angle), so near
    the data's edge tree tops and birds come to stand beyond the ground and
    become TIN seeds; a rotated label counts only where the point, so moved,
    still lies over the footprint of the tipped ground (``_over_ground``).
    Rock faces at the data's edge sit on the ground surface, move by little
    and keep their labels. The unrotated run still labels every point."""
    max_lift: float | None = Field(None, gt=0.0, le=1000.0)
    """Metres: a rotated run may add only points within this height of the
    unrotated ground surface (a TIN of its lowest ground per 2 m cell), as
    tipping isolates birds, which then seed a rotated TIN. None (default): no
    such band; the face evidence (``face_*``) rejects what stands off a
    smooth surface linked to the ground, birds among it. A band of 30 m cut
    the upper half of a 40 m face over a cave (its lowest ground is the
    cave's floor, 6 m under the lip, and the filter had lost the rim above):
    the steep family's cave tiles."""
    steep_reach: float | None = Field(None, gt=0.0, le=1000.0)
    """Metres: a rotated run may add only points this close (horizontally) to a
    steep facet (> 50°) of the unrotated ground surface. None (default): no
    such cap; what a run adds is judged by the face itself (``face_*``). A cap
    of 4 m missed overhang fronts whose lowest surface steps up at the back of
    a cave, well behind the face."""
    context: float | None = Field(20.0, ge=0.0, le=1000.0)
    """Metres: a rotated run sees only the points within this (+ ``steep_reach``
    when set) of the steep facets of the unrotated ground: the faces with their
    foot, rim and an overhang's depth, not the flats far from any face. This
    keeps a steep block's cost near a flat one's. None: whole block. It must
    exceed an overhang's depth: over a 10 m lip the ground labels' steep facets
    lie at the back wall, and 10 m missed a third of the front faces that 20 m
    found (the steep family's overhang tiles)."""
    aspect_window: float | None = Field(45.0, gt=0.0, le=180.0)
    """Degrees: with ``context``, the run tipped toward azimuth θ sees only the
    points near steep facets that look within this of θ (a face looking
    toward θ is the one that tip flattens; at 45° a face lies in the window of
    its one or two nearest directions of eight). A cliff band facing one way
    then costs one or two runs per tip instead of eight; a direction no face
    looks toward is not run. None: every run sees every steep facet's points."""
    aspect_rise: float = Field(2.0, ge=0.0, le=100.0)
    """Metres: with ``aspect_window``, only steep facets rising this much choose
    which points a run sees (the steepness test's ``min_rise``): the lowest
    ground steps by a few decimetres at bushes and trunks in every direction."""
    anchor_all: float | None = Field(10.0, gt=0.0, le=1000.0)
    """Metres. With ``context``: the views are also anchored on the steep facets
    of the surface through the lowest of all points per 2 m cell whose highest
    vertex stands this far (3-D) from every ground label, not only on those of
    the ground labels. A filter that lost a plateau (a raised body cut by the
    data's edge) leaves no step at the face below it in its ground labels, so
    no run saw that face; the lowest of all points still steps there. The
    distance keeps out crowns over kept ground, which would put most of a
    sparse block in every view. None: ground labels only."""
    face_evidence: bool = True
    """Keep only the added points that lie on a surface (see ``face_rough``),
    connected to the unrotated ground through such points (``face_link``)."""
    face_neighbours: int = Field(12, ge=4, le=64)
    """An added point's plane is fitted to this many nearest points (3-D) that
    some run called ground: the face with its foot and rim, not the crowns and
    bushes in front of it (no run takes them), which made a face 1–2 m from a
    tree look like vegetation."""
    face_trim: float = Field(0.6, gt=0.0, le=1.0)
    """Share of those neighbours the plane is refitted to (the closest to it,
    three times): where a face bends into its foot or rim, the plane of the
    majority."""
    face_rough: float = Field(0.10, gt=0.0, le=10.0)
    """Metres: RMS of the kept neighbours about their plane above which the point
    is in vegetation, not on a surface; the point itself must lie within the
    larger of 3 RMS and this of the plane. Holds for faces planar to a few cm
    over the neighbourhood (the synthetic family: 3 cm noise); rougher rock
    needs more."""
    face_tilt: float = Field(50.0, ge=0.0, le=90.0)
    """Degrees: an added point whose plane is tilted less than this from level is
    no face: it counts only within ``face_ground`` of the ground surface (the
    2.5-D lowest ground: talus, rims, ground under a lip), not on a roof."""
    face_ground: float = Field(1.0, ge=0.0, le=100.0)
    """Metres: see ``face_tilt``."""
    face_rounds: int = Field(2, ge=1, le=5)
    """Rounds of the surface tests: each after the first fits the planes again to
    the unrotated ground and the candidates that passed the round before, not to
    every candidate (crowns and trunks a run took in front of a face). 1: one
    round, every candidate a neighbour."""
    face_local_link: bool = True
    """A group of added points joined within ``face_link`` but to no ground
    is joined to it still when it reaches ground, or a joined group, along its
    own surface within ``face_link`` of its own spacing, if it is sampled
    ``face_thin`` times more thinly than the block. A face the beams graze
    (band tile 0: 87°, oblique beams) holds its points metres apart, in groups
    of 1–3 that ``face_link`` block spacings never join (240 face points of
    that tile, 3.5 m from the ground at the median); crowns crowd their returns.
    False: ``face_link`` block spacings only."""
    face_spacing_k: int = Field(12, ge=2, le=64)
    """A point's own spacing: distance to its ``face_spacing_k``-th nearest
    point of the block × √(π / k), the spacing of a surface that holds k points
    within that distance; a group's is the median of its points'."""
    face_thin: float = Field(2.0, ge=1.0, le=100.0)
    """Block spacings: a group reaches out (``face_local_link``) only when its
    own spacing is at least this many. Band tile 0, groups ``face_link`` left
    unjoined: 137 on the face, own spacing 3.6 / 6.5 / 8.5× (10th percentile /
    median / 90th), 19 of vegetation 1.5 / 2.1 / 3.2× (20 of their 71 points in
    groups at 2× or more; ``face_link_along`` keeps them out: Type II 1.01 →
    1.00 %). At 1× the crown beside the face of the face-evidence test joins."""
    face_link_along: float = Field(20.0, ge=0.0, le=90.0)
    """Degrees: a reach-out link counts only within this of the plane the point
    passed the surface tests on: up and down a thinly sampled face, not across
    to the ground off its own surface."""
    face_link: float = Field(5.0, gt=0.0, le=100.0)
    """Point spacings (the larger of the block's mean spacing and the median
    distance between the added points that passed): added points join each
    other and the unrotated ground within this distance (3-D); a group joined to
    no ground (a crown top, a bird) is dropped."""
    rerun_unrotated: bool = True
    """Steep blocks: run the unrotated cloud again with ``ground_preset``, as
    the seed does (nine conservative runs OR'ed), instead of keeping the
    block's default labels, whose low vegetation on the rims the OR would
    carry. False: keep them."""
    ground_preset: str = Field("conservative", alias="preset")
    """Parameter set of the ground method for every run (seed: conservative)."""

    #: Per ground method, named by its stage id; a block takes the one of its
    #: method (``stage_params(params, "ground.rotation", stage.id)``), the
    #: fields above otherwise (the seed's settings, which suit ground.ptd).
    #: ground.nist follows terrain only up to its slope caps and cannot grow
    #: from the labels found so far, so one tip leaves part of an overhang
    #: steeper than those caps; a second, larger tip finds it, and the first
    #: keeps the plateau and talus beside a face that the larger tip loses.
    #: Its conservative preset is no safe unrotated run (it can lose a
    #: plateau), so the block's default labels are kept. Each run sees only the
    #: faces looking its way (``aspect_window``) within ``context``. README
    #: *Measured* (choices of ``ground.rotation``) has the figures.
    presets = {"ground.nist": {"angle": 30.0, "second_angle": 45.0, "rerun_unrotated": False}}


@dataclass(frozen=True)
class SteepTest:
    """Outcome of the steepness test: share of steep facets, verdict, TIN size."""

    facet_share: float
    steep: bool
    n_facets: int


@dataclass
class RotatedResult:
    """Combined labels; ``added[k]``: points rotation k labelled ground beyond the
    unrotated run (the directions N… tipped by ``angle``, then by ``second_angle``)."""

    is_ground: NDArray[np.bool_]
    added: list[int] = field(default_factory=list)
    unrotated: int = 0


@register(
    "ground.steep",
    SteepParams,
    "per-block steepness test: share of steep facets of the lowest-point TIN",
)
def steepness(xyz: NDArray[np.float64], params: SteepParams) -> SteepTest:
    """Share of facets steeper than ``facet_angle`` in the TIN of the lowest
    point of every ``cell``; a few sorts and one small Delaunay."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.shape[0] < 3:
        return SteepTest(0.0, False, 0)
    x, y = xyz[:, 0], xyz[:, 1]
    lo = np.array([x.min(), y.min(), xyz[:, 2].min()])
    grid = Grid.covering(x - lo[0], y - lo[1], params.cell)
    flat = grid.index(x - lo[0], y - lo[1])
    low = lowest_per_bin(flat, xyz[:, 2], grid.size)
    # Cells the tested points span less than half of in x or y (slivers at the
    # data's edge, ground in a corner beside a building) give no lowest point:
    # several of them along an edge make thin facets with arbitrary slopes.
    spans = []
    for v in (x, y):
        vmin = np.full(grid.size, np.inf)
        vmax = np.full(grid.size, -np.inf)
        np.minimum.at(vmin, flat, v)
        np.maximum.at(vmax, flat, v)
        spans.append(vmax - vmin)
    low = low[(low >= 0) & (spans[0] >= 0.5 * params.cell) & (spans[1] >= 0.5 * params.cell)]
    pts = xyz[low] - lo
    steep, n = _steep_facets(pts, params)
    if params.support > 0 and steep.size:
        # Drop lone low vertices under steep facets and test again.
        xs = np.argsort(xyz[:, 0])
        cloud = xyz[xs] - lo
        lone = [v for v in np.unique(steep) if not _supported(cloud, pts[v], params)]
        if lone:
            pts = np.delete(pts, lone, axis=0)
            steep, n = _steep_facets(pts, params)
    steep = steep.shape[0]
    share = float(steep / n) if n else 0.0
    return SteepTest(share, share > params.steep_share, n)


def _steep_facets(pts: NDArray[np.float64], params: SteepParams) -> tuple[NDArray[np.int64], int]:
    """Lowest vertex of every steep facet of the TIN of ``pts``, and the number of facets counted."""
    try:
        tri = Delaunay(pts[:, :2])
    except (QhullError, ValueError):
        return np.zeros(0, dtype=np.int64), 0
    p = pts[tri.simplices]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    norm = np.linalg.norm(normal, axis=1)
    # Slivers along the convex hull join far-apart border cells; they are no terrain.
    edge = np.max(np.hypot(*(p[:, [1, 2, 0], :2] - p[:, :, :2]).transpose(2, 0, 1)), axis=1)
    good = np.flatnonzero((norm > 0) & (edge <= 3.0 * params.cell))
    slope = np.degrees(np.arccos(np.abs(normal[good, 2]) / norm[good]))
    # A thin facet (plan height onto its longest side < thin_facet cells: nearly
    # collinear lowest points, as along cell borders on rolling ground) tilts
    # its normal by any small height difference across it; it counts as steep
    # only when one of its sides is.
    thin = (
        np.abs(normal[good, 2]) / edge[good] < params.thin_facet * params.cell
    )  # |normal_z| = 2 * plan area
    if thin.any():
        q = p[good[thin]]
        d = q[:, [1, 2, 0]] - q
        side = np.degrees(np.arctan2(np.abs(d[..., 2]), np.hypot(d[..., 0], d[..., 1])))
        slope[thin] = side.max(axis=1)
    rise = np.ptp(p[good, :, 2], axis=1)
    hit = good[(slope > params.facet_angle) & (rise > params.min_rise)]
    low = tri.simplices[hit, np.argmin(p[hit, :, 2], axis=1)]
    return low, int(good.size)


def _supported(cloud: NDArray[np.float64], v: NDArray[np.float64], params: SteepParams) -> bool:
    """Has ``v`` ``support`` other points of ``cloud`` (sorted by x) near it, just above it?"""
    r = params.support_radius
    a, b = np.searchsorted(cloud[:, 0], [v[0] - r, v[0] + r])
    c = cloud[a:b]
    dz = c[:, 2] - v[2]
    near = (
        (np.hypot(c[:, 0] - v[0], c[:, 1] - v[1]) <= r)
        & (np.abs(dz) <= params.support_gap)
        & (dz != 0)
    )
    return int(np.count_nonzero(near)) >= params.support


def rotation_matrix(azimuth_deg: float, angle_deg: float) -> NDArray[np.float64]:
    """Rotation tipping faces that look toward ``azimuth_deg`` (compass) up by ``angle_deg``."""
    az = np.radians(azimuth_deg)
    d = np.array([np.sin(az), np.cos(az), 0.0])  # east, north
    axis = np.array([d[1], -d[0], 0.0])  # d × z
    t = np.radians(angle_deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * (k @ k)


def can_seed(stage: Stage) -> bool:
    """Does the ground stage grow from known labels (a ``seed_mask`` keyword, as ground.ptd)?"""
    return "seed_mask" in inspect.signature(stage.run).parameters


def bind_ground(
    stage: Stage, params: StageParams, **kwargs: Any
) -> tuple[GroundFn, SeededFn | None]:
    """The ground stage bound to ``params`` (and ``kwargs``, e.g. ``sensor_origin``)
    for ``classify_rotated``: the plain run and, when the stage can seed
    (``can_seed``), the run seeded with the labels found so far; else None."""

    def ground(p: NDArray[np.float64]) -> NDArray[np.bool_]:
        return stage.run(p, params, **kwargs)

    if not can_seed(stage):
        return ground, None

    def seeded(p: NDArray[np.float64], known: NDArray[np.bool_]) -> NDArray[np.bool_]:
        return stage.run(p, params, seed_mask=known, **kwargs)

    return ground, seeded


@register(
    "ground.rotation",
    RotationParams,
    "ground on the block and on copies tipped toward 8 directions, OR'ed",
)
def classify_rotated(
    xyz: NDArray[np.float64],
    ground: GroundFn,
    params: RotationParams,
    *,
    unrotated: NDArray[np.bool_] | None = None,
    seeded: Callable[[NDArray[np.float64], NDArray[np.bool_]], NDArray[np.bool_]] | None = None,
    last_return: NDArray[np.bool_] | None = None,
    restore: Callable[[NDArray[np.float64], NDArray[np.bool_]], NDArray[np.bool_]] | None = None,
) -> RotatedResult:
    """Boolean OR of ``ground`` on the block as it is and on ``directions``
    copies tipped by ``angle`` about the centroid (and ``directions`` more
    tipped by ``second_angle`` when set).

    ``ground`` is any ground method bound to its parameters. ``unrotated`` may
    carry labels the caller already has for the block as it is (then that run
    is not repeated). ``seeded(points, known_ground)``, when the ground method
    offers it (ground.ptd's ``seed_mask``), runs the rotated clouds with the
    unrotated ground as extra seeds: the TIN then already holds the cliff's foot
    and rim, and the tipped face between them is densified instead of being cut
    off under the rim (a tipped cliff top is a sharp ridge, which a TIN filter
    grown from cell minima cannot climb).

    ``last_return`` (per point: the last or only return of its pulse), when
    given, is echo evidence: a rotated run adds no point that a later return
    of the same pulse lies behind (crowns and bushes; a rock face is opaque).

    ``restore(points, labels)``, when given, follows the ground method in the
    runs tipped by ``angle`` (the landform rule, ``steps._ground``): tipped by
    30° a mesa is still a raised body to the filter, and the flank the tip
    flattens went with it. On the tune band tile 0 (stage level) faces > 60°
    were found 84.6 % without it, 87.6 % after the first tip's runs, 87.3 %
    after both tips' and 84.3 % after the second's alone, so the second tip's
    runs, which cost as much again, go without.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    base = np.asarray(ground(xyz) if unrotated is None else unrotated, dtype=bool)
    combined = base.copy()
    added: list[int] = []
    centroid = xyz.mean(axis=0)
    footing = None
    if params.edge_margin is None and base.any():
        footing = _ground_level(xyz, base)
        # The footprint test needs the feet's extent, not every foot: one per
        # 1 m voxel fills the 2 m cells of ``_over_ground`` at any tip.
        vox = np.floor(footing - footing.min(axis=0)).astype(np.int64)
        span = vox.max(axis=0) + 1
        key = (vox[:, 0] * span[1] + vox[:, 1]) * span[2] + vox[:, 2]
        _, first = np.unique(key, return_index=True)
        feet_xyz = footing[first]
    near = None
    work: slice | NDArray[np.intp] = slice(None)
    faces: _Faces | None = None
    wide = None
    if (
        params.max_lift is not None or params.steep_reach is not None or params.context is not None
    ) and base.any():
        wide = None if params.context is None else (params.steep_reach or 0.0) + params.context
        near, seen, faces = _near_surface(
            xyz,
            base,
            params.max_lift,
            params.steep_reach,
            wide,
            params.anchor_all is not None,
            params.anchor_all or 0.0,
        )
        if seen is not None:
            work = np.flatnonzero(seen)
    angles = [params.angle] if params.second_angle is None else [params.angle, params.second_angle]
    runs = [(360.0 * k / params.directions, a) for a in angles for k in range(params.directions)]
    views: dict[float, slice | NDArray[np.intp]] = {}
    for azimuth, angle in runs:
        view = work
        if faces is not None and params.aspect_window is not None and wide is not None:
            if azimuth not in views:
                views[azimuth] = faces.facing(
                    xyz, azimuth, params.aspect_window, wide, params.aspect_rise
                )
            view = views[azimuth]
        if not isinstance(view, slice) and view.size < 3:
            added.append(0)
            continue
        rot = rotation_matrix(azimuth, angle)
        shift = centroid - rot @ centroid
        # (x − c) R^T + c of the points this run sees: the only extra copy.
        part = _turn(xyz[view], rot, shift)
        labels = np.zeros(xyz.shape[0], dtype=bool)
        got = np.asarray(ground(part) if seeded is None else seeded(part, combined[view]), bool)
        if restore is not None and angle == params.angle:
            got = np.asarray(restore(part, got), dtype=bool)
        if got.any() and footing is not None:
            feet = _turn(feet_xyz, rot[:2], shift[:2])
            got &= _over_ground(part[:, :2], feet)
        elif got.any() and params.edge_margin:
            margin = params.edge_margin
            xy = _turn(xyz, rot[:2], shift[:2])
            lo, hi = xy[:, :2].min(axis=0) + margin, xy[:, :2].max(axis=0) - margin
            got &= np.all((part[:, :2] > lo) & (part[:, :2] < hi), axis=1)
        labels[view] = got
        if near is not None:
            labels &= near | base
        del part
        added.append(int(np.count_nonzero(labels & ~base)))
        combined |= labels
    if last_return is not None:
        combined &= base | np.asarray(last_return, dtype=bool)
    if params.face_evidence and (combined & ~base).any():
        combined = base | _on_faces(xyz, base, combined & ~base, footing, params)
    return RotatedResult(combined, added, int(np.count_nonzero(base)))


def _turn(
    points: NDArray[np.float64], rot: NDArray[np.float64], shift: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``points`` R^T + shift (R: the rows of the rotation wanted, e.g. x and y only)."""
    out = np.einsum("ij,kj->ik", points, rot)
    out += shift
    return out


def _on_faces(
    xyz: NDArray[np.float64],
    base: NDArray[np.bool_],
    cand: NDArray[np.bool_],
    footing: NDArray[np.float64] | None,
    params: RotationParams,
) -> NDArray[np.bool_]:
    """Which of the points ``cand`` (added by rotated runs) lie on a face: on a
    smooth surface (``face_rough``), steep (``face_tilt``) or else within
    ``face_ground`` of the ground surface, and linked to ``base`` ground through
    such points within ``face_link`` spacings."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    ci = np.flatnonzero(cand)
    span = np.ptp(xyz[:, :2], axis=0)
    density = xyz.shape[0] / max(float(span[0] * span[1]), 1.0)
    ok, normal = _fits(xyz, ci, np.flatnonzero(base | cand), footing, params)
    for _ in range(params.face_rounds - 1):
        # Again with the neighbours cleaned of the candidates that failed: the
        # crowns and trunks a run took in front of a face crowd its sparse
        # points out of their own neighbourhood; without them a face point is
        # judged by the face, a crown point by its distance to it.
        called = np.flatnonzero(base | _at(ci[ok], xyz.shape[0]))
        ok, normal = _fits(xyz, ci, called, footing, params)
    good, normal = ci[ok], normal[ok]
    out = np.zeros(xyz.shape[0], dtype=bool)
    if good.size == 0:
        return out
    # Link: the good points and the base ground near them, joined within face_link spacings.
    # A face is sampled more thinly than the ground below near-vertical beams:
    # the spacing is the larger of the block's and the good points' own.
    spacing = float(1.0 / np.sqrt(density))
    if good.size >= 3:
        own, _ = cKDTree(xyz[good]).query(xyz[good], k=2)
        spacing = max(spacing, float(np.median(own[:, 1])))
    r = params.face_link * spacing
    gi = np.flatnonzero(base)
    if gi.size == 0:
        return out
    d, _ = cKDTree(xyz[good]).query(xyz[gi], distance_upper_bound=r)
    gi = gi[np.isfinite(d)]
    nodes = np.concatenate([good, gi])
    pairs = cKDTree(xyz[nodes]).query_pairs(r, output_type="ndarray")
    n = nodes.size
    graph = coo_matrix((np.ones(pairs.shape[0]), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    grounded = np.zeros(comp.max() + 1, dtype=bool)
    grounded[comp[good.size :]] = True
    comp = comp[: good.size]
    if params.face_local_link:
        _reach_out(xyz, good, normal, comp, grounded, base, spacing, r, params)
    out[good[grounded[comp]]] = True
    return out


def _reach_out(
    xyz: NDArray[np.float64],
    good: NDArray[np.intp],
    normal: NDArray[np.float64],
    comp: NDArray[np.intp],
    grounded: NDArray[np.bool_],
    base: NDArray[np.bool_],
    spacing: float,
    r: float,
    params: RotationParams,
) -> None:
    """Ground (in ``grounded``, per group ``comp`` of the ``good`` points) the
    groups that reach ground along their own surface within ``face_link`` of
    their own spacing (``face_local_link``): a face the beams graze is sampled
    metres apart, so its points form small groups farther from each other and
    from the ground than ``r``; a crown's returns crowd, and its group's median
    spacing stays near the block's."""
    from scipy.spatial import cKDTree

    kk = params.face_spacing_k
    local, _ = cKDTree(xyz).query(xyz[good], k=kk + 1)
    own = local[:, -1] * np.sqrt(np.pi / kk)  # spacing of a surface holding kk points within
    order = np.argsort(comp, kind="stable")
    cuts = np.flatnonzero(np.diff(comp[order])) + 1
    med = np.zeros(grounded.size)
    for members in np.split(order, cuts):
        med[comp[members[0]]] = np.median(own[members])
    thin = med[comp] >= params.face_thin * spacing
    reach = np.where(thin, params.face_link * med[comp], r)
    sin_along = np.sin(np.radians(params.face_link_along))
    for _ in range(params.face_rounds + 3):
        loose = np.flatnonzero(~grounded[comp] & (reach > r))
        if loose.size == 0:
            return
        held = np.r_[np.flatnonzero(base), good[grounded[comp]]]
        hits = cKDTree(xyz[held]).query_ball_point(xyz[good[loose]], reach[loose])
        li = np.repeat(loose, [len(h) for h in hits])
        if li.size == 0:
            return
        v = xyz[held[np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])]]
        v = v - xyz[good[li]]
        dist = np.linalg.norm(v, axis=1)
        on = np.abs(np.einsum("mi,mi->m", v, normal[li])) <= sin_along * dist
        new = np.unique(comp[li[on]])
        if grounded[new].all():
            return
        grounded[new] = True


def _at(idx: NDArray[np.intp], n: int) -> NDArray[np.bool_]:
    """A mask of ``n`` points holding ``idx``."""
    out = np.zeros(n, dtype=bool)
    out[idx] = True
    return out


def _fits(
    xyz: NDArray[np.float64],
    ci: NDArray[np.intp],
    called: NDArray[np.intp],
    footing: NDArray[np.float64] | None,
    params: RotationParams,
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Per candidate ``ci``: does it lie on a smooth surface through its nearest
    ``called`` points (``_on_faces``' plane tests, before the link), and the
    unit normal of that surface (of the first plane that holds it)."""
    from scipy.spatial import cKDTree

    k = min(params.face_neighbours, called.size - 1)
    if k < 3:
        return np.zeros(ci.size, dtype=bool), np.zeros((ci.size, 3))
    _, nb = cKDTree(xyz[called]).query(xyz[ci], k=k + 1)
    # The point itself left out where it is among ``called``, the k-th else.
    itself = called[nb[:, 0]] == ci
    near = xyz[called][np.where(itself[:, None], nb[:, 1:], nb[:, :-1])]  # (m, k, 3)
    keep = max(3, int(round(params.face_trim * k)))
    # Two planes: the majority of the neighbours (refitted three times to the
    # closest ``face_trim``), and the ``face_trim`` nearest to the point. At a
    # face's foot or rim the majority may be the flat ground beside it, which a
    # face point stands off by decimetres; the nearest lie on its own face.
    sub = near
    for _ in range(3):
        centre, normal, rough = _plane(sub)
        off = np.abs(np.einsum("mki,mi->mk", near - centre[:, None, :], normal))
        sub = np.take_along_axis(near, np.argsort(off, axis=1)[:, :keep, None], axis=1)
    ok = np.zeros(ci.size, dtype=bool)
    normals = np.zeros((ci.size, 3))
    for centre, normal, rough in (_plane(sub), _plane(near[:, :keep])):
        own = np.abs(np.einsum("mi,mi->m", xyz[ci] - centre, normal))
        tilt = np.degrees(np.arccos(np.clip(np.abs(normal[:, 2]), 0.0, 1.0)))
        fits = (rough <= params.face_rough) & (own <= np.maximum(3.0 * rough, params.face_rough))
        gentle = tilt < params.face_tilt
        if footing is not None:
            fits &= ~gentle | (xyz[ci, 2] - footing[ci, 2] <= params.face_ground)
        else:
            fits &= ~gentle
        normals[fits & ~ok] = normal[fits & ~ok]
        ok |= fits
    return ok, normals


def _plane(
    pts: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per row of ``pts`` (m, k, 3): centroid, unit normal and RMS about the
    least-squares plane."""
    centre = pts.mean(axis=1)
    d = pts - centre[:, None, :]
    val, vec = np.linalg.eigh(np.einsum("mki,mkj->mij", d, d) / pts.shape[1])
    return centre, vec[:, :, 0], np.sqrt(np.maximum(val[:, 0], 0.0))


def _ground_level(xyz: NDArray[np.float64], ground: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Every point dropped onto the surface through the lowest ``ground`` point per
    2 m cell (points below it stay): its foot, which tipping does not move sideways
    relative to the ground."""
    from terrasift.workers.surface import TinSurface

    g = np.flatnonzero(ground)
    lo = xyz[g, :2].min(axis=0)
    grid = Grid.covering(xyz[g, 0] - lo[0], xyz[g, 1] - lo[1], 2.0)
    low = lowest_per_bin(grid.index(xyz[g, 0] - lo[0], xyz[g, 1] - lo[1]), xyz[g, 2], grid.size)
    surf = TinSurface(xyz[g[low[low >= 0]]])
    foot = xyz.copy()
    foot[:, 2] = np.minimum(xyz[:, 2], surf(xyz[:, 0], xyz[:, 1]))
    return foot


def _over_ground(
    xy: NDArray[np.float64], foot_xy: NDArray[np.float64], cell: float = 2.0
) -> NDArray[np.bool_]:
    """Which tipped points (``xy``) lie over the footprint of the tipped feet
    (``foot_xy``): cells of ``cell`` metres holding a foot, gaps of a cell closed,
    less the outermost cell (a foot at the rim has no ground beyond it)."""
    from scipy import ndimage

    lo = np.minimum(xy.min(axis=0), foot_xy.min(axis=0)) - 2 * cell
    shape = (np.maximum(xy.max(axis=0), foot_xy.max(axis=0)) - lo) // cell + 3
    nx, ny = int(shape[0]), int(shape[1])
    occ = np.zeros((ny, nx), dtype=bool)
    fi = ((foot_xy - lo) // cell).astype(np.int64)
    occ[fi[:, 1], fi[:, 0]] = True
    occ = ndimage.binary_closing(occ, structure=np.ones((3, 3)))
    occ = ndimage.binary_erosion(occ, structure=np.ones((3, 3)))
    pi = ((xy - lo) // cell).astype(np.int64)
    return occ[pi[:, 1], pi[:, 0]]


#: Metres: radius over which the steep facets' normals are summed for their aspect.
_ASPECT_R = 6.0


@dataclass(frozen=True)
class _Faces:
    """Vertices of the steep facets of the unrotated ground (x, y), the compass
    azimuth (degrees) their facet looks toward and the facet's rise (metres)."""

    xy: NDArray[np.float64]
    aspect: NDArray[np.float64]
    rise: NDArray[np.float64]
    group: int = 3
    """Cells looking within the window in the 5 × 5 cells around a face cell."""

    def facing(
        self,
        xyz: NDArray[np.float64],
        azimuth: float,
        window: float,
        wide: float,
        min_rise: float = 0.0,
        cell: float = 2.0,
    ) -> NDArray[np.intp]:
        """Points within ``wide`` (x, y, on a raster of ``cell``) of the facets
        rising at least ``min_rise`` that look within ``window`` of ``azimuth``."""
        from scipy import ndimage

        off = np.abs((self.aspect - azimuth + 180.0) % 360.0 - 180.0)
        pick = (off < window) & (self.rise >= min_rise)
        if not pick.any():
            return np.zeros(0, dtype=np.intp)
        lo = xyz[:, :2].min(axis=0)
        ij = ((xyz[:, :2] - lo) // cell).astype(np.int64)
        shape = ij.max(axis=0) + 1
        hit = np.ones((int(shape[1]), int(shape[0])), dtype=bool)
        aj = np.clip(((self.xy[pick] - lo) // cell).astype(np.int64), 0, shape - 1)
        hit[aj[:, 1], aj[:, 0]] = False
        # A face is a run of cells looking the same way; a lone facet so
        # turned is where a jagged face line or a trunk bends the lowest ground.
        own = ndimage.uniform_filter((~hit).astype(np.float64), size=5, mode="constant") * 25
        hit |= own < self.group - 0.5
        if hit.all():
            return np.zeros(0, dtype=np.intp)
        dist = ndimage.distance_transform_edt(hit) * cell
        # A cell's centre may lie up to a half-diagonal from a point in it.
        return np.flatnonzero(dist[ij[:, 1], ij[:, 0]] <= wide + cell * 0.7072)


def _steep_facets_of(
    verts: NDArray[np.float64],
    top: NDArray[np.bool_] | None = None,
    foot: NDArray[np.bool_] | None = None,
) -> (
    tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None
):
    """Of the TIN of ``verts`` (x, y, z): the vertices of its facets steeper
    than 50° (x, y), and per such facet its upward normal, plan centre and
    rise; None when there is no TIN. With ``top`` and ``foot``, only the
    facets whose highest vertex ``top`` marks and lowest ``foot``."""
    try:
        tri = Delaunay(verts[:, :2])
    except (QhullError, ValueError):
        return None
    p = verts[tri.simplices]
    nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    slope = np.abs(nrm[:, 2]) < np.cos(np.radians(50.0)) * np.linalg.norm(nrm, axis=1)
    if top is not None and foot is not None:
        rows = np.arange(p.shape[0])
        slope &= top[tri.simplices[rows, np.argmax(p[:, :, 2], axis=1)]]
        slope &= foot[tri.simplices[rows, np.argmin(p[:, :, 2], axis=1)]]
    up = nrm[slope] * np.sign(nrm[slope, 2:3] + (nrm[slope, 2:3] == 0))
    corners = verts[tri.simplices[slope].ravel(), :2]
    return corners, up, p[slope, :, :2].mean(axis=1), np.ptp(p[slope, :, 2], axis=1)


def _near_surface(
    xyz: NDArray[np.float64],
    ground: NDArray[np.bool_],
    lift: float | None,
    reach: float | None,
    wide: float | None = None,
    all_points: bool = False,
    anchor_gap: float = 10.0,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_] | None, _Faces | None]:
    """Points within ``lift`` of the surface through the lowest ``ground`` point
    per 2 m cell and within ``reach`` (in x, y) of its facets steeper than 50°;
    the points within ``wide`` of those facets (None when not asked); and the
    facets themselves (``_Faces``, None when not asked). With ``all_points``
    the facets of the surface through the lowest point of every point per cell
    count for ``wide`` and the faces too where their highest vertex stands
    ``anchor_gap`` or more (3-D) from the lowest ground point of every cell
    (``RotationParams.anchor_all``)."""
    from scipy.spatial import cKDTree

    from terrasift.workers.surface import TinSurface

    g = np.flatnonzero(ground)
    lo = xyz[g, :2].min(axis=0)
    grid = Grid.covering(xyz[g, 0] - lo[0], xyz[g, 1] - lo[1], 2.0)
    low = lowest_per_bin(grid.index(xyz[g, 0] - lo[0], xyz[g, 1] - lo[1]), xyz[g, 2], grid.size)
    verts = xyz[g[low[low >= 0]]] - [lo[0], lo[1], 0.0]
    ok = np.ones(xyz.shape[0], dtype=bool)
    if lift is not None:
        surf = TinSurface(verts + [lo[0], lo[1], 0.0])
        ok &= np.abs(xyz[:, 2] - surf(xyz[:, 0], xyz[:, 1])) < lift
    if reach is None and wide is None:
        return ok, None, None
    own = _steep_facets_of(verts)
    if own is None:
        return ok, None, None
    sets = [own]
    if wide is not None and all_points:
        alo = xyz[:, :2].min(axis=0)
        agrid = Grid.covering(xyz[:, 0] - alo[0], xyz[:, 1] - alo[1], 2.0)
        al = lowest_per_bin(
            agrid.index(xyz[:, 0] - alo[0], xyz[:, 1] - alo[1]), xyz[:, 2], agrid.size
        )
        av = xyz[al[al >= 0]]
        # Only steps from the ground labels (the face's foot) up to a lowest
        # point far from every ground label: a plateau the filter lost, not a
        # crown over ground it kept nor a tree on that plateau.
        # (The ground labels stand for their lowest point per 2 m cell.)
        av = av - [lo[0], lo[1], 0.0]
        off, _ = cKDTree(verts).query(av, distance_upper_bound=anchor_gap)
        every = _steep_facets_of(av, ~np.isfinite(off), off <= 2.0)
        if every is not None:
            sets.append(every)
    none = np.zeros(xyz.shape[0], dtype=bool)
    if own[1].shape[0] == 0:
        if reach is not None:
            ok = none
        if wide is None:
            return ok, None, None
    far = max(wide or 0.0, reach or 0.0)
    if reach is not None and own[1].shape[0]:
        dist, _ = cKDTree(own[0]).query(xyz[:, :2] - lo, distance_upper_bound=far)
        ok &= dist <= reach
    if wide is None:
        return ok, None, None
    corners = np.concatenate([s[0] for s in sets])
    up = np.concatenate([s[1] for s in sets])
    mid = np.concatenate([s[2] for s in sets])
    rise = np.concatenate([s[3] for s in sets])
    if up.shape[0] == 0:
        return ok, none, _Faces(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    dist, _ = cKDTree(corners).query(xyz[:, :2] - lo, distance_upper_bound=far)
    # The upward normal's horizontal part points where the facet looks;
    # summed (area-weighted) over the steep facets within ``_ASPECT_R``,
    # as a jagged face line in 2 m cells turns single facets by up to 60°.
    near = cKDTree(mid).sparse_distance_matrix(cKDTree(mid), _ASPECT_R, output_type="coo_matrix")
    rows = np.r_[near.row, np.arange(mid.shape[0])]
    cols = np.r_[near.col, np.arange(mid.shape[0])]
    sx = np.bincount(rows, weights=up[cols, 0], minlength=mid.shape[0])
    sy = np.bincount(rows, weights=up[cols, 1], minlength=mid.shape[0])
    aspect = np.degrees(np.arctan2(sx, sy)) % 360.0
    faces = _Faces(corners + lo, np.repeat(aspect, 3), np.repeat(rise, 3))
    return ok, np.isfinite(dist), faces
