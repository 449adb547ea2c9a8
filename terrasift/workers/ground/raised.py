"""Raised segments of a ground TIN: parts that stand above the rest behind steps.

A roof or a bridge deck wide enough to fill the bins of every pass reaches the
ground TIN as a patch of well-behaved vertices: flat, screened as smooth, not
mowed. What gives it away is its border: everywhere it meets the rest of the
TIN, the TIN drops by a wall (an edge rising at least ``step`` metres, steeper
than ``step_slope``), while terrain joins its surroundings somewhere without
one. So the TIN is cut into segments along step edges, and a segment that is
only ever the upper side of its steps is dropped as a whole. The largest
segment is kept, and so is one that reaches the edge of the data along more
than a roof's or platform's end would (``edge``; what lies beyond is unknown,
and a plateau crossing the data is walled on both its long sides as a platform
is). Repeated, so a roof under a raised part (a tower) goes too.

On a slope a roof is not the upper side everywhere: where the hill rises
behind it, the terrain stands above its uphill wall. So a segment that is the
upper side of at least ``up_share`` of its steps is dropped too when it stands
on average ``min_lift`` or more above the least-squares plane through the feet
of its steps (the vertices beyond them). A terrace tread between a wall above
and a wall below, or a bench of a cut slope, sits near that plane and is the
lower side about as often as the upper.

A platform whose neighbours (wagons) were dropped meets the ground across the
holes they left by long gentle edges; where the terrain behind their far end
does not tell (it bends over that run), the platform's own walls do: cut off
from the rest by its walls and the holes, it is a level walled patch, and an
edge across a hole falling from it about as far as its walls drop is a step.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay

from terrasift.workers.ground._kernels import _lower_medians, _ramp_counts

#: ``sides``: share of the returns over the middle of a segment's steps that lie on their ramps
#: (an embankment of the rural family 0.35-0.37 with low vegetation on it; walls of roofs and
#: platforms 0.06-0.11 at 0.5-20 pts/m²)
_RAMP_SHARE = 0.25
#: ...over its steps no longer than this many median edges (the rural family's embankment
#: sides 0.8-2.8, slivers along the hull of steep data 10-140)
_RAMP_RUNS = 4.0
#: ...for a segment of at least this many vertices: a crest more than a bin or two across. The
#: steps of a lone vertex or a pair (a shrub's top) radiate from one spot, and their ramps
#: cross its canopy's returns as readily as a bank's (rural seed 202 kept such a shrub)
_RAMP_VERTICES = 3
#: ``over_walls``: the fewest returns over an edge's middle that tell a ramp from a wall (one
#: under the ramp and one over it; railway seed 97's edge across a 0.8 m wall at 2 pts/m² has 2)
_RAMP_MIN = 2
#: Most grid cells ``_on_ramp`` lays over its steps (8 MB of cell offsets): steps far apart on
#: a dense tile get wider cells, which only lengthens each cell's list
_RAMP_CELLS = 1_000_000
#: ``along``: edges at least this many median edges long are judged by the terrain behind them
_ALONG_RUNS = 2.0
#: ...sampled this many runs behind the end (the median of the slopes they give)
_BEHIND = (0.5, 0.75, 1.0)


def tin_edges(tri: Delaunay) -> NDArray[np.int64]:
    """Unique undirected edges (i < j) of a 2-D triangulation, shape (m, 2)."""
    indptr, indices = tri.vertex_neighbor_vertices
    owner = np.repeat(np.arange(indptr.size - 1), np.diff(indptr))
    e = np.column_stack([owner, indices]).astype(np.int64)
    return e[e[:, 0] < e[:, 1]]


def raised_segments(
    xyz: NDArray[np.float64],
    tri: Delaunay,
    step: float,
    step_slope_deg: float,
    *,
    up_share: float = 1.0,
    min_lift: float = 0.0,
    rounds: int = 4,
    relative: bool = False,
    walls: float = 0.0,
    rise: float = 0.0,
    rim: float = 0.0,
    edge: float = 0.0,
    cut: tuple[float, float, float, float] | None = None,
    along: bool = False,
    heights: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
    graded: float = 0.0,
    walled: float = 0.0,
    even: bool = False,
    sides: float = 0.0,
    points: NDArray[np.float64] | None = None,
    over_walls: bool = False,
) -> NDArray[np.bool_]:
    """Vertices of ``tri`` (built on ``xyz[:, :2]``) in raised segments; see the module doc.

    ``up_share`` 1 keeps to wholly raised segments (``min_lift`` is then unused).
    With ``relative``, an edge is a step only when its gradient exceeds the
    median gradient of the edges going down from its lower end by
    tan(``step_slope_deg``): a wall rises out of the terrain at its foot, a
    slope edge of steep terrain continues the slope below it.
    ``walls`` > 0 keeps the steps measured against level (so the segments stay
    the same) but drops a segment only when at least this share of the steps it
    is the upper side of are walls in that relative sense: the verdict is taken
    over the whole border, so one steep slope edge more or less (where the bins
    fell) does not cut a hilltop off, while a roof or platform, walled all round,
    still goes.
    ``rise`` > 0: an edge rising at least this much more than the slope at its
    foot predicts over its run is a step and a wall however gentle its gradient:
    a 1 m platform whose neighbours (wagons, cars) were dropped meets the
    ground 5–9 m away, at 6–10° (walls then count with ``walls``). A segment the
    upper side of such an edge goes only when it is also flat (its vertices within
    ``step`` RMS of their least-squares plane): a platform or a row of wagons is,
    a hillside that long edges happen to cut off is not.
    ``rim`` > 0: edges longer than ``rim`` median edges with both ends within
    one median edge of the hull's border join no segments. They are slivers
    along the edge of the data (tens of metres long) and carry no evidence; a
    platform reaching that edge was joined by them to ground far along it.
    ``edge`` > 0: a segment is kept when its vertices within one median edge of
    the hull's border span at least ``edge`` metres (bounding-box diagonal); 0:
    when it holds a vertex of the hull. The hull's vertices are a handful of
    points on a straight edge of the data, so which segment holds one is luck
    (a 1 cm rounding moves them); the span measures how far a segment runs
    along the edge.
    ``cut`` (xmin, ymin, xmax, ymax in the coordinates of ``xyz``): the box the
    points were cut to from data that goes on beyond it (a block's core and
    halo). Hull edges along its sides are cuts, not the edge of the data, so
    ``edge`` judges only the rest of the hull: a roof crossing the cut is
    judged by its walls, as in a run over all the data.
    ``along``: an edge across a hole (at least ``_ALONG_RUNS`` median edges long)
    is judged by the terrain behind each of its ends, over the edge's own run
    (``_excess``): an end standing ``rise`` above what the terrain behind the other
    end predicts for it, while that end is not above the prediction from it (a
    hollow), is the upper side of a step and a wall, also where the edge is level
    (ground rising away from a platform across the hole). Terrain behind steeper
    than ``step_slope_deg`` (a wall's gradient) is not extrapolated. The slope at the foot
    alone, fitted from neighbours half a metre to two metres away, carries the
    1 cm rounding and the noise of the data as 1-2 % of grade, which over a 25-46 m
    run is the whole margin; its size alone also predicts a rise for an edge
    running downhill onto a platform.
    ``graded`` > 0: a segment reaching the edge of the data is kept when at least this
    share of its steps down land on ground falling on beyond them (``_graded_at_edge``):
    an embankment cut by the edge, not a platform.
    ``walled`` > 0: an edge across a hole (at least ``_ALONG_RUNS`` median edges long,
    not a step) that falls from a walled flat patch by at least this share of the median
    height of the patch's walls is a step and a wall (``_walled_falls``). The patches are
    the segments joined by short edges only; a walled one is flat (``step`` RMS, on a
    plane gentler than ``step_slope_deg``), not the largest, the upper side of every
    short step on its border, walled on ``walls`` of them and graded (``graded``) on
    fewer than that share of them: a platform whose neighbours left holes around it meets the ground beyond them
    at a gentle grade, which the terrain behind the far end may predict (a slope bending
    over 70 m), but its own walls say how high it stands.
    ``even``: a segment above a ``rise`` edge counts as flat also when its own walls
    (steps up onto it, not ``rise`` edges nor steps found by ``walled``) are at least
    ``walls`` of its steps up and stand at one height: their median absolute deviation,
    as a standard deviation (x 1.4826), at most ``step`` (``_even_walls``). A platform
    following the ground along 100-150 m is level across but bends with the terrain
    under it, so it leaves its least-squares plane by more than ``step``; it still
    stands the same height above its foot all round, which a hillside cut off by
    long edges does not (its walls are the slope's edges, metres apart in height).
    ``heights``: the TIN's height at points (k, 2), nan outside it (``along``; None:
    interpolated on ``tri``, which must then be a scipy ``Delaunay``).
    ``sides`` > 0 with ``points`` (the data, (m, 3), in the coordinates of ``xyz``): a segment
    is kept when at least this share of its steps up onto it carry a point of the data on
    the ramp between their ends, and at least ``_RAMP_SHARE`` of all the points over the
    middle of those steps lie on their ramps (``_on_ramp``): the sloped side of an embankment
    holds returns at intermediate heights between its foot and crest, the wall of a roof or
    platform has its foot and top level up to it (a facade or a shrub is a point or two).
    ``over_walls`` with ``points``: an edge gentler than a step that rises ``step`` or more
    from the top of a wall, no longer than ``_RAMP_RUNS`` median edges, is a step and a wall
    when the returns over its middle stand at its foot's level and at its top's, fewer than
    ``_RAMP_SHARE`` of them between (``_on_ramp``): it crosses the wall on a diagonal, the
    foot going on past its start and the top before its end, and alone it joined a platform
    to the terrain at some bin phases (railway seed 97). A bank or a slope crossed so
    carries returns on its face, between: it joins.
    """
    n = xyz.shape[0]
    e = tin_edges(tri)
    dz = xyz[e[:, 1], 2] - xyz[e[:, 0], 2]
    run = np.hypot(*(xyz[e[:, 1], :2] - xyz[e[:, 0], :2]).T)
    med = float(np.median(run))
    grad = np.abs(dz) / np.maximum(run, 1e-9)
    tan_step = np.tan(np.radians(step_slope_deg))
    wall = grad >= tan_step
    big = np.zeros(e.shape[0], dtype=bool)
    rising = dz > 0  # the step's upper end is e[:, 1]
    if relative or walls > 0 or rise > 0:
        # The terrain at an edge's foot: the edges going down from its lower end.
        upper = np.where(dz > 0, e[:, 1], e[:, 0])
        base = _median_per_vertex(upper, grad, n)
        lower = np.where(dz > 0, e[:, 0], e[:, 1])
        wall = grad - base[lower] >= tan_step
        if rise > 0:
            # Only edges under the step gradient: steeper ones are judged as walls above.
            big = (grad < tan_step) & (np.abs(dz) - base[lower] * run >= rise)
            if along:
                # Edges across holes (a few median edges long): the terrain behind each end,
                # over the edge's own run, predicts the other end (``_excess``).
                far = np.flatnonzero((grad < tan_step) & (run >= _ALONG_RUNS * med))
                if far.size:
                    to_1, to_0 = _excess(
                        xyz, heights or _heights_of(xyz, tri), e[far], base, tan_step
                    )
                    # Above the prediction from one end only; from both, it is a hollow.
                    up_1, up_0 = (to_1 >= rise) & (to_0 < rise), (to_0 >= rise) & (to_1 < rise)
                    big[far] = up_1 | up_0
                    rising[far] = np.where(up_1 | up_0, up_1, rising[far])
            wall |= big
        if relative:
            grad = grad - base[lower]
    is_step = ((np.abs(dz) >= step) & (grad >= tan_step)) | (big & ((np.abs(dz) >= step) | along))
    if over_walls and points is not None:
        crossing = _over_walls(xyz, e, dz, run, med, is_step, wall, step, points)
        is_step[crossing], wall[crossing] = True, True
    joins = ~is_step
    if rim > 0:
        # Slivers along the border of the data: long edges between vertices near
        # the hull join what lies far apart along the edge, by no evidence.
        long = np.flatnonzero(run > rim * med)
        if long.size:
            ends = np.unique(e[long])  # only their ends need the distance to the hull
            near = np.zeros(n, dtype=bool)
            near[ends] = _hull_distance(xyz[:, :2], tri, ends) <= med
            joins[long[near[e[long, 0]] & near[e[long, 1]]]] = False
    across = np.zeros(e.shape[0], dtype=bool)  # steps found across holes by ``walled``
    if walled > 0:
        falls, fall_up = _walled_falls(
            xyz, e, dz, run, med, joins, is_step, wall, step, tan_step, walls, walled, graded
        )
        if falls.size:
            is_step[falls], joins[falls], wall[falls] = True, False, True
            rising[falls], across[falls] = fall_up, True
    gentle = e[joins]
    graph = coo_matrix((np.ones(gentle.shape[0]), (gentle[:, 0], gentle[:, 1])), shape=(n, n))
    n_seg, seg = connected_components(graph, directed=False)
    size = np.bincount(seg, minlength=n_seg)
    # The hull's edges that are the edge of the data (None: all of them).
    border = None if cut is None else data_border(xyz[:, :2], tri, cut, med)
    if edge > 0:
        fixed = _along_edge(xyz[:, :2], tri, seg, n_seg, med, border) >= edge
    else:
        fixed = np.zeros(n_seg, dtype=bool)
        fixed[seg[np.unique(tri.convex_hull if border is None else border)]] = True
    fixed[np.argmax(size)] = True
    st = e[is_step]
    up = rising[is_step]
    lo_v = np.where(up, st[:, 0], st[:, 1])
    hi_v = np.where(up, st[:, 1], st[:, 0])
    lo, hi = seg[lo_v], seg[hi_v]
    cross = lo != hi
    lo, hi, lo_v, hi_v = lo[cross], hi[cross], lo_v[cross], hi_v[cross]
    if graded > 0:
        # Only the steps of the border itself: one across a hole says nothing of its sides.
        own = ~across[is_step][cross]
        fixed |= _graded_at_edge(
            xyz, tri, seg, n_seg, med, border, e, hi[own], lo_v[own], hi_v[own], step, graded
        )
    if sides > 0 and points is not None and hi.size:
        # Steps of the border only, no longer than a few median edges: the slivers along
        # the hull and the edges across holes span tens of metres of any terrain.
        # Only the steps of segments this can still keep (wide, not kept yet): the data near
        # them is a small part of a dense block's.
        short = np.hypot(*(xyz[hi_v, :2] - xyz[lo_v, :2]).T) <= _RAMP_RUNS * med
        short &= ~fixed[hi] & (size[hi] >= _RAMP_VERTICES)
        on, mid = _on_ramp(points, xyz[lo_v[short]], xyz[hi_v[short]])
        h = hi[short]
        n_up = np.bincount(h, minlength=n_seg)
        carried = np.bincount(h, on > 0, n_seg) / np.maximum(n_up, 1)
        pooled = np.bincount(h, on, n_seg) / np.maximum(np.bincount(h, mid, n_seg), 1)
        wide = size >= _RAMP_VERTICES
        fixed |= wide & (n_up > 0) & (carried >= sides) & (pooled >= _RAMP_SHARE)
    is_wall = wall[is_step][cross]
    is_big = big[is_step][cross]
    flat = _flat(xyz, seg, n_seg, step) if is_big.any() else np.ones(n_seg, dtype=bool)
    if even and is_big.any():
        own = is_wall & ~is_big & ~across[is_step][cross]
        height = np.abs(xyz[hi_v, 2] - xyz[lo_v, 2])
        flat |= _even_walls(hi, own, height, n_seg, step, walls)
    gone = np.zeros(n_seg, dtype=bool)
    for _ in range(rounds):
        live = ~gone[lo] & ~gone[hi]
        n_up = np.bincount(hi[live], minlength=n_seg)
        n_down = np.bincount(lo[live], minlength=n_seg)
        # Share of its steps a segment is the upper side of (1 with none left).
        share = np.where(n_down > 0, n_up / np.maximum(n_up + n_down, 1), 1.0)
        raised = ~fixed & ~gone & (share >= up_share)
        if walls > 0:
            n_wall = np.bincount(hi[live & is_wall], minlength=n_seg)
            raised &= (n_up == 0) | (n_wall >= walls * n_up)
        if is_big.any():
            n_big = np.bincount(hi[live & is_big], minlength=n_seg)
            raised &= (n_big == 0) | flat
        partly = raised & (share < 1.0)
        if partly.any():
            # The foot of each step seen from its segment: the lower end seen
            # from the upper segment and the upper end from the lower one.
            s = np.concatenate([hi[live], lo[live]])
            foot = np.concatenate([lo_v[live], hi_v[live]])
            raised &= ~partly | (_lift(xyz, seg, n_seg, s, foot) >= min_lift)
        if not raised.any():
            break
        gone |= raised
    return gone[seg]


def _over_walls(
    xyz: NDArray[np.float64],
    e: NDArray[np.int64],
    dz: NDArray[np.float64],
    run: NDArray[np.float64],
    med: float,
    is_step: NDArray[np.bool_],
    wall: NDArray[np.bool_],
    step: float,
    points: NDArray[np.float64],
) -> NDArray[np.int64]:
    """Edges (indices into ``e``) gentler than a step, rising ``step`` or more to a vertex
    that tops a wall (the upper end of a step that is a wall), no longer than
    ``_RAMP_RUNS`` median edges, over whose middle at least ``_RAMP_MIN`` returns lie,
    some at the foot's level and some at the top's, and fewer than ``_RAMP_SHARE`` of them
    between: a wall crossed on a diagonal (``raised_segments``' ``over_walls``)."""
    walled = is_step & wall
    top = np.zeros(xyz.shape[0], dtype=bool)
    top[np.where(dz[walled] > 0, e[walled, 1], e[walled, 0])] = True
    upper = np.where(dz > 0, e[:, 1], e[:, 0])
    cand = np.flatnonzero(~is_step & (np.abs(dz) >= step) & top[upper] & (run <= _RAMP_RUNS * med))
    if cand.size == 0:
        return cand
    lower = np.where(dz[cand] > 0, e[cand, 0], e[cand, 1])
    on, mid = _on_ramp(points, xyz[lower], xyz[upper[cand]], both=True)
    return cand[(mid >= _RAMP_MIN) & (on < _RAMP_SHARE * mid)]


def _on_ramp(
    points: NDArray[np.float64],
    foot: NDArray[np.float64],
    top: NDArray[np.float64],
    both: bool = False,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per step (ends ``foot`` → ``top``, (k, 3)): the points of ``points`` over the middle of
    its run (in plan 20–80 % along it, within half the run of its line), and how many of them
    lie on the straight ramp between its ends (within 25 % of the rise of the ramp's height
    there). Fractions of the step's own run and rise: a graded side carries returns at
    intermediate heights, a wall's foot and top are level up to it. With ``both``: how many
    of them stand between the ends' heights (in the middle half of the rise) instead of
    how many on the ramp, and the count over the middle is 0 for a step without a return
    at its foot's level (the lowest quarter of the rise or under) and one at its top's
    (the highest quarter or over): a wall crossed on a diagonal has both and none between;
    a bank or a slope crossed so has returns on its face, between."""
    k = foot.shape[0]
    if k == 0 or points.shape[0] == 0:
        return np.zeros(k), np.zeros(k)
    d = top[:, :2] - foot[:, :2]
    run = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    rise = top[:, 2] - foot[:, 2]
    centre = 0.5 * (foot[:, :2] + top[:, :2])
    # Cells no narrower than the widest disc, at most _RAMP_CELLS of them over the discs' box.
    lo = (centre - 0.5 * run[:, None]).min(axis=0) - 1e-3
    extent = (centre + 0.5 * run[:, None]).max(axis=0) + 1e-3 - lo
    cell = max(float(run.max()), float(np.sqrt(extent[0] * extent[1] / _RAMP_CELLS)))
    nx, ny = (np.floor(extent / cell).astype(np.int64) + 1).tolist()
    counts = _ramp_counts(
        np.ascontiguousarray(points, dtype=np.float64),
        np.ascontiguousarray(foot, dtype=np.float64),
        d,
        run,
        rise,
        centre,
        float(lo[0]),
        float(lo[1]),
        cell,
        nx,
        ny,
    ).astype(np.float64)
    mid, on = counts[:, 0], counts[:, 1]
    if not both:
        return on, mid
    return counts[:, 4], mid * ((counts[:, 2] > 0) & (counts[:, 3] > 0))


def data_border(
    xy: NDArray[np.float64],
    tri: Delaunay,
    cut: tuple[float, float, float, float],
    tol: float,
) -> NDArray[np.int64]:
    """Edges (k, 2) of the hull of ``tri`` that are the edge of the data: all of them
    but those with both ends within ``tol`` of one side of the ``cut`` box."""
    h = np.asarray(tri.convex_hull, dtype=np.int64)
    x0, y0, x1, y1 = cut
    ends = [xy[h[:, 0]], xy[h[:, 1]]]
    along = np.zeros(h.shape[0], dtype=bool)
    for axis, side in ((0, x0), (1, y0), (0, x1), (1, y1)):
        along |= (np.abs(ends[0][:, axis] - side) <= tol) & (np.abs(ends[1][:, axis] - side) <= tol)
    return h[~along]


def _hull_distance(
    xy: NDArray[np.float64],
    tri: Delaunay,
    idx: NDArray[np.int64],
    border: NDArray[np.int64] | None = None,
) -> NDArray[np.float64]:
    """Distance of the vertices ``idx`` of ``tri`` (vertex positions ``xy``) to its hull's
    border, or to the hull edges ``border`` (a part of it; inf when there are none)."""
    h = np.asarray(tri.convex_hull if border is None else border, dtype=np.int64)
    a, b = xy[h[:, 0]], xy[h[:, 1]]
    xy = xy[idx]
    d = b - a
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)
    length2 = length**2
    out = np.full(xy.shape[0], np.inf)
    for k in range(h.shape[0]):  # hull edges are few; points many
        u, v = xy[:, 0] - a[k, 0], xy[:, 1] - a[k, 1]
        if border is None:
            # Inside a convex hull, the distance to the nearest line through an
            # edge is the distance to the border.
            np.minimum(out, np.abs(u * d[k, 1] - v * d[k, 0]) / length[k], out=out)
        else:
            # Part of the border: distance to the edges themselves, not their lines.
            t = np.clip((u * d[k, 0] + v * d[k, 1]) / length2[k], 0.0, 1.0)
            np.minimum(out, np.hypot(u - t * d[k, 0], v - t * d[k, 1]), out=out)
    return out


def _along_edge(
    xy: NDArray[np.float64],
    tri: Delaunay,
    seg: NDArray[np.int64],
    n_seg: int,
    near: float,
    border: NDArray[np.int64] | None = None,
) -> NDArray[np.float64]:
    """Per segment: the diagonal of the bounding box of its vertices within ``near``
    of the hull's border (or of its edges ``border``; 0 for a segment with none or one)."""
    idx = np.flatnonzero(_hull_distance(xy, tri, np.arange(xy.shape[0]), border) <= near)
    s, p = seg[idx], xy[idx]
    lo = np.full((n_seg, 2), np.inf)
    hi = np.full((n_seg, 2), -np.inf)
    np.minimum.at(lo, s, p)
    np.maximum.at(hi, s, p)
    span = np.hypot(*(hi - lo).T)
    return np.where(np.isfinite(span), span, 0.0)


def _graded_at_edge(
    xyz: NDArray[np.float64],
    tri: Delaunay,
    seg: NDArray[np.int64],
    n_seg: int,
    med: float,
    border: NDArray[np.int64] | None,
    e: NDArray[np.int64],
    hi: NDArray[np.int64],
    lo_v: NDArray[np.int64],
    hi_v: NDArray[np.int64],
    step: float,
    graded: float,
) -> NDArray[np.bool_]:
    """Per segment: it reaches the edge of the data and at least ``graded`` of the steps
    down from it (upper segment ``hi``, ends ``lo_v`` → ``hi_v``) land on ground that goes
    on falling away from it: a TIN edge from the step's foot, pointing away from the
    step, dropping ``step`` or more at half the step's gradient or more. That is the
    sloped side of an embankment the edge of the data cuts, which the TIN descends in
    low steps; a platform's or a roof's wall stands on a level foot, or on a hillside
    much gentler than the wall."""
    n_step = np.bincount(hi, minlength=n_seg)
    if hi.size == 0:
        return np.zeros(n_seg, dtype=bool)
    on = _falls_on(xyz, e, lo_v, hi_v, step)
    share = np.bincount(hi, on, n_seg) / np.maximum(n_step, 1)
    touches = _along_edge(xyz[:, :2], tri, seg, n_seg, med, border) > 0
    return touches & (n_step > 0) & (share >= graded)


def _falls_on(
    xyz: NDArray[np.float64],
    e: NDArray[np.int64],
    lo_v: NDArray[np.int64],
    hi_v: NDArray[np.int64],
    step: float,
) -> NDArray[np.bool_]:
    """Per step (ends ``lo_v`` → ``hi_v``): a TIN edge (of ``e``) from its foot, pointing
    away from the step, drops ``step`` or more at half the step's gradient or more: the
    ground goes on falling beyond it (a graded side, not a wall on a level foot)."""
    # The TIN's edges from each step's foot (each edge once in both directions).
    a = np.concatenate([e[:, 0], e[:, 1]])
    order = np.argsort(a, kind="stable")
    a, b = a[order], np.concatenate([e[:, 1], e[:, 0]])[order]
    start = np.searchsorted(a, lo_v)
    count = np.searchsorted(a, lo_v, side="right") - start
    k = np.repeat(np.arange(lo_v.size), count)
    w = b[np.repeat(start, count) + np.arange(k.size) - np.repeat(np.cumsum(count) - count, count)]
    out = xyz[lo_v, :2] - xyz[hi_v, :2]
    grad_step = (xyz[hi_v, 2] - xyz[lo_v, 2]) / np.maximum(np.hypot(*out.T), 1e-9)
    nxt = xyz[w, :2] - xyz[lo_v[k], :2]
    fall = xyz[lo_v[k], 2] - xyz[w, 2]
    falls = (
        (np.einsum("ij,ij->i", out[k], nxt) > 0)
        & (fall >= step)
        & (fall >= 0.5 * grad_step[k] * np.hypot(*nxt.T))
    )
    on = np.zeros(lo_v.size, dtype=bool)
    on[k[falls]] = True
    return on


def _walled_falls(
    xyz: NDArray[np.float64],
    e: NDArray[np.int64],
    dz: NDArray[np.float64],
    run: NDArray[np.float64],
    med: float,
    joins: NDArray[np.bool_],
    is_step: NDArray[np.bool_],
    wall: NDArray[np.bool_],
    step: float,
    steep: float,
    walls: float,
    share: float,
    graded: float,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Joining edges across holes (indices into ``e``) that fall from a walled flat patch
    by at least ``share`` of the median height of its walls, and per such edge whether
    its upper end is ``e[:, 1]``; see ``raised_segments``' ``walled``.

    Patches: the TIN cut along steps and along every edge at least ``_ALONG_RUNS``
    median edges long. A patch is walled when it is not the largest, its vertices lie
    within ``step`` RMS of their plane and that plane is gentler than a wall (``steep``,
    rise/run: a piece of an embankment's side is not a platform's top), it is the upper
    side of every short step on its border, at least ``walls`` of those are walls
    (``wall``) and, with ``graded`` > 0, fewer than ``graded`` of them land on ground
    that falls on beyond them (``_falls_on``: an embankment's crest above its graded
    side, not a platform's top)."""
    n = xyz.shape[0]
    short = run < _ALONG_RUNS * med
    far = np.flatnonzero(joins & ~short)
    none = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool)
    if far.size == 0:
        return none
    near = e[joins & short]
    graph = coo_matrix((np.ones(near.shape[0]), (near[:, 0], near[:, 1])), shape=(n, n))
    n_seg, seg = connected_components(graph, directed=False)
    st = np.flatnonzero(is_step & short)
    st = st[seg[e[st, 0]] != seg[e[st, 1]]]
    up = dz[st] > 0
    hi = seg[np.where(up, e[st, 1], e[st, 0])]
    lo = seg[np.where(up, e[st, 0], e[st, 1])]
    n_up = np.bincount(hi, minlength=n_seg)
    n_wall = np.bincount(hi[wall[st]], minlength=n_seg)
    n_down = np.bincount(lo, minlength=n_seg)
    ok = (n_up > 0) & (n_down == 0) & (n_wall >= walls * n_up)
    ok[np.argmax(np.bincount(seg, minlength=n_seg))] = False
    if graded > 0 and ok.any():
        mine = ok[hi]
        lo_v = np.where(up, e[st, 0], e[st, 1])[mine]
        hi_v = np.where(up, e[st, 1], e[st, 0])[mine]
        on = _falls_on(xyz, e, lo_v, hi_v, step)
        ok &= np.bincount(hi[mine], on, n_seg) < graded * np.maximum(n_up, 1)
    if not ok.any():
        return none
    ok &= _flat(xyz, seg, n_seg, step, steep)
    # The walls' height per patch: the median drop of the steps down from it.
    height = _median_per_vertex(hi, np.abs(dz[st]), n_seg)
    s0, s1 = seg[e[far, 0]], seg[e[far, 1]]
    drop1 = ok[s1] & (s0 != s1) & (dz[far] >= share * height[s1])
    drop0 = ok[s0] & (s0 != s1) & (-dz[far] >= share * height[s0])
    pick = drop1 | drop0
    return far[pick], drop1[pick]


def _flat(
    xyz: NDArray[np.float64],
    seg: NDArray[np.int64],
    n_seg: int,
    tol: float,
    steep: float = np.inf,
) -> NDArray[np.bool_]:
    """Per segment: its vertices lie within ``tol`` RMS of their least-squares plane,
    gentler than ``steep`` (rise/run; segments of fewer than four vertices count as flat)."""
    size = np.maximum(np.bincount(seg, minlength=n_seg), 1)
    cx = np.bincount(seg, xyz[:, 0], n_seg) / size
    cy = np.bincount(seg, xyz[:, 1], n_seg) / size
    u, v, z = xyz[:, 0] - cx[seg], xyz[:, 1] - cy[seg], xyz[:, 2]
    coef, cnt = _plane_per_group(seg, u, v, z, n_seg, 4)
    res = z - coef[seg, 0] - coef[seg, 1] * u - coef[seg, 2] * v
    rms = np.sqrt(np.bincount(seg, res**2, n_seg) / size)
    return (cnt < 4) | ((rms <= tol) & (np.hypot(coef[:, 1], coef[:, 2]) < steep))


def _even_walls(
    hi: NDArray[np.int64],
    own: NDArray[np.bool_],
    height: NDArray[np.float64],
    n_seg: int,
    tol: float,
    share: float,
) -> NDArray[np.bool_]:
    """Per segment: of the steps up onto it (upper segment ``hi``, heights ``height``), at
    least ``share`` are its own walls (``own``) and their heights' median absolute deviation,
    scaled to a standard deviation (x 1.4826), is at most ``tol``: it stands at one height
    above its foot all round."""
    n_up = np.bincount(hi, minlength=n_seg)
    s, h = hi[own], height[own]
    n_own = np.bincount(s, minlength=n_seg)
    mid = _median_per_vertex(s, h, n_seg)
    mad = _median_per_vertex(s, np.abs(h - mid[s]), n_seg)
    return (n_own > 0) & (n_own >= share * n_up) & (1.4826 * mad <= tol)


def _plane_per_group(
    group: NDArray[np.int64],
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    z: NDArray[np.float64],
    n: int,
    least: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Least-squares plane z = c0 + c1 u + c2 v of each of ``n`` groups of points
    (``group`` per point) and the points per group; the mean level where a group
    has fewer than ``least`` points or they do not span a plane."""

    def b(a: NDArray[np.float64]) -> NDArray:
        return np.bincount(group, a, n)

    cnt, su, sv, suu, svv, suv = b(np.ones_like(u)), b(u), b(v), b(u * u), b(v * v), b(u * v)
    m = np.stack(
        [np.stack([cnt, su, sv], -1), np.stack([su, suu, suv], -1), np.stack([sv, suv, svv], -1)],
        -2,
    )
    r = np.stack([b(z), b(u * z), b(v * z)], -1)
    coef = np.zeros((n, 3))
    coef[:, 0] = r[:, 0] / np.maximum(cnt, 1)
    ok = (cnt >= least) & (np.linalg.det(m) > 1e-6 * cnt * (suu + svv) ** 2)
    if ok.any():
        coef[ok] = np.linalg.solve(m[ok], r[ok][..., None])[..., 0]
    return coef, cnt


def _excess(
    xyz: NDArray[np.float64],
    heights: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    pairs: NDArray[np.int64],
    fallback: NDArray[np.float64],
    steepest: float = np.inf,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """How far each end of the edges ``pairs`` (k, 2) stands above the height the terrain
    behind the other end predicts for it: (end 1 seen from end 0, end 0 seen from end 1).

    The terrain behind an end is the TIN sampled on the line through the edge, beyond
    that end, at ``_BEHIND`` times the edge's run; the median of the slopes from those
    samples to the end, continued over the run, is the prediction. The baseline is the
    edge's own run, so a platform met across a hole tens of metres wide is judged by
    the terrain's slope over as many metres, not by two neighbours half a metre away
    (whose 1 cm rounding alone is a 2 % slope). Where no sample lies inside the TIN,
    or the terrain behind is steeper than ``steepest`` (rise/run: steep slopes bend
    within such a run, and extrapolated they move labels with where the bins fall),
    the other end is predicted to rise by ``fallback`` (a gradient per vertex) times the run."""
    a, b = xyz[pairs[:, 0]], xyz[pairs[:, 1]]
    d = b[:, :2] - a[:, :2]
    out = []
    run = np.hypot(d[:, 0], d[:, 1])
    for end, foot, top, sign in ((0, a, b, 1.0), (1, b, a, -1.0)):
        rises = np.sort(
            [(foot[:, 2] - heights(foot[:, :2] - sign * t * d)) / t for t in _BEHIND],
            axis=0,
        )  # nan (outside the TIN) sort last
        k = np.isfinite(rises).sum(axis=0)
        lo = rises[np.maximum(k - 1, 0) // 2, np.arange(k.size)]
        hi = rises[np.maximum(k, 1) // 2, np.arange(k.size)]
        pred = (lo + np.where(k % 2 == 1, lo, hi)) / 2
        # Steep terrain bends within such a run: extrapolated, its slope predicts nothing.
        ok = (k > 0) & (np.abs(pred) <= steepest * run)
        pred = np.where(ok, pred, fallback[pairs[:, end]] * run)
        out.append(top[:, 2] - foot[:, 2] - pred)
    return out[0], out[1]


def _heights_of(
    xyz: NDArray[np.float64], tri: Delaunay
) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
    """Heights of the TIN ``tri`` (a scipy ``Delaunay``; vertex heights ``xyz[:, 2]``) at
    points (k, 2), linear in each triangle; nan outside it."""

    def at(p: NDArray[np.float64]) -> NDArray[np.float64]:
        s = tri.find_simplex(p)
        inside = s >= 0
        out = np.full(p.shape[0], np.nan)
        t = tri.transform[s[inside]]
        bc = np.einsum("kij,kj->ki", t[:, :2], p[inside] - t[:, 2])
        w = np.column_stack([bc, 1.0 - bc.sum(axis=1)])
        out[inside] = (w * xyz[tri.simplices[s[inside]], 2]).sum(axis=1)
        return out

    return at


def _median_per_vertex(
    v: NDArray[np.int64], value: NDArray[np.float64], n: int
) -> NDArray[np.float64]:
    """Median (lower middle) of ``value`` per vertex id ``v`` (0 where a vertex has none)."""
    return _lower_medians(
        np.asarray(v, dtype=np.int64), np.asarray(value, dtype=np.float64), int(n)
    )


def _lift(
    xyz: NDArray[np.float64],
    seg: NDArray[np.int64],
    n_seg: int,
    s: NDArray[np.int64],
    foot: NDArray[np.int64],
) -> NDArray[np.float64]:
    """Mean height of each segment's vertices above the least-squares plane through
    the feet of its steps (pairs ``s``: segment, ``foot``: vertex beyond a step);
    a level plane where the feet do not span one."""
    n = xyz.shape[0]
    key = np.unique(s.astype(np.int64) * n + foot)  # each foot once per segment
    ss, vv = key // n, key % n
    size = np.maximum(np.bincount(seg, minlength=n_seg), 1)
    cx = np.bincount(seg, xyz[:, 0], n_seg) / size
    cy = np.bincount(seg, xyz[:, 1], n_seg) / size
    u, v, z = xyz[vv, 0] - cx[ss], xyz[vv, 1] - cy[ss], xyz[vv, 2]
    coef, _ = _plane_per_group(ss, u, v, z, n_seg, 3)
    plane = (
        coef[seg, 0] + coef[seg, 1] * (xyz[:, 0] - cx[seg]) + coef[seg, 2] * (xyz[:, 1] - cy[seg])
    )
    return np.bincount(seg, xyz[:, 2] - plane, n_seg) / size
