"""Ground determination as NIST does it (Witzgall, Cheok, Gilsinn; DESIGN §5.1).

Four procedures, combined by the schedule of the paper's §6.1:

- select/reject on a grid: a bin is rejected when it holds fewer than
  ``min_points``, when the RMS of its elevations exceeds ``z_tol``, or when a
  mask point falls in it; the lowest point of each accepted bin is a ground
  candidate (``select_reject``);
- masking: a partial TIN built by largest-deviation insertion, stopped at
  ``mask_fraction`` of the points; vertices of its triangles whose edges are all
  shorter than ``mask_edge`` block bins (``masking.py``);
- meshing and screening: Delaunay TIN through the candidates; vertices more
  than ``screen_tol`` above the median of their neighbours are deleted, until
  none is (``tin.screen``); the mowed point file is screened likewise with
  ``screen_points_tol``;
- mowing: points more than a tolerance above the current surface are dropped.

Recipe (§6.1): mask → bin (cell_1) → mesh/screen → mow (mow_tol_1)
→ screen the mowed points → mask them → bin (cell_2) → mesh/screen → mow the
original points (mow_tol_2) → bin (cell_3) → mesh/screen, then ``repeats``
more rounds of mow → bin (cell_3) → mesh/screen; both masking steps are off
by default (``mask``, measured on airborne data). Then two steps of our own:
raised segments of that TIN (roofs wider than every pass's bins, also those
cut into a slope) are dropped (``raised.py``), and the surface is grown back
onto terrain the coarse passes cut off — ridges, embankments, hilltops — but
not onto the dropped roofs (``growth.py``); a level group of grown nodes that
drops onto the terrain by walls all round is a low flat object and goes, and so
does an island of segments (a pitched roof cut into rows) standing on walls
above the terrain all round (``plateaus.py``). Final labels: ground
is every point from ``ground_tol_below`` under to ``ground_tol`` over the last
surface, both widened by ``ground_slope`` × the local TIN slope (as SMRF does)
and on sparse data in proportion to cell_3 (``ground_tol_cell``),
and every point above that band with two of its nearest ground points at or
above its own height (``support.py``: crests the TIN still cuts).

Where this departs from the paper, and why (measured on ISPRS and synthetic
scenes): screening tolerances grow with a pass's bin size; with plane bins,
neighbours vote with heights extrapolated along their planes, no steeper than
``screen_slope_cap`` (a bin astride a wall is not a slope); vertices far
below their neighbours (low outliers) are screened too; mowing tolerances
grow with slope × bin size, since a TIN one bin apart cuts convex breaks;
"screen the mowed file" uses 3 × 3 cells of lowest points as neighbours
instead of a TIN of millions of points; masking inserts from the lowest and
highest point per ``mask_pool_cell``.

On sparse data (final bins of a couple of points) everything from pass 3 on
runs over four phases of the final grid and a point is ground when two of them
say so (``vote_phases``): which lowest point a bin holds, and whether growth
finds a path onto a crest, otherwise moves with where the bins fall.

§7 extensions: ``bin_fit="plane"`` judges RMS and the lowest point relative
to a least-squares plane per bin, so steep bare bins are not taken for
vegetation; ``grid="concentric"`` bins a ground-based scan in rings around the
sensor.

Cell sizes follow the point density when left at 0 (auto): with the mean point
spacing s = 1/sqrt(points per m²), cell_1 = max(10 s, 6 m), cell_2 =
max(4 s, 3 m), cell_3 = max(1.5 s, 1.5 m), mask_edge = 2.5 s. At 1 pt/m² (ISPRS)
this gives 10, 4, 1.5 m; at 8 pts/m² 6, 3, 1.5 m. The floors keep bins wider
than a tree crown's gap-free core and the last TIN coarse enough to stay fast.
For ground-based scans (``sensor_origin``) the concentric grid's angular step
``ring_step_deg`` plays the cell's part (earlier passes scale it by the cell
ratios); the auto ``mask_edge`` (2.5 spacings) serves there as well as the
paper's 10 cm (README *Measured*, choices of ``ground.nist``).

Example::

    from terrasift.workers.ground.nist import NistParams, classify_ground
    ground = classify_ground(xyz, NistParams.preset("default", bin_fit="level"))
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.spatial import QhullError, cKDTree

from terrasift.workers.bins import (
    ANCHOR,
    BinStats,
    Grid,
    PlaneStats,
    anchored_origin,
    bin_statistics,
    cell_order,
    lowest_per_bin,
    plane_fit_statistics,
    snap_cell,
)
from terrasift.workers.ground.closefit import close_fit_high
from terrasift.workers.ground.concentric import ConcentricGrid
from terrasift.workers.ground.growth import grow_ground
from terrasift.workers.ground.halfdisc import half_disc_vegetation
from terrasift.workers.ground.masking import extremes_per_cell, mask_points
from terrasift.workers.ground.nodes import square_lowest
from terrasift.workers.ground.plateaus import walled_islands, walled_plateaus
from terrasift.workers.ground.raised import raised_segments
from terrasift.workers.ground.roughedge import edge_high
from terrasift.workers.ground.roughness import rough_points
from terrasift.workers.ground.support import supported_points
from terrasift.workers.ground.tin import ABOVE, IN_BAND, Tin, screen
from terrasift.workers.registry import StageParams, register

#: why a bin was not accepted
ACCEPTED, EMPTY, OCCUPANCY, RMS, MASK = 0, 1, 2, 3, 4

_AUTO_CELLS = ((10.0, 6.0), (4.0, 3.0), (1.5, 1.5))  # (× spacing, floor in m) per pass
_GROW_TOL_PER_CELL = 0.12  # auto growth tolerance per metre of final cell (ISPRS samples)


class NistParams(StageParams):
    """Parameters of ``ground.nist``; lengths in metres, 0 means derived from point density."""

    density: float = Field(0.0, ge=0, le=1e6)
    """Points per m² the density-derived sizes (cells, masking, support radius) follow (0:
    measured on each block's occupied area). Given, every block of a tile bins and masks
    alike even where their own densities differ (strip overlaps, voids)."""
    grid: Literal["auto", "regular", "concentric"] = "auto"
    """Binning grid; ``auto`` is concentric when a sensor origin is given, else regular."""
    bin_fit: Literal["level", "plane"] = "plane"
    """Judge bin RMS and lowest point about the bin mean (``level``) or a least-squares plane."""
    cell_1: float = Field(0.0, ge=0, le=500)
    """Bin size of the first select/reject pass (0: max(10 s, 6 m))."""
    cell_2: float = Field(0.0, ge=0, le=500)
    """Bin size of the second pass (0: max(4 s, 3 m))."""
    cell_3: float = Field(0.0, ge=0, le=500)
    """Bin size of the third, final pass (0: max(1.5 s, 1.5 m))."""
    bin_phases: int = Field(1, ge=1, le=4)
    """Regular grids are laid this many times per axis, offset by 1/k of a bin each way
    (k² grids); every grid's accepted lowest points are candidates, and the growth nodes
    are the lowest points of every final-pass grid. 1: one grid. More grids make the
    candidates depend less on where the bins fall (translations, block cuts)."""
    vote_phases: int = Field(0, ge=0, le=4)
    """Pass 3, raised segments, growth and labels run over k² phases of the final grid
    (offset by 1/k of a bin along x and y); a point is ground when at least half of them
    say so. On sparse data each final bin holds a couple of points, so which one is its
    lowest, and whether growth finds a path onto a crest, is luck of where the bins fall
    (a translation of a few metres moved ISPRS kappas by up to 6 points). 0: auto, k = 2
    where final bins hold fewer than ``vote_points`` points on average, else 1 (one grid;
    the vote costs about three times the stage time)."""
    vote_share: float = Field(0.5, gt=0, le=1)
    """A point is ground when phases holding at least this share of the vote say so."""
    vote_weight: Literal["equal", "centre"] = "equal"
    """Each phase's say in the vote: ``equal``, or ``centre``: by how central the point
    lies in that phase's final bin (a tent per axis; with two phases per axis the
    weights are those of bilinear interpolation between the phases)."""
    grow_share: float = Field(0.0, ge=0, le=1)
    """With the final vote over several phases, a point that growth (and the supported
    points of the grown surface) adds to a phase's labels is ground when phases holding at
    least this share of the vote add it (0: off, such points are voted like the rest).
    Whether growth finds a path onto a crest is one event per phase, which the phases'
    majority turns into luck of where the bins fall."""
    final_nodes: Literal["bins", "square"] = "bins"
    """Nodes of every pass and of growth: the lowest point of each bin (``bins``), or on
    sparse data (where the final vote would run) every point lowest in the pass's cell-sized
    square centred on it (``square``, ``nodes.py``): chosen by the data, not by where the
    bins fall, so labels do not move with the tile's origin and one run replaces the vote.
    Off: it loses kappa on three ISPRS samples (samp52 a hillside as a raised segment;
    README *Measured*)."""
    mow_share: float = Field(0.0, ge=0, le=1)
    """Passes 1 and 2 vote too when the final pass does (0: off, one grid each): each pass
    is run over the final vote's phases of its own grid, and a point survives its mowing
    when the surfaces of phases holding at least this share of them keep it."""
    vote_points: float = Field(4.0, ge=0, le=1000)
    """Mean points per final bin below which the auto ``vote_phases`` votes (4: up to about
    1.8 points per m² with 1.5 m bins; the ISPRS samples hold 2.25)."""
    bin_anchor: Literal["absolute", "data"] = "data"
    """Where the bins of every pass are laid: ``absolute``, on multiples of the cell in the
    data's coordinates (``bins.anchored_origin``), so that tiles and jobs bin alike where
    they meet; ``data``, with a bin corner at the centre of the data's bounding box (or at
    ``anchor`` when given): the bins move with the data and a translated tile labels alike
    point for point, where a translation of a few metres moves sparse ISPRS kappas by up to
    5 points. Labels still depend on the bin phase, which follows the data's extent (or the
    job's anchor): samp61 84.0–89.9 over bin phases; the platform of railway seed 97 that
    passed as ground at this phase is held by ``raised_over_walls`` (README *Measured*)."""
    anchor: tuple[float, float] | None = None
    """With ``bin_anchor="data"``: the x, y a bin corner of every block sits at (a job gives
    the centre of its inputs' bounds, so that its blocks bin alike); None: the centre of the
    bounding box of the points the stage is given."""
    snap_cells: bool = True
    """Bin sizes derived from the density (cells, masking pool) snap to the nearest divisor of
    240 m (``bins.snap_cell``, steps of 4–33 %): blocks of one tile whose densities differ a
    little then bin alike, on bins anchored on the same absolute multiples."""
    min_points: int = Field(1, ge=1, le=1000)
    """Minimum bin occupancy; the paper also accepts single occupancy."""
    z_tol: float = Field(3.0, gt=0, le=100)
    """RMS of elevations (about the mean or the plane) above which a bin is rejected."""
    mask: bool = False
    """Run TIN masking before the first and second select/reject, and screen the mowed points
    before the second (the paper's recipe). Off by
    default: on airborne data it masks the walls of low flat objects, so the bins beside a
    platform go and its top passes as ground, and the partial TIN, stopped at a share of a
    block's points, makes labels depend on where a tile is cut into blocks; without it the
    ISPRS samples and the synthetic scans score alike (README *Measured*)."""
    mask_fraction: float = Field(0.12, gt=0, le=0.5)
    """Share of the (pooled) points the partial TIN takes in; the paper uses 10–15 %."""
    mask_edge: float = Field(0.0, ge=0, le=100)
    """Partial-TIN triangles with every edge shorter than this are mask triangles (0: 2.5 s)."""
    mask_rule: Literal["deviation", "area"] = "deviation"
    """Insertion order: largest deviation, or deviation × triangle area."""
    mask_pool_cell: float = Field(0.0, ge=0, le=100)
    """Masking inserts from the lowest and highest point of each such cell (0: max(2 s, 1 m))."""
    screen_tol: float = Field(0.75, gt=0, le=100)
    """A TIN vertex more than this above the median of its neighbours is deleted (grows with
    each pass's bin size). Low enough that the second pass deletes the edge of a deck 1–3 m
    above the ground beside it (README *Measured*, choices of ``ground.nist``)."""
    screen_points_tol: float = Field(1.0, gt=0, le=100)
    """Screening of the mowed point file (pass 2): a point more than this above the median of
    its neighbours' lowest points is dropped. Apart from ``screen_tol``: these neighbours are
    single low points of small cells, not bin minima, and at ``screen_tol`` they strip the
    rough tops of cut crests and slopes."""
    screen_slope_cap: float = Field(1.5, ge=0, le=10)
    """Screening with plane bins: neighbours' votes follow their bin planes up to this gradient
    (rise/run, 1.5 ≈ 56°, above the 35–45° of steep terrain; 0: uncapped). Steeper planes fit bins
    astride walls and deck edges."""
    screen_rim: float = Field(4.0, ge=0, le=100)
    """Screening: a TIN edge longer than this many of the pass's bins with both ends within
    one bin of the outline of the pass's candidates (a sliver along the data's edge) casts no
    vote (0: every edge votes). Such slivers joined plateau vertices at a tile's edge to terrain
    26–112 m away along it (6 m bins), which voted them down one after the other, so a plateau
    crossing the tile no longer reached its edge and went as a raised segment."""
    screen_low_tol: float = Field(1.0, ge=0, le=100)
    """A vertex more than this below its second-lowest neighbour is a low outlier (0: off)."""
    mow_tol_1: float = Field(3.0, gt=0, le=100)
    """First mowing: drop points this far above the first surface."""
    mow_tol_2: float = Field(0.3, gt=0, le=100)
    """Second mowing, of the original points, against the second surface."""
    mow_slope: float = Field(0.5, ge=0, le=10)
    """Mowing tolerance grows by this × local surface slope × the pass's bin size."""
    slope_cap: float = Field(1.0, ge=0, le=10)
    """Slope allowances (mowing, labels) use min(facet slope, slope_cap): facets
    steeper than that span walls or crown edges, not terrain, and an uncapped
    allowance there lets mowing keep roofs and the surface climb."""
    repeats: int = Field(1, ge=0, le=10)
    """Extra mow (mow_tol_2) → bin (cell_3) → mesh/screen rounds against the last surface."""
    ground_tol: float = Field(0.3, gt=0, le=10)
    """Final labels: ground within this height of the final surface."""
    ground_tol_cell: float = Field(0.15, ge=0, le=1)
    """Final labels: ``ground_tol`` is at least this × the final cell size, and ``ground_tol_below``
    grows in proportion: on sparse data a fixed band misses ground between coarse nodes."""
    ground_tol_below: float = Field(0.5, gt=0, le=10)
    """Final labels: ground down to this depth below the final surface."""
    ground_slope: float = Field(1.0, ge=0, le=10)
    """Extra tolerance per unit of local TIN slope (rise/run), for steep terrain."""
    raised_step: float = Field(0.3, ge=0, le=100)
    """Drop segments of the final TIN that stand above the rest behind steps this high (0: off; ``raised.py``).
    Low, so roofs 1–5 m high whose border the TIN climbs in several smaller steps go too."""
    raised_slope: float = Field(10.0, gt=0, lt=90)
    """Degrees: a TIN edge rising ``raised_step`` or more at a steeper angle than this is a step…"""
    raised_relative: bool = False
    """…steeper than the terrain at its foot by that much (its gradient less the median gradient
    of the TIN edges going down from its lower end; off: than level). On, plain slope edges of
    steep terrain stop being steps, but roofs on built-up slopes stay, so it is off."""
    raised_walls: float = Field(0.5, ge=0, le=1)
    """A raised segment is dropped only when at least this share of the steps it is the upper
    side of are walls measured against the terrain at their foot (``raised_relative``'s test,
    taken over the whole border; 0: off). Roofs and platforms are walled nearly all round; a
    hilltop that slope edges cut off at some bin phases is not."""
    raised_rise: float = Field(0.3, ge=0, le=100)
    """An edge of the final TIN, gentler than ``raised_slope``, that rises this many metres more
    than the slope at its foot predicts over its run is a step and a wall (0: off; 0.3 m, as
    ``raised_step``). A platform about a metre high whose neighbours (wagons, cars) left a hole
    in the TIN meets the ground several metres away at a gentle angle."""
    raised_along: bool = True
    """``raised_rise`` judged across holes by the terrain behind each end of an edge, over
    the edge's own run (``raised.py``); off: by the size of the slope at its foot times the
    run, which a 1 cm rounding of the coordinates flips (railway seed 104: Type II 0.4 or
    22.9 %) and which cannot see a platform level with ground rising away from it (208)."""
    raised_graded: float = Field(0.5, ge=0, le=1)
    """A raised segment that reaches the edge of the data is kept when at least this share of
    its steps down land on ground that goes on falling away beyond them (0: off; ``raised.py``):
    a road embankment the edge cuts, whose sloped sides the TIN descends in low steps; a
    platform's wall stands on level ground (railway seed 413: an embankment's crest reaching
    the edge along 10–16 m, under ``raised_edge``, went as a platform)."""
    raised_walled: float = Field(0.5, ge=0, le=10)
    """An edge of the final TIN across a hole that falls from a walled flat patch (cut off
    from the rest by steps and holes, level within ``raised_step`` RMS on a plane gentler
    than ``raised_slope``, the upper side of every step on its border, ``raised_walls`` of
    them walls, fewer than ``raised_graded`` of them on ground falling on beyond) by at
    least this share of the median height of the patch's walls is a step and a wall (0:
    off; ``raised.py``): a platform whose neighbours left holes around it meets the ground
    beyond them at a gentle grade that the terrain behind may predict (railway seed 618:
    37 m edges, ground bending from 3.4 to 1.5 % of grade), but its own walls say how high
    it stands."""
    raised_even: bool = True
    """A segment above a ``raised_rise`` edge counts as flat (so it may go) also when its own
    walls, ``raised_walls`` of its steps up, stand at one height: their median absolute
    deviation as a standard deviation at most ``raised_step`` (``raised.py``). Off: only
    within ``raised_step`` RMS of its plane, which a platform 110–140 m long following
    ground that bends under it leaves (railway seed 721: 0.31–0.36 m RMS, walls 1.13 m
    ± 0.08); a hillside cut off by long edges has walls metres apart in height."""
    raised_sides: float = Field(0.5, ge=0, le=1)
    """A raised segment is kept when at least this share of its steps up onto it carry a
    return of the block on the ramp between their ends (0: off; ``raised.py``): an embankment's
    1:1–1:2 sides hold returns at intermediate heights, a wall of a roof or platform does not."""
    raised_over_walls: bool = True
    """An edge of the final TIN gentler than a step, rising ``raised_step`` or more to the top
    of a wall, is a step and a wall when the returns over its middle stand at its foot's
    level and at its top's and hardly any between (``raised.py``): it crosses the wall on a
    diagonal, and that one edge joined a 0.8 m platform to the terrain at some bin phases
    (railway seed 97 moved by (0, 0.5) m: Type II 0.5 → 20 %). A bank or slope crossed so
    carries returns on its face and still joins."""
    raised_rim: float = Field(4.0, ge=0, le=100)
    """Final-TIN edges longer than this many median edges with both ends within one median
    edge of the hull's border (slivers along the edge of the data) join no segments (0: off;
    ``raised.py``): a platform reaching the tile's edge was joined by them to ground 30–80 m
    away along it."""
    raised_edge: float = Field(20.0, ge=0, le=1000)
    """A walled segment whose vertices within one median edge of the hull's border span at
    least this many metres is kept: it reaches the edge of the data further than the end of a
    roof or platform does (railway family: platforms 4–8 m, sheds 8–15 m wide, spans 3–8 m
    measured), as a plateau crossing the data does (steep family: 39–195 m). 0: kept when it
    holds a vertex of the hull, which a 1 cm rounding of the coordinates decides (``raised.py``)."""
    raised_islands: bool = True
    """Also drop islands of raised segments: the segments other than the terrain's taken
    together where they touch, when every edge from an island to the terrain is a step up
    onto it (``raised_walls`` of them walls) and it does not reach the data's edge along
    ``raised_edge``: a pitched roof is cut into rows of segments, none raised on its own
    (``plateaus.py``)."""
    raised_share: float = Field(0.7, ge=0.5, le=1)
    """A segment that is the upper side of at least this share of its steps is raised too, when
    it also stands ``raised_lift`` above the plane through the feet of its steps (a roof cut
    into a slope is the lower side only along its uphill wall; 1: only wholly raised segments)."""
    raised_lift: float = Field(1.5, ge=0, le=100)
    """…metres. Terrace treads and benches between walls sit near that plane; a roof stands
    higher, though less than its walls, as the hill behind it lifts the plane."""
    grow: bool = True
    """Grow the final surface onto terrain the coarse passes cut off (``growth.py``)."""
    grow_tol: float = Field(0.0, ge=0, le=10)
    """Growth: a node joins when a ground neighbour's slope predicts its height within this…
    (0: 0.12 × the final cell size, 0.18 m at 1 pt/m², 0.41 m at 0.17 pts/m²)"""
    grow_bend: float = Field(5.0, ge=0, le=45)
    """…plus tan(this many degrees) × their distance: how fast the slope may bend."""
    grow_down: float = Field(2.0, ge=1, le=10)
    """Growth: a node lower than predicted may miss by this many times the tolerance (objects
    stand above terrain, so going down climbs onto nothing; 2 carries growth over crests)."""
    grow_bend_down: float = Field(15.0, ge=0, le=60)
    """Growth: …and its slope may bend by tan(this many degrees) × distance (at least ``grow_bend``):
    over a crest the slope turns from rising to falling within one edge, more so between nodes
    further apart (a dike crest between sparse nodes)."""
    grow_rise: float = Field(3.0, gt=0, le=100)
    """Growth never climbs an edge rising more than this (metres)."""
    grow_peak: float = Field(1.0, ge=0, le=100)
    """Growth: a grown node standing more than this × the growth tolerance above all its
    ground neighbours is an object beside a slope, not terrain, and is dropped (until none is)."""
    grow_peak_area: float = Field(20.0, ge=0, le=1000)
    """…and so is a group of grown nodes level with each other (within that height) covering
    at most this many m² (nodes × final cell²; at least one node): a car, a shed, a bush;
    larger, and crest nodes of sparse data go too."""
    grow_agree: float = Field(0.0, ge=0, le=1)
    """Growth: a node joins only when at least this share of its ground neighbours predict it
    (0: any one). A slope fitted from two close neighbours predicts an object's top at a wall
    (``growth.py``); 0.5 keeps growth off platforms in rail yards but costs the ISPRS samples
    (README *Measured*), so it is off by default."""
    grow_peaks: bool = True
    """…switch for those rules."""
    grow_low: bool = True
    """Growth: a grown node more than ``screen_low_tol`` below the second-lowest of its
    ground neighbours is a low outlier and is dropped, as screening drops such vertices
    (a deep return is its bin's lowest point; growth reached one 4.4 m deep along a long
    edge at the edge of the data, where the allowed bend is metres, at some bin phases;
    ISPRS kappas within 0.07 of it off, README *Measured*)."""
    grow_reach: float = Field(0.0, ge=0, le=100)
    """Growth reaches a node only along a path of at most this many first-pass cells from the
    final surface's ground (0: no limit). The halo is ``halo_cells`` of those cells, so with
    a reach inside it a block grows its core as a run over the whole tile does."""
    grow_phases: int = Field(1, ge=1, le=4)
    """Growth runs over this many phases per axis of the final bins within each voted final
    phase (offsets of 1/(this × vote phases) of a bin; sparse data only, where the final
    passes vote), and a point's vote from that phase is the share of them that label it.
    Whether growth climbs a crest or a hillside segment hinges on which lowest points its
    nodes are; more phases average that over where the bin edges fall (1: one growth)."""
    halo_cells: float = Field(4.0, ge=1, le=20)
    """A block's halo in first-pass cells (``halo``). A core point's coarse bin and the bins
    whose candidates screen it and mesh over it lie within 2.5; growth reaches further (ISPRS
    samp61: a dike crest along a path leaving a 2.5-cell halo; with 4 cells 2 × 2 blocks
    agree with one run on 99.99 % of its labels, README *Measured*)."""
    plateau_step: float = Field(0.5, ge=0, le=100)
    """After growth, a level group of grown nodes that stands above all its ground neighbours
    and drops this many metres or more straight onto the passes' own ground along most of its
    edge (``plateau_share``) is a low flat object growth climbed onto (a platform, a row of
    wagons, a shed), and goes (0: off; ``plateaus.py``). Half the lowest platform (0.8 m)."""
    plateau_share: float = Field(0.9, gt=0, le=1)
    """…share of the group's edges to ground outside it that must be such drops (and at most
    the rest may reach ground as high as the group: a node on a wall, a wagon beside it).
    1 left a platform of railway seed 53 (0.5 pts/m²) that one noisy edge held; 0.8–0.95 alike
    on the ISPRS samples (README *Measured*)."""
    support_k: int = Field(8, ge=0, le=64)
    """Supported points (``support.py``): a point joins the ground when at least two of its
    ``support_k`` nearest ground points stand as high or higher (0: off)."""
    support_radius: float = Field(3.0, gt=0, le=20)
    """…counting only ground points within this many mean point spacings."""
    support_tol: float = Field(0.0, ge=0, le=2)
    """…and allowing the point to stand this many metres above the second highest of them."""
    support_rounds: int = Field(2, ge=1, le=10)
    """…repeated this many times, so supported points support others."""
    ring_step_deg: float = Field(3.0, gt=0.1, le=45)
    """Concentric grid: angular step of the final pass (earlier passes scale it up)."""
    ring_inner: float = Field(2.0, gt=0, le=100)
    """Concentric grid: inner radius; closer points share the central bin."""
    rough_k: int = Field(48, ge=0, le=128)
    """Low vegetation on sparse data (``roughness.py``): a ground point is taken back when it
    stands above the plane of its ``rough_k`` nearest ground points by more than
    ``rough_factor`` times their deviation below it (0: off). Runs where final bins hold
    fewer than ``rough_points`` points on average: there the ground band is widened with
    the cell and the slope, and shrub returns 0.25–1 m high pass it."""
    rough_factor: float = Field(5.0, gt=0, le=20)
    """…deviations (of the neighbours below the plane: noise and curvature, the data's own;
    never less than the median deviation of those neighbours, so rough ground is held to its
    own roughness and a block labels as the whole tile does)."""
    rough_clip: float = Field(2.0, gt=0, le=10)
    """…the plane refitted without neighbours more than this many deviations above it."""
    rough_floor: float = Field(0.05, ge=0, le=5)
    """…and never less than this many metres (LAS quantisation, perfectly smooth ground)."""
    rough_envelope: bool = False
    """…the plane started from the neighbours' lower envelope (the lowest of each of 8
    angular sectors, then refitted to those within ``rough_clip`` deviations above it;
    ``envelope.py``), so that scrub among them does not lift it (off: the least-squares
    plane clipped from above)."""
    rough_shrub: float = Field(0.0, ge=0, le=5)
    """Isolated-shrub test (metres; 0: off): a ground point is also taken back when it
    stands this much above the lower-envelope plane of its ``rough_k`` neighbours and, in
    each of ``rough_sectors`` angular sectors, one of its ``rough_near`` nearest neighbours
    there lies under half its height (a crest or an embankment's edge has neighbours as
    high along its length); held to no deviation, so it acts near breaks too."""
    rough_sectors: int = Field(4, ge=3, le=16)
    """…sectors of the isolated-shrub test."""
    rough_near: int = Field(3, ge=1, le=16)
    """…nearest neighbours per sector it looks at."""
    rough_half: int = Field(12, ge=0, le=64)
    """Half-disc test (``halfdisc.py``; 0: off): after the roughness test, a ground point
    is also taken back when it stands above every well-fitting plane of its ``rough_half``
    nearest sure ground points (all of them, and each half-disc of them) by more than
    ``max(rough_half_floor, rough_half_factor`` × its deviation or the roughness around); near a slope
    break one half lies on the point's own facet and fits it with the ground's noise. Real
    ground that bends within a few metres stands as high: held to a quadratic too
    (``rough_half_curve``; without it ISPRS kappa falls 2–22 points, README *Measured*)."""
    rough_half_rounds: int = Field(5, ge=1, le=20)
    """…the sure ground: the ground left by the roughness test, cleaned this many times
    less one by the same test held to half the factor and floor."""
    rough_half_factor: float = Field(4.0, gt=0, le=20)
    """…deviations of the plane above which a point is vegetation."""
    rough_half_floor: float = Field(0.1, ge=0, le=5)
    """…and never less than this many metres."""
    rough_half_curve: int = Field(30, ge=0, le=64)
    """…and (when > 6; 0: off) also above the quadratic surface of its this many nearest
    sure ground points (refitted once without those high above it) by more than
    ``rough_half_curve_factor`` × that surface's deviation: mounds, rounded crests and
    field banks stand above planes, not above a quadratic; in the cleaning too, at half."""
    rough_half_curve_factor: float = Field(5.0, gt=0, le=20)
    """…deviations of the quadratic above which a point is vegetation."""
    rough_half_curve_near: int = Field(12, ge=0, le=64)
    """…and (when > 6 with ``rough_half_curve``; 0: off) a point that quadratic kept still
    goes when it stands above the quadratic of its this many nearest sure ground points by
    more than ``rough_half_curve_near_factor`` × that surface's deviation: the wider
    quadratic cannot follow mounds and waves a few metres across (final judgement only)."""
    rough_half_curve_near_factor: float = Field(10.0, gt=0, le=40)
    """…deviations of that nearer quadratic above which a point is vegetation."""
    rough_fit: int = Field(12, ge=0, le=64)
    """After the half-disc test (sparse data only; 0: off): a point goes when it stands
    above the quadratic of its ``rough_fit`` nearest sure ground points by more than
    max(``rough_fit_floor``, 3 × the ground noise, the robust deviation of the sure
    points' heights within 15 m in the last round: the same however the job is cut), the
    sure ground re-estimated over 3 rounds, and at most
    ``rough_fit_ceiling`` (``closefit.py``: also held to ``rough_fit_local`` × the
    deviation around it, to its three nearest sure points and to the wider quadratic)."""
    rough_fit_floor: float = Field(0.15, ge=0, le=5)
    """Metres: the least height above the close surface that takes a point."""
    rough_fit_ceiling: float = Field(1.0, ge=0, le=100)
    """Metres: the most; above it the close surface overshoots (steep breaks). 1 m: on
    the rural family 0.8 m left 17–31 returns of tall shrubs per tile between 0.8 and
    1 m over it against 0–5 ground points (seen seeds 960–971)."""
    rough_fit_local: float = Field(4.0, gt=0, le=20)
    """…and more than this many times the robust deviation of the heights of its 24
    nearest sure points (6 before: on the rural family that deviation is 0.07–0.1 m
    beside low scrub, twice the tile's noise, and 0.25–0.4 m returns passed; README
    *Measured* for what 4 costs the ISPRS samples)."""
    rough_fit_step_plane: bool = False
    """…and above its three nearest sure points carried to it along their local plane,
    not in raw height (on 15–40 % slopes the uphill neighbour hides a low return). Off:
    on the rural family it takes more (seen seeds 960–971, stage: Type II worst 10.30 →
    8.69 %) but costs samp61 0.88 kappa, 0.7 under moves (README *Measured*)."""
    rough_fit_step_slope: float = Field(1.5, ge=0, le=100)
    """…and (> 0, with ``rough_fit_step_plane`` off) carried so only where their plane's
    gradient is at most this many times the tile's median gradient of such planes: a
    tile-wide 15–40 % slope is carried, a dike or bank flank steeper than its tile is not
    (0: raw heights everywhere). 1.5: the vegetation the plane step takes on the seen
    steep rural tiles (seeds 940–971) stands on planes 0.5–1.6 × its tile's median
    gradient for most of it, the ISPRS ground it takes on planes 1.1–9 × (samp61 mostly
    2–5 ×); at 2 samp61 moved by (0, 5) m falls to 86.0 (README *Measured*)."""
    rough_fit_clip_noise: float = Field(2.0, ge=0, le=20)
    """…the close surfaces after the first round refitted without the neighbours more than
    2 × min(their deviation, this many × the tile's ground noise) above the first fit (0:
    their deviation alone). Beside low scrub a third of a point's dozen sure neighbours
    may be returns 0.15–0.3 m up; they widen the deviation, stay in the refit and lift
    the surface by 0.1–0.3 m (seen rural seeds 960–971, 940–951)."""
    rough_edge: float = Field(2.0, ge=0, le=20)
    """After the close fit (sparse data only; 0: off): a ground point goes when it stands
    over every ground neighbour of ``rough_edge_sectors`` of the four quadrants around it
    (neighbours within ``rough_edge_reach`` local ground spacings, carried to it along the
    plane of its ``rough_edge_k`` nearest) by more than this many times the block's 95th
    percentile of the ground's absolute residuals about such planes (and at least
    ``rough_edge_floor``), where the local
    ground density is at least ``rough_edge_density`` and that plane no steeper than
    ``rough_edge_slope`` (``roughedge.py``): a shrub return has ground below it on most
    sides, a crest has ground as high along it."""
    rough_edge_sectors: int = Field(3, ge=1, le=4)
    """…quadrants in which it must stand over every neighbour."""
    rough_edge_k: int = Field(16, ge=4, le=64)
    """…nearest ground points giving the plane and the local density."""
    rough_edge_reach: float = Field(2.0, gt=0, le=10)
    """…local ground spacings (1 / sqrt(density)) within which neighbours are compared."""
    rough_edge_density: float = Field(0.2, ge=0, le=1000)
    """…ground points per m² (``rough_edge_k`` over the disc holding them) below which the
    test does not act. Measured over 0.2–0.97 (the rural family's ground) and on the
    ISPRS samples (0.13–0.7): below 0.2, on samp61 (0.16–0.18), neighbours up to 5 m
    away are carried over bends and the test took ground (−0.12 kappa ungated)."""
    rough_edge_slope: float = Field(0.7, ge=0, le=10)
    """…gradient (rise / run) of that plane above which it does not act: without it the
    ISPRS ground the test took stands on planes of gradient 0.38–1.69 (10th–90th
    percentile), the rural family's vegetation on 0.12–0.61 (terrain up to 0.4)."""
    rough_edge_floor: float = Field(0.25, ge=0, le=5)
    """…metres: the least height over them that takes a point. The rural family's shrub
    returns stand 0.25–0.6 m over the ground; on railway yards' flat ground (residuals'
    95th percentile 0.05 m) the test took ground standing 0.10–0.20 m over its neighbours
    (seeds 608, 610)."""
    rough_points: float = Field(4.0, ge=0, le=1000)
    """Mean points per final bin below which the roughness test runs (4: up to about 1.8
    points per m² with 1.5 m bins; dense data keep a narrow band and are left alone)."""

    presets = {
        "conservative": {
            "screen_tol": 0.5,
            "screen_points_tol": 0.5,
            "mow_tol_2": 0.2,
            "ground_tol": 0.2,
            "z_tol": 1.0,
        },
        "aggressive": {
            "screen_tol": 2.0,
            "screen_points_tol": 2.0,
            "mow_tol_2": 0.5,
            "ground_tol": 0.5,
            "z_tol": 5.0,
        },
    }

    def halo(self, density: float) -> float:
        """``halo_cells`` first-pass cells: the bins that screen and mesh over a core
        point, and growth's paths onto it, lie within that."""
        spacing = 1.0 / np.sqrt(max(density, 1e-9))
        factor, floor = _AUTO_CELLS[0]
        return self.halo_cells * (self.cell_1 or _auto(self, max(factor * spacing, floor)))


@dataclass(frozen=True)
class SelectReject:
    """Outcome of one select/reject pass over a grid.

    ``stats`` are the plain per-bin elevation statistics (n, lowest point,
    mean, max, RMS about the mean) the vegetation stage uses; ``plane`` is set
    when bins were judged about planes. ``reason`` is ACCEPTED, EMPTY,
    OCCUPANCY, RMS or MASK per bin; ``candidates`` index the input points.
    """

    grid: Grid | ConcentricGrid
    stats: BinStats
    plane: PlaneStats | None
    accepted: NDArray[np.bool_]
    reason: NDArray[np.uint8]
    candidates: NDArray[np.int64]


def point_spacing(xy: NDArray[np.float64]) -> float:
    """Mean point spacing 1/sqrt(density), density over the occupied area only."""
    n = xy.shape[0]
    if n < 2:
        return 1.0
    span = np.array([np.ptp(xy[:, 0]), np.ptp(xy[:, 1])])  # per column: fast on (n, 2) rows
    area = max(float(span[0] * span[1]), 1e-6)
    for _ in range(2):  # refine: the second pass sizes cells from the first density
        c = max(np.sqrt(4.0 * area / n), 1e-3)
        g = Grid.covering(xy[:, 0], xy[:, 1], c)
        occupied = np.count_nonzero(np.bincount(g.index(xy[:, 0], xy[:, 1]), minlength=g.size))
        area = occupied * c * c
    return float(np.sqrt(area / n))


def select_reject(
    xyz: NDArray[np.float64],
    params: NistParams,
    grid: Grid | ConcentricGrid,
    *,
    mask_xy: NDArray[np.float64] | None = None,
) -> SelectReject:
    """Select/reject over ``grid`` (NIST §3.1): accepted bins give their lowest point.

    Mask points block bins; without ``mask_xy`` they are computed from ``xyz``
    when ``params.mask`` is on (pass an empty array to skip masking).
    """
    flat = grid.index(xyz[:, 0], xyz[:, 1])
    stats = bin_statistics(xyz, grid, flat)
    if mask_xy is None:
        mask_xy = _mask(xyz, params, point_spacing(xyz[:, :2])) if params.mask else np.zeros((0, 2))
    rms, lowest = stats.rms, stats.lowest
    plane = None
    if params.bin_fit == "plane":
        plane = plane_fit_statistics(xyz, grid, flat)
        fitted = np.isfinite(plane.rms)
        rms = np.where(fitted, plane.rms, rms)
        lowest = np.where(fitted, plane.lowest, lowest)
    reason = np.full(grid.size, ACCEPTED, dtype=np.uint8)
    with np.errstate(invalid="ignore"):
        reason[rms > params.z_tol] = RMS
    if mask_xy.shape[0]:
        blocked = grid.index(mask_xy[:, 0], mask_xy[:, 1])
        blocked = blocked[blocked >= 0]
        reason[blocked] = np.where(reason[blocked] == ACCEPTED, MASK, reason[blocked])
    reason[stats.n < params.min_points] = OCCUPANCY
    reason[stats.n == 0] = EMPTY
    accepted = (reason == ACCEPTED) & (lowest >= 0)
    return SelectReject(grid, stats, plane, accepted, reason, lowest[accepted])


def _auto(params: NistParams, cell: float) -> float:
    """A bin size derived from the point spacing, snapped when ``snap_cells`` is on."""
    return snap_cell(cell) if params.snap_cells else cell


def _mask(xyz: NDArray[np.float64], params: NistParams, spacing: float) -> NDArray[np.float64]:
    pool_cell = params.mask_pool_cell or _auto(params, max(2.0 * spacing, 1.0))
    edge = params.mask_edge or 2.5 * spacing
    pool = extremes_per_cell(xyz, pool_cell)
    return xyz[
        pool[mask_points(np.take(xyz, pool, axis=0), params.mask_fraction, edge, params.mask_rule)],
        :2,
    ]


def _screen_points(
    xyz: NDArray[np.float64], params: NistParams, spacing: float
) -> NDArray[np.int64]:
    """Screening of a point file (§6.1 "screen the mowed file"), in grid form.

    A full TIN of millions of mowed points costs more than the whole stage;
    the neighbours of a point are taken instead as the lowest points of the
    3 × 3 pool cells around it: a point more than ``screen_points_tol`` above
    their median is dropped.
    """
    cell = params.mask_pool_cell or _auto(params, max(2.0 * spacing, 1.0))
    g = Grid.covering(xyz[:, 0], xyz[:, 1], cell)
    flat = g.index(xyz[:, 0], xyz[:, 1])
    zmin = np.full(g.size, np.inf)
    np.minimum.at(zmin, flat, xyz[:, 2])
    raster = zmin.reshape(g.ny, g.nx)
    filled = np.where(np.isfinite(raster), raster, np.nan)
    stack = np.full((9, g.ny + 2, g.nx + 2), np.nan)
    padded = np.pad(filled, 1, constant_values=np.nan)
    for k, (dy, dx) in enumerate(np.ndindex(3, 3)):
        stack[k, 1:-1, 1:-1] = padded[dy : dy + g.ny, dx : dx + g.nx]
    med = _nanmedian_first_axis(stack[:, 1:-1, 1:-1].reshape(9, -1))
    return np.flatnonzero(~(xyz[:, 2] - med[flat] > params.screen_points_tol))


def _nanmedian_first_axis(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """``np.nanmedian(a, axis=0)`` (NaN where a column is all NaN) by one sort
    along the axis, NaN sorting last: several times faster than nanmedian's masked arrays."""
    s = np.sort(a, axis=0)
    cnt = np.count_nonzero(~np.isnan(s), axis=0)
    cols = np.arange(s.shape[1])
    lo = s[np.maximum(cnt - 1, 0) // 2, cols]
    hi = s[np.minimum(cnt // 2, s.shape[0] - 1), cols]
    return np.where(cnt % 2 == 1, lo, (lo + hi) / 2)


def _grids(
    xyz: NDArray[np.float64], params: NistParams, spacing: float, origin: NDArray[np.float64] | None
) -> list[Grid | ConcentricGrid]:
    fixed = (params.cell_1, params.cell_2, params.cell_3)
    cells = [
        c or _auto(params, max(f * spacing, floor))
        for c, (f, floor) in zip(fixed, _AUTO_CELLS, strict=True)
    ]
    concentric = params.grid == "concentric" or (params.grid == "auto" and origin is not None)
    if not concentric:
        return [Grid.covering(xyz[:, 0], xyz[:, 1], c) for c in cells]
    if origin is None:
        raise ValueError('grid="concentric" needs a sensor origin')
    r = np.hypot(xyz[:, 0] - origin[0], xyz[:, 1] - origin[1])
    r_outer = float(r.max()) * (1 + 1e-9) + 1e-6
    r_inner = min(params.ring_inner, 0.5 * r_outer)
    return [
        ConcentricGrid.build(
            origin[0], origin[1], r_inner, r_outer, params.ring_step_deg * c / cells[2]
        )
        for c in cells
    ]


def _surface(
    xyz: NDArray[np.float64],
    srs: SelectReject | list[SelectReject],
    params: NistParams,
    origin_xy: NDArray,
    scale: float = 1.0,
) -> Tin:
    """Mesh the candidates of ``srs`` (one pass, or the same pass over several grid
    phases: their candidates pooled, each once) and screen them until stable
    (tolerance × ``scale``)."""
    srs = srs if isinstance(srs, list) else [srs]
    idx = np.concatenate([sr.candidates for sr in srs])
    idx, first = np.unique(idx, return_index=True)
    cand = xyz[idx]
    if cand.shape[0] < 3:
        raise _TooSparse
    slopes = None
    if srs[0].plane is not None:
        grads = []
        for sr in srs:
            assert sr.plane is not None
            c = xyz[sr.candidates]
            b = sr.grid.index(c[:, 0], c[:, 1])
            grads.append(np.column_stack([sr.plane.sx[b], sr.plane.sy[b]]))
        slopes = _vote_slopes(np.concatenate(grads)[first], params.screen_slope_cap)
    return _screened(cand, slopes, params, scale, _cell_of(srs[0].grid), origin_xy)


def _screened(
    cand: NDArray[np.float64],
    slopes: NDArray[np.float64] | None,
    params: NistParams,
    scale: float,
    cell: float,
    origin_xy: NDArray,
) -> Tin:
    """Screen the mesh of ``cand`` until stable (tolerances × ``scale``, rims in
    ``cell`` units); every candidate when fewer than three would stay."""
    keep, tin = screen(
        cand,
        params.screen_tol * scale,
        params.screen_low_tol * scale,
        slopes=slopes,
        rim_len=params.screen_rim * cell,
        rim_band=cell,
    )
    if tin is not None:
        return tin
    if keep.size < 3:
        keep = np.arange(cand.shape[0])
    return Tin(cand[keep], origin=origin_xy)


def _vote_slopes(slopes: NDArray[np.float64], cap: float) -> NDArray[np.float64]:
    """Bin-plane gradients for screening votes, steeper ones scaled down to ``cap`` (0: as they are).

    A bin astride a wall or a deck's edge fits a plane far steeper than
    terrain; extrapolated one bin along it, its vote lifts the deck or roof
    vertex beside it above any tolerance. Scaled, not dropped, so the vote
    still leans the way the slope goes.
    """
    slopes = np.nan_to_num(slopes)
    if cap <= 0:
        return slopes
    g = np.hypot(slopes[:, 0], slopes[:, 1])
    return slopes * (np.minimum(g, cap) / np.maximum(g, 1e-12))[:, None]


class _TooSparse(Exception):
    """Fewer than three ground candidates: no surface can be meshed."""


def _cell_of(g: Grid | ConcentricGrid) -> float:
    return float(np.median(g.cell)) if isinstance(g, ConcentricGrid) else g.cell


def _mow(
    tin: Tin, xyz: NDArray[np.float64], tol: float, cell: float, params: NistParams
) -> NDArray[np.int64]:
    """Indices of the points that survive mowing against ``tin``.

    The tolerance is ``tol`` plus ``mow_slope`` × facet slope × bin size: a
    TIN through vertices one bin apart cuts convex slope breaks by up to the
    slope change times half the spacing, and steep facets flag where that happens
    (slope capped at ``slope_cap``).
    """
    code = tin.band(xyz, tol, np.inf, params.mow_slope * cell, params.slope_cap)
    return np.flatnonzero(code == IN_BAND)


@register(
    "ground.nist",
    NistParams,
    "NIST select/reject, TIN masking, meshing, screening, mowing",
    role="ground",
)
def classify_ground(
    xyz: NDArray[np.float64],
    params: NistParams,
    *,
    sensor_origin: NDArray[np.float64] | None = None,
    window: tuple[float, float, float, float] | None = None,
) -> NDArray[np.bool_]:
    """Ground mask of the (n, 3) block ``xyz`` (core + halo) by the §6.1 schedule.

    ``window`` (xmin, ymin, xmax, ymax): the box the block's points were cut to
    (its core and halo) from data that may go on beyond it. Where the data
    reaches a side of the box it was cut there, so the rules for the edge of
    the data (``raised_edge``) hold only along the rest of its outline; None:
    the points are all the data there is.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    n = xyz.shape[0]
    if n < 4:
        return np.ones(n, dtype=bool)
    try:
        return _classify(xyz, params, sensor_origin, window)
    except (_TooSparse, QhullError):
        # A sliver of a block at the edge of the data: too few (or only
        # collinear) bins pass select/reject to mesh anything, so nothing is
        # called ground.
        return np.zeros(n, dtype=bool)


def _classify(
    xyz: NDArray[np.float64],
    params: NistParams,
    sensor_origin: NDArray[np.float64] | None,
    window: tuple[float, float, float, float] | None = None,
) -> NDArray[np.bool_]:
    n = xyz.shape[0]
    # Work in local coordinates: projected x, y of 5e5/5e6 m cost precision.
    # Anchored origin: bins line up between neighbouring blocks.
    shift = _origin(xyz, params)
    # Spatial order (8 m cells, row-major) keeps every later gather — bins,
    # triangles, walks — in cache; file order is often random.
    order = cell_order(xyz[:, 0] - shift[0], xyz[:, 1] - shift[1], 8.0)
    # np.take: several times faster than fancy indexing of rows (here and below), same values.
    local = np.take(xyz[:, :3], order, axis=0)
    local[:, :2] -= shift
    if params.bin_anchor == "data":
        # To the micrometre (below any LAS scale): the local coordinates of a translated
        # tile then come out bit for bit alike, and so do ties between equal distances.
        local[:, :2] = np.round(local[:, :2], 6)
    origin = (
        None if sensor_origin is None else np.asarray(sensor_origin, dtype=np.float64)[:2] - shift
    )
    spacing = 1.0 / np.sqrt(params.density) if params.density > 0 else point_spacing(local[:, :2])
    g1, g2, g3 = _grids(local, params, spacing, origin)
    k = params.bin_phases if isinstance(g3, Grid) else 1
    # Screening tolerances grow with the bin size of a pass: with vertices
    # further apart, smooth terrain departs further from neighbour votes.
    scales = [_cell_of(g) / _cell_of(g3) for g in (g1, g2)]
    centre = local[:, :2].mean(axis=0)
    none = np.zeros((0, 2))

    # Pass 3 onwards runs once per final grid phase (``vote_phases``); with
    # ``mow_share`` passes 1 and 2 vote over as many phases of their own grids.
    votes_k = params.vote_phases or (2 if (_cell_of(g3) / spacing) ** 2 < params.vote_points else 1)
    mow_k = votes_k if params.mow_share > 0 else 1

    # Pass 1: mask, bin, mesh/screen; mow the original points.
    mask1 = _mask(local, params, spacing) if params.mask else none
    square = (
        params.final_nodes == "square" and isinstance(g3, Grid) and votes_k > 1 and not params.mask
    )
    if square:
        # Pass 2's surface is meshed on what pass 1 left; both mow the original points.
        kept = local
        for grid, tol, scale in (
            (g1, params.mow_tol_1, scales[0]),
            (g2, params.mow_tol_2, scales[1]),
        ):
            cell = _cell_of(grid)
            mowed = _mow(
                _square_surface(kept, cell, params, centre, scale), local, tol, cell, params
            )
            kept = np.take(local, mowed, axis=0)
    else:
        mowed = _passes_1_2(local, params, spacing, g1, g2, k, mow_k, centre, scales, mask1)

    # A point is ground when at least ``vote_share`` of the final phases label it so.
    finals = [g3] if square or not isinstance(g3, Grid) else _phased(g3, votes_k)
    reach = params.grow_reach * _cell_of(g1)
    votes, grown, weights = np.zeros(n), np.zeros(n), np.zeros(n)
    for g in finals:
        w = _vote_weights(local, g, params, len(finals))
        phase, added = _final(
            local,
            mowed,
            g,
            k,
            params,
            centre,
            spacing,
            _local_cut(window, shift),
            reach,
            square,
            grow_sub=params.grow_phases if len(finals) > 1 else 1,
            grow_step=params.grow_phases * votes_k,
        )
        if len(finals) == 1:
            break  # one grid: its labels are the vote (any vote_share > 0 keeps them)
        votes += w * phase
        grown += w * added
        weights += w
    labels = votes >= params.vote_share * weights if len(finals) > 1 else phase >= 0.5
    if params.grow_share > 0 and len(finals) > 1:
        labels |= grown >= params.grow_share * weights
    labels &= ~_rough(local, labels, params, _cell_of(g3) / spacing)
    ground = np.empty(n, dtype=bool)
    ground[order] = labels
    return ground


_ANCHOR_BACKOFF = 1e-6  # m: data anchors sit this far below the data's minimum (see _origin)


def _origin(xyz: NDArray[np.float64], params: NistParams) -> NDArray[np.float64]:
    """Local origin, where every pass's bins start (``bin_anchor``). A data anchor is
    moved by whole ``ANCHOR``s (a multiple of every snapped cell) to at or below the
    data, and backed off by 1 µm: far above the rounding of projected coordinates
    (~1e-10 m) and below any LAS scale in use (≥ 0.1 mm), so points on bin edges of a
    quantised tile fall in the same bin however the tile is translated."""
    if params.bin_anchor == "absolute":
        return anchored_origin(xyz)
    lo = np.array([xyz[:, 0].min(), xyz[:, 1].min()])
    if params.anchor is not None:
        a = np.asarray(params.anchor, dtype=np.float64)
    else:
        a = (lo + np.array([xyz[:, 0].max(), xyz[:, 1].max()])) / 2
    return a - np.ceil((a - lo) / ANCHOR) * ANCHOR - _ANCHOR_BACKOFF


def _passes_1_2(
    local: NDArray[np.float64],
    params: NistParams,
    spacing: float,
    g1: Grid | ConcentricGrid,
    g2: Grid | ConcentricGrid,
    k: int,
    mow_k: int,
    centre: NDArray,
    scales: list[float],
    mask1: NDArray[np.float64],
) -> NDArray[np.int64]:
    """Indices of ``local`` that survive passes 1 and 2 over the bins of ``g1`` and ``g2``
    (``k`` bin phases; ``mow_k`` voting phases of each pass)."""
    mowed = _voted_mow(
        local,
        local,
        [
            [select_reject(local, params, g, mask_xy=mask1) for g in _phased(p, k)]
            for p in _phased(g1, mow_k)
        ],
        params,
        centre,
        scales[0],
        params.mow_tol_1,
        _cell_of(g1),
    )

    # Pass 2: screen the mowed points, mask them, bin, mesh/screen; mow the originals again.
    mowed_pts = np.take(local, mowed, axis=0)
    mask2 = np.zeros((0, 2))
    if params.mask:
        mowed_pts = mowed_pts[_screen_points(mowed_pts, params, spacing)]
        mask2 = _mask(mowed_pts, params, spacing)
    mowed = _voted_mow(
        local,
        mowed_pts,
        [
            [select_reject(mowed_pts, params, g, mask_xy=mask2) for g in _phased(p, k)]
            for p in _phased(g2, mow_k)
        ],
        params,
        centre,
        scales[1],
        params.mow_tol_2,
        _cell_of(g2),
    )

    return mowed


def _voted_mow(
    local: NDArray[np.float64],
    pts: NDArray[np.float64],
    phases: list[list[SelectReject]],
    params: NistParams,
    centre: NDArray,
    scale: float,
    tol: float,
    cell: float,
) -> NDArray[np.int64]:
    """Indices of ``local`` that survive mowing against the surfaces meshed from each
    entry of ``phases`` (select/reject over ``pts``, which are ``local``'s points or a
    subset): kept by at least ``mow_share`` of them, or by the one surface."""
    if len(phases) == 1:
        return _mow(_surface(pts, phases[0], params, centre, scale), local, tol, cell, params)
    kept = np.zeros(local.shape[0])
    for srs in phases:
        kept[_mow(_surface(pts, srs, params, centre, scale), local, tol, cell, params)] += 1
    return np.flatnonzero(kept >= params.mow_share * len(phases))


def _rough(
    local: NDArray[np.float64], labels: NDArray[np.bool_], params: NistParams, per_side: float
) -> NDArray[np.bool_]:
    """Ground points standing above their neighbours' plane by more than its roughness
    (``roughness.py``), on sparse data only (``per_side``: final cell / point spacing)."""
    if params.rough_k == 0 or per_side**2 >= params.rough_points:
        return np.zeros(labels.shape[0], dtype=bool)
    high = rough_points(
        local,
        labels,
        params.rough_k,
        params.rough_factor,
        params.rough_clip,
        params.rough_floor,
        envelope=params.rough_envelope,
        shrub=params.rough_shrub,
        sectors=params.rough_sectors,
        nearest=params.rough_near,
    )
    if params.rough_half > 0:
        high |= half_disc_vegetation(
            local,
            labels & ~high,
            params.rough_half,
            params.rough_half_rounds,
            params.rough_half_factor,
            params.rough_half_floor,
            params.rough_half_curve,
            params.rough_half_curve_factor,
            params.rough_half_curve_near,
            params.rough_half_curve_near_factor,
        )
    if params.rough_fit > 0:
        high |= close_fit_high(
            local,
            labels & ~high,
            params.rough_fit,
            floor=params.rough_fit_floor,
            ceiling=params.rough_fit_ceiling,
            local=params.rough_fit_local,
            step_plane=params.rough_fit_step_plane,
            clip_noise=params.rough_fit_clip_noise,
            step_slope=params.rough_fit_step_slope,
        )
    if params.rough_edge > 0:
        high |= edge_high(
            local,
            labels & ~high,
            k=params.rough_edge_k,
            need=params.rough_edge_sectors,
            factor=params.rough_edge,
            reach=params.rough_edge_reach,
            density=params.rough_edge_density,
            max_slope=params.rough_edge_slope,
            floor=params.rough_edge_floor,
        )
    return high


def _final(
    local: NDArray[np.float64],
    mowed: NDArray[np.int64],
    g3: Grid | ConcentricGrid,
    k: int,
    params: NistParams,
    centre: NDArray,
    spacing: float,
    cut: tuple[float, float, float, float] | None = None,
    reach: float = 0.0,
    square: bool = False,
    grow_sub: int = 1,
    grow_step: int = 1,
) -> tuple[NDArray[np.bool_] | NDArray[np.float64], NDArray[np.bool_] | NDArray[np.float64]]:
    """Labels of ``local`` from pass 3 over ``g3`` on the twice-mowed points ``mowed``:
    final surface, raised segments, growth, band and supported points (``cut``: the
    block's window in local coordinates, see ``classify_ground``; ``reach``: growth's
    path limit in metres, 0 none); and the labelled points outside the band of the
    surface before growth (what growth and the supported points added). With
    ``grow_sub`` > 1 growth runs over ``grow_sub``² phases of ``g3`` (offsets of
    1/``grow_step`` of a bin) and the labels are the share of them labelling a point
    (and what growth added, the share of them adding it)."""
    # Pass 3: bin the twice-mowed points, mesh/screen: the final surface.
    mowed_pts = np.take(local, mowed, axis=0)
    tin3 = _final_surface(mowed_pts, g3, k, params, centre, square)
    # Repeats of mow → bin → mesh/screen at the final cell size let the
    # surface climb back onto convex breaks that the coarser passes cut.
    for _ in range(params.repeats):
        mowed_pts = np.take(
            local, _mow(tin3, local, params.mow_tol_2, _cell_of(g3), params), axis=0
        )
        tin3 = _final_surface(mowed_pts, g3, k, params, centre, square)
    raised = None
    if params.raised_step > 0:
        tin3, raised = _without_raised(tin3, params, cut, local)
    # The final TIN departs further from rough terrain between vertices that
    # are further apart: on sparse data the label tolerances grow with the cell.
    widen = max(1.0, params.ground_tol_cell * _cell_of(g3) / params.ground_tol)
    params = params.model_copy(
        update={
            "ground_tol": widen * params.ground_tol,
            "ground_tol_below": widen * params.ground_tol_below,
        }
    )
    before = None
    if params.grow:
        if params.grow_share > 0:
            before = _band(tin3, local, params)[0]
        if grow_sub > 1 and isinstance(g3, Grid) and not square:
            c = g3.cell / grow_step
            share = np.zeros(local.shape[0])
            for j in range(grow_sub):
                for i in range(grow_sub):
                    g = Grid(g3.x0 - i * c, g3.y0 - j * c, g3.cell, g3.nx + 1, g3.ny + 1)
                    tin = _grown(local, tin3, _phased(g, k), params, centre, raised, reach)
                    share += _supported(tin, local, params, spacing)
            share /= grow_sub**2
            return share, share if before is None else share * ~before
        tin3 = _grown(local, tin3, _phased(g3, k), params, centre, raised, reach, square)
    labels = _supported(tin3, local, params, spacing)
    return labels, np.zeros_like(labels) if before is None else labels & ~before


def _supported(
    tin: Tin, local: NDArray[np.float64], params: NistParams, spacing: float
) -> NDArray[np.bool_]:
    """Points in the ground band of ``tin``, and points above it that ground supports."""
    labels, above = _band(tin, local, params)
    if params.support_k > 0:
        # Only points above the band may join: those below it are low outliers.
        labels = supported_points(
            local,
            labels,
            eligible=above,
            radius=params.support_radius * spacing,
            k=params.support_k,
            tol=params.support_tol,
            rounds=params.support_rounds,
        )
    return labels


def _final_surface(
    pts: NDArray[np.float64],
    g3: Grid | ConcentricGrid,
    k: int,
    params: NistParams,
    centre: NDArray,
    square: bool,
) -> Tin:
    """Pass 3's mesh/screen of ``pts``: over the bins of ``g3`` (``k`` phases), or with
    ``square`` over the points lowest in the final-cell square around them."""
    if not square:
        srs = [select_reject(pts, params, g, mask_xy=np.zeros((0, 2))) for g in _phased(g3, k)]
        return _surface(pts, srs, params, centre)
    return _square_surface(pts, _cell_of(g3), params, centre)


def _square_surface(
    pts: NDArray[np.float64], cell: float, params: NistParams, centre: NDArray, scale: float = 1.0
) -> Tin:
    """Mesh/screen of the points of ``pts`` lowest in the ``cell`` square around them
    (``nodes.py``), screening tolerances × ``scale``."""
    idx, grads = square_lowest(pts, cell, params.z_tol)
    if idx.size < 3:
        raise _TooSparse
    slopes = _vote_slopes(grads, params.screen_slope_cap) if params.bin_fit == "plane" else None
    return _screened(pts[idx], slopes, params, scale, cell, centre)


def _label(tin: Tin, xyz: NDArray[np.float64], params: NistParams) -> NDArray[np.bool_]:
    """Points from ``ground_tol_below`` under to ``ground_tol`` over ``tin``, widened with slope."""
    return _band(tin, xyz, params)[0]


def _band(
    tin: Tin, xyz: NDArray[np.float64], params: NistParams
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Points in the ground band of ``tin`` (see ``_label``), and points above it."""
    code = tin.band(
        xyz, params.ground_tol, params.ground_tol_below, params.ground_slope, params.slope_cap
    )
    return code == IN_BAND, code == ABOVE


def _without_raised(
    tin: Tin,
    params: NistParams,
    cut: tuple[float, float, float, float] | None = None,
    local: NDArray[np.float64] | None = None,
) -> tuple[Tin, tuple[NDArray[np.float64], NDArray[np.bool_]] | None]:
    """``tin`` without its raised segments (roofs that filled the bins of every pass),
    and, when some were dropped, the local (x, y) of all of ``tin``'s vertices with
    the dropped ones flagged (their nearest-vertex regions are the raised ground plans).
    ``local``: the block's points (for ``raised_sides``)."""
    xyz = np.column_stack([tin.xy, tin.z])
    points = None
    if (params.raised_sides > 0 or params.raised_over_walls) and local is not None:
        points = np.column_stack([local[:, :2] - tin.origin, local[:, 2]])
    drop = raised_segments(
        xyz,
        tin.tri,
        params.raised_step,
        params.raised_slope,
        up_share=params.raised_share,
        min_lift=params.raised_lift,
        relative=params.raised_relative,
        walls=params.raised_walls,
        rise=params.raised_rise,
        rim=params.raised_rim,
        edge=params.raised_edge,
        cut=None if cut is None else _shifted_box(cut, -tin.origin),
        along=params.raised_along,
        heights=lambda q: _inside(tin, q),
        graded=params.raised_graded,
        walled=params.raised_walled,
        even=params.raised_even,
        sides=params.raised_sides,
        points=points,
        over_walls=params.raised_over_walls,
    )
    if params.raised_islands:
        drop |= walled_islands(
            xyz,
            tin.tri,
            drop,
            params.raised_step,
            params.raised_slope,
            walls=params.raised_walls,
            edge=params.raised_edge,
            cut=None if cut is None else _shifted_box(cut, -tin.origin),
        )
    if not drop.any() or np.count_nonzero(~drop) < 3:
        return tin, None
    try:
        return tin.without(drop), (tin.xy + tin.origin, drop)
    except (QhullError, ValueError):
        return tin, None


def _low_grown(
    z: NDArray[np.float64],
    ground: NDArray[np.bool_],
    seed: NDArray[np.bool_],
    adjacency: tuple[NDArray[np.int64], NDArray[np.int64]],
    low_tol: float,
) -> NDArray[np.bool_]:
    """Grown nodes (``ground`` but not ``seed``) more than ``low_tol`` below the
    second-lowest of their ground neighbours: low outliers, judged as screening judges a
    TIN's vertices (``screen_low_tol``). A node is the lowest point of its bin, so a deep
    return takes its bin's place, and growth reached one 4.4 m deep at the edge of the
    data where the bend allowed over a long edge along the hull is metres."""
    indptr, indices = adjacency
    grown = np.flatnonzero(ground & ~seed)
    out = np.zeros(z.shape[0], dtype=bool)
    if grown.size == 0:
        return out
    counts = indptr[grown + 1] - indptr[grown]
    owner = np.repeat(np.arange(grown.size), counts)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    nb = indices[indptr[grown][owner] + np.arange(owner.size) - first[owner]]
    nz = np.where(ground[nb], z[nb], np.inf)
    order = np.lexsort((nz, owner))
    second = np.full(grown.size, np.inf)
    has2 = counts >= 2
    second[has2] = nz[order][first[has2] + 1]
    out[grown] = z[grown] < second - low_tol
    return out


def _inside(tin: Tin, q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Heights of ``tin`` at local points ``q``; nan outside its hull."""
    t, b = tin.locate(q)
    inside = t >= 0
    h = np.full(q.shape[0], np.nan)
    h[inside] = (b[inside] * tin.z[tin.simplices[t[inside]]]).sum(axis=1)
    return h


def _vote_weights(
    local: NDArray[np.float64], g: Grid | ConcentricGrid, params: NistParams, phases: int
) -> NDArray[np.float64] | float:
    """Weight of grid phase ``g``'s labels in the vote (``vote_weight``): 1, or with
    ``centre`` a tent falling from 1 at the centre of a point's bin to 0 at its sides
    (per axis, multiplied), so a phase counts least where its bin edges pass."""
    if params.vote_weight == "equal" or phases <= 1 or not isinstance(g, Grid):
        return 1.0
    fx = np.mod((local[:, 0] - g.x0) / g.cell, 1.0)
    fy = np.mod((local[:, 1] - g.y0) / g.cell, 1.0)
    return (1.0 - np.abs(2.0 * fx - 1.0)) * (1.0 - np.abs(2.0 * fy - 1.0)) + 1e-9


def _local_cut(
    window: tuple[float, float, float, float] | None, shift: NDArray
) -> tuple[float, float, float, float] | None:
    """``window`` in the stage's local coordinates (less ``shift``)."""
    return None if window is None else _shifted_box(window, -np.asarray(shift, dtype=np.float64))


def _shifted_box(
    box: tuple[float, float, float, float], by: NDArray
) -> tuple[float, float, float, float]:
    """``box`` (xmin, ymin, xmax, ymax) moved by ``by`` (x, y)."""
    dx, dy = float(by[0]), float(by[1])
    return (box[0] + dx, box[1] + dy, box[2] + dx, box[3] + dy)


def _phased(grid: Grid | ConcentricGrid, k: int) -> list[Grid | ConcentricGrid]:
    """``grid`` and its copies offset by multiples of 1/k of a bin along x and y (k² grids)."""
    if k <= 1 or not isinstance(grid, Grid):
        return [grid]
    c = grid.cell
    out: list[Grid | ConcentricGrid] = [grid]
    return out + [
        Grid(grid.x0 - i * c / k, grid.y0 - j * c / k, c, grid.nx + 1, grid.ny + 1)
        for j in range(k)
        for i in range(k)
        if i or j
    ]


def _grown(
    local: NDArray[np.float64],
    tin: Tin,
    grids: list[Grid | ConcentricGrid],
    params: NistParams,
    centre: NDArray,
    raised: tuple[NDArray[np.float64], NDArray[np.bool_]] | None = None,
    reach: float = 0.0,
    square: bool = False,
) -> Tin:
    """The surface through the lowest point of every final bin that ``tin``
    labels ground or that growth reaches from there (``growth.py``).

    ``raised`` (vertex x, y and dropped flags from ``_without_raised``): nodes
    nearest a dropped vertex are barred, so growth does not walk back onto a
    raised roof where it meets the terrain at grade (a roof cut into a slope).
    """
    grid = grids[0]
    if square:
        low = square_lowest(local, _cell_of(grid), params.z_tol)[0]
        per_bin = 1.0
    else:
        lows = [
            lowest_per_bin(g.index(local[:, 0], local[:, 1]), local[:, 2], g.size) for g in grids
        ]
        low = np.unique(np.concatenate(lows))
        low = low[low >= 0]
        # Nodes per final bin: more than one when several grid phases are pooled.
        per_bin = low.size / max(int(np.count_nonzero(lows[0] >= 0)), 1)
    nodes = local[low]
    seed = _label(tin, nodes, params)
    barred = None
    if raised is not None:
        _, j = cKDTree(raised[0]).query(nodes[:, :2])
        barred = raised[1][j] & ~seed
    # One triangulation of the nodes serves growth (neighbours) and, with the
    # nodes left out re-triangulated, the grown surface.
    full = None
    if nodes.shape[0] >= 4 and seed.any() and not seed.all():
        try:
            full = Tin(nodes, origin=centre)
        except QhullError:
            full = None
    # Nodes further apart differ more on rough terrain; closer ones can be
    # held to less, which keeps growth off low objects in dense data.
    tol = params.grow_tol or _GROW_TOL_PER_CELL * _cell_of(grid)
    ground = grow_ground(
        nodes,
        seed,
        tol=tol,
        tol_below=params.grow_down * tol,
        bend_below_deg=params.grow_bend_down,
        bend_deg=params.grow_bend,
        max_rise=params.grow_rise,
        adjacency=None if full is None else full.neighbours(),
        barred=barred,
        peak=params.grow_peak * tol if params.grow_peaks else None,
        peak_nodes=max(1, int(per_bin * params.grow_peak_area / _cell_of(grid) ** 2)),
        agree=params.grow_agree,
        reach=reach,
    )
    if params.grow_low and params.screen_low_tol > 0 and full is not None:
        ground &= ~_low_grown(nodes[:, 2], ground, seed, full.neighbours(), params.screen_low_tol)
    if params.plateau_step > 0 and full is not None:
        ground &= ~walled_plateaus(
            nodes[:, 2],
            ground,
            seed,
            full.neighbours(),
            margin=params.grow_peak * tol,
            step=params.plateau_step,
            share=params.plateau_share,
        )
    if np.count_nonzero(ground) < 3:
        return tin
    try:
        return Tin(nodes[ground], origin=centre) if full is None else full.without(~ground)
    except (QhullError, ValueError):
        return tin
