"""Mixed-measurement removal for ground-based scans (Tuley, Vandapel, Hebert 2005, §IV).

A mixed measurement lands between a foreground edge and the background behind
it, so mixed returns line up along the rays in the edge's range shadow: a thin
sheet that contains the ray. Per interest point (or sparse voxel) we take a box
whose long axis is the ray sensor→point, the point at the centre of its front
face; the scatter matrix of the points in the box gives eigenvalues
λ0 ≥ λ1 ≥ λ2 and the saliencies linear = λ0−λ1, surface = λ1−λ2, random = λ2.
A trigger (surface dominates, or the fitted normal is near orthogonal to the
ray, or both) starts one of six marking variants.

Extensions to the seed, each a parameter:

- Box content. A mixed return is isolated in range from the surfaces on both
  sides of it, so the points of a surface crossing the box would swamp the thin
  sheet (the board face in front, the wall strip behind). A point is *supported*
  when the surface seen in the next two angular cells across the box, extrapolated
  linearly, passes through it (``support_tol``); supported points are interest
  points but never box content, so they neither enter the scatter matrix nor get
  marked. Marking variants act on the content (and the interest point).
- Background. Mixing needs a surface behind: a box fires only when at least
  ``background_share`` of its content has a supported point behind it within
  ``box_depth``. Random clutter has none, so it is never marked (seed §V-D).
- Normal trigger. The seed compares the fitted normal with the ray. We fit the
  best plane constrained to contain the ray to the content's centroid and compare
  its residual with the free fit's; that is the same angle, and stays defined
  when the content is a line along the ray (one mixed column).
- ``cross_box``: a second box rolled 90° for horizontal edges (off by default:
  far ground at grazing incidence passes for a horizontal sheet and costs fpr).

Neighbours are gathered through a sparse hash of sensor-centred angular cells:
points are sorted by (cell, range) and carry prefix sums of their first and
second moments, so the points of one cell inside a range interval — the part of
a cell that lies in a box — cost two binary searches and one subtraction, and
marking an interval is two entries in a difference array. Boxes are therefore
resolved to whole cells across the ray (``cell_angle``) and exactly along it.
No Python loop runs over points; the only loop is over scan positions.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, model_validator

from terrasift.errors import InputError, ParameterError
from terrasift.workers.mixed_box import box_frames, window_extent, window_pairs
from terrasift.workers.mixed_cross import PositionGrid, cross_check
from terrasift.workers.mixed_grid import GridSettings, mark_grid
from terrasift.workers.registry import StageParams, register
from terrasift.workers.scan_geometry import (
    ScanGeometry,
    field_of_view,
    lenders,
    measure_scan_geometry,
    pool_footprints,
)

GRID_REST = 0.02  # share of returns off the grid above which the boxes judge them
GRID_SPAN = 2  # beams between the surfaces of a blend beyond the footprint
GRID_FOOTPRINT = 3.0  # footprint (steps) the grid searches over when none was measured
# With open_edges, a beam past an open edge is marked when the geometry (footprint, step, range) gives it
# a probability above this of lying more than min_offset past the edge. Below one half on
# purpose: such beams are few beside the returns kept, so a false mark costs the false
# positive rate less than a miss costs the true positive rate. Chosen on the tune
# families (stage alone, 41 scans): 0.5 → 0.3 raised the worst tpr 0.620 → 0.736 and the
# scans meeting tpr ≥ 0.85 with fpr ≤ 0.02 from 22 to 29; 0.2 gave 0.800 and 29 but a
# worst fpr of 0.040 (0.035 at 0.3, 0.031 at 0.5); those figures count such beams as mixed
# when they lie more than 3 cm past the edge (the benchmark's earlier truth, ``--truth off``).
GRID_BLEED = 0.3

Variant = Literal[
    "naive", "aggressive", "accumulator", "exclusive", "blind_window", "exclusive_blind_window"
]
Trigger = Literal["surfaceness", "normal", "both"]
Method = Literal["grid", "box"]


class MixedParams(StageParams):
    """Parameters of the mixed-measurement filter (lengths in metres, angles in degrees)."""

    method: Method = "grid"
    """grid: returns between a nearer and a farther surface along the scan's own
    angular grid (``mixed_grid``), with the interest boxes for the returns the grid
    cannot place (LAS scale too coarse for their beam spacing) and for scans with no
    measurable grid; box: the interest boxes of the seed everywhere (the variants
    and triggers below apply to the boxes only)."""
    grid_sigmas: float = Field(4.0, gt=0.0, le=50.0)
    """grid: a surface continued to a beam passes through it when within grid_sigmas ×
    the scatter of the continuation (from the measured range scatter)."""
    margin_sigmas: float = Field(5.0, gt=0.0, le=50.0)
    """grid: a mixed return lies more than margin_sigmas × the measured range scatter of
    returns on a surface (edges and blends trimmed out) off the surfaces either side of it."""
    min_offset: float = Field(0.03, ge=0.0, le=1.0)
    """grid: returns nearer a surface than this, measured across it, count as on it (at
    grazing incidence a large range offset is a small distance off the surface: a blend
    of ground and a wall's foot). 3 cm is the distance from every surface beyond which
    the benchmark family counts a return as mixed."""
    pool_rows: int = Field(5, ge=0, le=1000)
    """grid: least run of consecutive rows (one column) whose first ramp beams beside a
    face-on surface are judged together: marked when their mean offset off that surface,
    towards the ramp, exceeds 3 standard errors of the mean of the run's offsets (the
    surface's measured range scatter) and more than 80 % of them point towards the ramp.
    0: off (each return judged on its own)."""
    anchor_beams: int = Field(3, ge=2, le=3)
    """grid: beams of an anchor's surface continued to a return to judge whether the
    return lies off it. 3: on a face-on surface (the anchor and its two outer beams on
    one line, their range within the scatter of a difference of two returns), the
    least-squares line through the three, whose continuation one beam on scatters by
    1.83 returns' sd against 2.45 through two (a blend 10 cm off two surfaces 20 cm
    apart at 9 mm noise is then found); sloped surfaces keep two beams (a bleeding end
    bends the third). 2: the line through the anchor and its outer beam everywhere."""
    variant: Variant = "exclusive_blind_window"
    """Marking: naive (the interest point), aggressive (the whole box), accumulator
    (points reported by at least ``votes`` boxes), exclusive (box but the interest
    point), blind_window (box but a slab of ``blind_depth`` behind the interest
    point), exclusive_blind_window (blind window and not the interest point)."""
    trigger: Trigger = "normal"
    """surfaceness: surface saliency dominates the box; normal: the fitted plane
    contains the ray within ``normal_angle``; both: the two together."""
    votes: int = Field(3, ge=1, le=1000)
    """Votes a point needs to be marked by the accumulator variant."""
    box_width: float | None = Field(None, gt=0.0, le=10.0)
    """Box extent across the ray, horizontal before roll, in metres. None: an angle,
    ``box_factor`` × (footprint + cell_angle) of the scan, times each box's range."""
    box_height: float = Field(0.8, gt=0.0, le=10.0)
    """Box extent across the ray, vertical before roll."""
    box_depth: float = Field(2.5, gt=0.0, le=20.0)
    """Box extent along the ray behind the interest point (the seed saw mixing up to 2.5 m)."""
    box_roll: float = Field(0.0, ge=-90.0, le=90.0)
    """Rotation of the box about the ray, to find mixed sheets in non-vertical planes."""
    blind_depth: float = Field(0.05, ge=0.0, le=10.0)
    """Depth behind the interest point left unmarked by the blind-window variants.
    Surfaces crossing the box are never its content, so this only has to cover the
    range noise and the voxel step."""
    normal_angle: float = Field(8.0, gt=0.0, le=90.0)
    """Largest deviation of the plane normal from orthogonal to the ray (normal trigger)."""
    surface_ratio: float = Field(1.0, ge=0.1, le=100.0)
    """surfaceness fires when surface > surface_ratio × max(linear, random)."""
    thinness: float = Field(1.0, gt=0.0, le=1.0)
    """The sheet must be thinner (rms across it) than thinness × the rms of points
    filling the box width, taken at the content's range (the box is the angular
    window of its front face, so it widens with range)."""
    voxel_size: float = Field(0.05, ge=0.0, le=1.0)
    """Range step of the sparse voxels that share one interest box (0: one box per point)."""
    cell_angle: float | None = Field(None, gt=0.0, le=5.0)
    """Angular size of the hash cells seen from the sensor; sets the lateral precision.
    None: ``cell_steps`` × the scan's measured angular step. A cell equal to the step
    is the worst choice (every beam sits on a cell border, so neighbouring cells hold
    zero or two beams and lateral support fails), and cells of 1.2–2 steps alias
    against the scan lines; a fixed value should be about 2.5 steps or more."""
    cell_steps: float = Field(2.5, ge=1.0, le=20.0)
    """Cell angle in measured angular steps when ``cell_angle`` is None (a non-integer
    multiple keeps the cell borders off the scan lines' rhythm)."""
    support_tol: float | None = Field(None, gt=0.0, le=1.0)
    """Lateral support: a point where the surface seen in the next two angular cells
    across the box, extrapolated linearly, lands within support_tol of its range
    lies on a surface crossing the box, so it is not box content (it can still be
    an interest point). Mixed returns lie off that line. None: ``support_sigmas`` ×
    the scan's measured range scatter (noise and LAS quantisation)."""
    support_sigmas: float = Field(5.0, gt=0.0, le=50.0)
    """Support tolerance in measured range sd when ``support_tol`` is None (the
    extrapolation from two cells scatters by about 2.4 sd)."""
    box_factor: float = Field(2.0, gt=0.0, le=20.0)
    """Box width as an angle, in units of (footprint + cell_angle), when ``box_width``
    is None: a mixed ramp spreads over the footprint, and the box must hold it
    with its neighbouring cells."""
    resolve: float = Field(0.25, gt=0.0, le=10.0)
    """Points whose angle the LAS coordinate step blurs by more than resolve × cell_angle
    (sd of the quantisation, scale / √12 / range) are never box content: too near for
    the file to tell neighbouring beams apart. Needs the measured geometry."""
    footprint: float | None = Field(None, gt=0.0, le=10.0)
    """Beam footprint across the scan lines in degrees when known; None measures it
    from the ramps of blended returns at range edges (one step when none shows)."""
    cross_box: bool = False
    """Also evaluate a second box turned 90° about the ray, for mixed sheets along
    horizontal edges (board tops and bottoms)."""
    background_share: float = Field(0.5, ge=0.0, le=1.0)
    """Share of the box content that must have a surface behind it (within box_depth,
    in its own or the next cell across the box). A mixed return blends a foreground
    with a background; random clutter has none (seed §V-D)."""
    open_edges: bool = False
    """grid: also mark returns at an edge with nothing behind it (no return, or a
    background beyond box_depth) that lie off the surface they end: a footprint partly
    past the edge answers from that one surface, on its own central ray, up to half a
    footprint past the edge (``mixed_grid._bleeding``), or from the mean range of the part
    still on a sloped surface. No second surface answers, so such a return is no
    mixed measurement (seed §III-C.1: no blend without a background within 2.5 m); it
    is a return displaced by the beam's width. Off by default: face on, its range does not
    tell whether it lies past the edge, so it is marked by probability and whole edges
    come out wrong together (false positive rates of 0.02-0.04 at 0.3-0.5° steps). Off,
    a return at such an edge is still marked when it lies off the surface it ends by more
    than that surface alone could pull it: a blend with a background ending in the beam."""
    cross_positions: bool = False
    """grid: take off the marks of returns that another scan position of the tile sees
    on a surface (``mixed_cross``); needs several positions seeing the same place."""
    cross_sigmas: float = Field(2.0, gt=0.0, le=50.0)
    """grid: another position's surface, interpolated to a return's direction, passes
    within cross_sigmas × the two positions' combined range scatter of it."""
    cross_free: bool = False
    """grid, with cross_positions: also mark returns lying where another position's
    beams pass to returns more than cross_free_margin beyond them, unless their own
    position sees them on a smooth surface."""
    cross_free_margin: float = Field(0.3, gt=0.0, le=10.0)
    """Free space must reach this far beyond a return (m); chosen on shared-scene tune
    scans at 0.3-0.5° steps, 2-10 mm range noise."""
    min_points: int = Field(8, ge=3, le=1000)
    """Boxes with fewer content points are not classified. Saliency needs three (the
    seed's minimum); a few more keep the fitted plane meaningful."""

    @model_validator(mode="after")
    def _check(self) -> MixedParams:
        if self.blind_depth >= self.box_depth:
            raise ValueError("blind_depth must be smaller than box_depth")
        if self.voxel_size >= self.box_depth:
            raise ValueError("voxel_size must be smaller than box_depth")
        return self


@dataclass(frozen=True)
class MixedResult:
    """Marked points, points no box could classify, and counts.

    A supported point (on a surface crossing the boxes) is classified by that; an
    unsupported one is unclassified when no box of its own held ``min_points`` of
    content and it was not marked (the seed's loss).
    """

    marked: NDArray[np.bool_]
    unclassified: NDArray[np.bool_]
    loss_rate: float  # unclassified / all points
    n_points: int
    n_marked: int
    n_unclassified: int
    n_regions: int  # interest boxes evaluated
    n_triggered: int  # interest boxes whose trigger fired
    geometry: list[dict[str, Any]] = field(default_factory=list)
    """Per scan position: the measured scan geometry and the values it gave the stage."""


@register("mixed", MixedParams, "Tuley mixed-measurement removal for ground-based scans")
def mark_mixed(
    xyz: NDArray[np.float64],
    params: MixedParams,
    sensor_origin: NDArray[np.float64],
    scan_id: NDArray[np.integer] | None = None,
    geometry: Sequence[ScanGeometry | None] | None = None,
    gps_time: NDArray[np.floating] | None = None,
) -> MixedResult:
    """Mark mixed measurements of one or several scans with known sensor origins.

    ``sensor_origin`` is (3,) for one scan, or (k, 3) with ``scan_id`` giving each
    point's scan position (0..k-1). Coordinates may be absolute: each scan is
    shifted to its own sensor before anything else. ``geometry`` (one entry per scan
    position) is the scan geometry measured beforehand on more points than these (a
    job measures it once from all its blocks); a position without one is measured here.
    ``gps_time`` (one per point, or None) places the returns on the scan grid by their
    firing order (grid method), where the times show a regular pulse period.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"xyz must be (n, 3), got {xyz.shape}")
    origins, ids = _scan_layout(xyz.shape[0], sensor_origin, scan_id)
    n = xyz.shape[0]
    times = None
    if gps_time is not None:
        times = np.asarray(gps_time, dtype=np.float64)
        if times.shape != (n,):
            raise ParameterError(f"gps_time must have shape ({n},), got {times.shape}")
    marked = np.zeros(n, dtype=bool)
    unclassified = np.zeros(n, dtype=bool)
    n_regions = n_triggered = 0
    found: list[dict[str, Any]] = []
    grids: list[PositionGrid | None] = [None] * origins.shape[0]
    geos = _position_geometry(xyz, params, origins, ids, geometry, times)
    for k in range(origins.shape[0]):
        idx = np.flatnonzero(ids == k) if ids is not None else slice(None)
        rel = xyz[idx] - origins[k]
        if rel.shape[0] == 0:
            continue
        known = geos[k]
        t = times[idx] if times is not None else None
        derived = derive_params(rel, params, absolute=xyz[idx], geometry=known, gps_time=t)
        extra: dict[str, Any] = {"method": "box"}
        if params.method == "grid" and derived.geometry is not None:
            gs = grid_settings(derived.geometry, params)
            grids[k] = PositionGrid(gs.step_az, gs.step_el, gs.sigma, gs.footprint)
            fov = derived.geometry.field_of_view
            if fov is None:
                r_ = np.linalg.norm(rel, axis=1)
                fov = field_of_view(
                    np.arctan2(rel[:, 1], rel[:, 0]),
                    np.arcsin(np.clip(rel[:, 2] / np.maximum(r_, 1e-12), -1.0, 1.0)),
                )
            m, judged, timed = mark_grid(rel, gs, t, fov)
            u = np.zeros(rel.shape[0], dtype=bool)
            nr, nt = int(judged.sum()), int(m.sum())
            rest = ~judged
            if np.count_nonzero(rest) > GRID_REST * rel.shape[0]:
                mb, ub, nrb, ntb = _mark_boxes(rel, params, derived, not timed, rest)
                m |= mb & rest
                u = ub & rest
                nr, nt = nr + nrb, nt + ntb
            extra = {
                "method": "grid",
                "grid_share": round(float(judged.mean()), 4),
                "grid_index": "GPS time (firing order)" if timed else "angles",
                "reach": gs.reach,
                "thin": gs.thin,
            }
        else:
            m, u, nr, nt = _mark_boxes(rel, params, derived, True)
        marked[idx], unclassified[idx] = m, u
        n_regions += nr
        n_triggered += nt
        found.append({"scan": k, "points": int(rel.shape[0]), **derived.report(), **extra})
    if params.cross_positions and ids is not None and origins.shape[0] > 1:
        margin = params.cross_free_margin if params.cross_free else None
        seen, free = cross_check(xyz, ids, origins, grids, marked, params.cross_sigmas, margin)
        marked = (marked & ~seen) | free
        for entry in found:
            on = ids == entry["scan"]
            entry["cross_positions"] = {
                "unmarked": int(np.count_nonzero(seen & on)),
                "marked": int(np.count_nonzero(free & on)),
            }
    n_unc = int(unclassified.sum())
    return MixedResult(
        marked=marked,
        unclassified=unclassified,
        loss_rate=n_unc / n if n else 0.0,
        n_points=n,
        n_marked=int(marked.sum()),
        n_unclassified=n_unc,
        n_regions=n_regions,
        n_triggered=n_triggered,
        geometry=found,
    )


def _position_geometry(
    xyz: NDArray[np.float64],
    params: MixedParams,
    origins: NDArray[np.float64],
    ids: NDArray[np.intp] | None,
    geometry: Sequence[ScanGeometry | None] | None,
    times: NDArray[np.float64] | None = None,
) -> list[ScanGeometry | None]:
    """Each position's geometry: the one given, else measured on its points; the
    footprints of positions of one scanner pooled (``pool_footprints``) when any was
    measured here (a job passes every position's, pooled once on all its blocks)."""
    k = origins.shape[0]
    geos: list[ScanGeometry | None] = [
        geometry[i] if geometry is not None and i < len(geometry) else None for i in range(k)
    ]
    fixed = params.cell_angle is not None and params.support_tol is not None
    if k < 2 or (fixed and params.box_width is not None and params.method == "box"):
        return geos
    if all(g is not None for g in geos):
        return geos
    given = geometry is not None
    for lend in (False, True):
        # a position whose angles show no grid takes the steps of another (``lent_steps``);
        # a job has tried that on the geometry it passes
        if lend and (given or all(g is None for g in geos)):
            break
        others = lenders(geos) if lend else []
        for i in range(k):
            if geos[i] is None:
                idx = np.flatnonzero(ids == i) if ids is not None else slice(None)
                if xyz[idx].shape[0] > 0:
                    geos[i] = measure_scan_geometry(
                        xyz[idx] - origins[i],
                        footprint=params.footprint,
                        absolute=xyz[idx],
                        gps_time=None if times is None else times[idx],
                        lenders=others,
                    )
    return pool_footprints(geos)


@dataclass(frozen=True)
class Derived:
    """Stage parameters of one scan position with the geometry they came from."""

    params: MixedParams  # cell_angle and support_tol resolved
    box_angle: float | None  # box width as an angle (radians); None: params.box_width
    geometry: Any  # ScanGeometry or None

    @property
    def las_scale(self) -> float:
        return self.geometry.las_scale if self.geometry is not None else 0.0

    def report(self) -> dict[str, Any]:
        p = self.params
        out: dict[str, Any] = {
            "cell_angle": round(float(p.cell_angle or 0.0), 6),
            "support_tol": round(float(p.support_tol or 0.0), 6),
            # box width across the ray: metres, or degrees (times each box's range)
            "box_width": p.box_width,
            "box_angle": None if self.box_angle is None else round(np.degrees(self.box_angle), 6),
        }
        if self.geometry is not None:
            out["measured"] = self.geometry.to_dict()
        return out


def derive_params(
    rel: NDArray[np.float64],
    p: MixedParams,
    absolute: NDArray[np.float64] | None = None,
    geometry: ScanGeometry | None = None,
    gps_time: NDArray[np.float64] | None = None,
) -> Derived:
    """Resolve the angles and distances left open (None) from the scan's measured geometry.

    ``geometry``, when given, was measured beforehand (on the whole scan) and is used
    as it is; ``gps_time`` (one per point, or None) lets it measure the steps from the
    firing order where the angles show no grid. Without enough points to measure, the values the filter was first tuned
    with (0.25° cells, 2 cm support, 15 cm boxes) stand in.
    """
    fixed = p.cell_angle is not None and p.support_tol is not None and p.box_width is not None
    if fixed and p.method == "box":
        return Derived(p, None, None)
    geo = geometry or measure_scan_geometry(
        rel, footprint=p.footprint, absolute=absolute, gps_time=gps_time
    )
    if geo is None:
        upd = {"cell_angle": p.cell_angle or 0.25, "support_tol": p.support_tol or 0.02}
        return Derived(p.model_copy(update={**upd, "box_width": p.box_width or 0.15}), None, None)
    cell = p.cell_angle if p.cell_angle is not None else p.cell_steps * geo.step
    # a range scatters at least by its coordinates' quantisation (scale / √12), as the
    # grid takes it (``grid_settings``): on a few far returns the measured scatter can
    # come out far below (report 7006: 0.01 mm with 1 cm coordinates), and near ground,
    # whose angle the scale blurs, then lies off the line of its neighbours
    q_sd = geo.las_scale / np.sqrt(12.0)
    tol = (
        p.support_tol
        if p.support_tol is not None
        else float(np.clip(p.support_sigmas * max(geo.range_sigma, q_sd), 0.002, 1.0))
        if np.isfinite(geo.range_sigma)
        else 0.02
    )
    box = None if p.box_width is not None else np.radians(p.box_factor * (geo.footprint + cell))
    return Derived(p.model_copy(update={"cell_angle": cell, "support_tol": tol}), box, geo)


def grid_settings(geo: ScanGeometry, p: MixedParams) -> GridSettings:
    """Grid-method settings from the measured geometry: surfaces are looked for up to
    2 footprints + 1 beams away (a ramp spans about a footprint, a thin object's blend
    up to two), thin runs up to as long, gaps up to the box depth (the seed's mixing
    distance)."""
    fp = max(geo.footprint_steps, 1.0)
    # bleeding past an edge follows the measured footprint only (one step when none
    # was measured): with 1 cm coordinates at 0.05-0.09° steps the assumed three
    # steps marked whole rows past edges (fpr 0.022-0.028 on two quant tune scans)
    bleed_fp = fp
    if geo.how.get("footprint", "").startswith("no mixing"):
        # no ramp measured (too few resolved edges): the search for surfaces, blends
        # and thin runs takes the widest footprint of the family's range; on the tune
        # family a missed ramp cost more than edge beams
        fp = max(fp, GRID_FOOTPRINT)
    wide = fp
    reach = int(np.clip(np.ceil(2 * wide) + 1, 2, 7))
    sigma = geo.range_sigma if np.isfinite(geo.range_sigma) else 0.01
    sigma = max(sigma, geo.las_scale / np.sqrt(12.0), 1e-4)
    # the margin, how far off both surfaces a blend must lie, in the scatter of returns on
    # a surface: the median residual also holds edges and blends, 15-50 % more at coarse
    # steps (shared-report 5205: blends 3-4 cm off a wall at 9-13 mm were missed). The
    # anchor tolerances keep ``sigma``, since they also take up what edges add
    surface = geo.surface_sigma if np.isfinite(geo.surface_sigma) else sigma
    surface = max(surface, geo.las_scale / np.sqrt(12.0), 1e-4)
    return GridSettings(
        step_az=float(np.radians(geo.step_az)),
        step_el=float(np.radians(geo.step_el)),
        sigma=float(sigma),
        sigmas=p.grid_sigmas,
        margin=float(p.margin_sigmas * surface),
        reach=reach,
        max_gap=p.box_depth,
        thin=int(min(np.ceil(2 * wide) + 1, reach + 1)),
        thin_peak=int(min(2 * np.ceil(wide) + 1, reach + 1)),
        footprint=float(bleed_fp),
        span=int(np.ceil(fp)) + GRID_SPAN,
        las_scale=geo.las_scale,
        min_offset=p.min_offset,
        bleed_prob=GRID_BLEED,
        open_edges=p.open_edges,
        fit_beams=p.anchor_beams,
        surface_sigma=float(surface),
        pool_rows=p.pool_rows,
    )


def _scan_layout(
    n: int, sensor_origin, scan_id
) -> tuple[NDArray[np.float64], NDArray[np.intp] | None]:
    origins = np.asarray(sensor_origin, dtype=np.float64)
    if origins.shape == (3,):
        origins = origins[None, :]
    if origins.ndim != 2 or origins.shape[1] != 3 or origins.shape[0] == 0:
        raise ParameterError(f"sensor_origin must be (3,) or (k, 3), got {np.shape(sensor_origin)}")
    if not np.isfinite(origins).all():
        raise ParameterError("sensor_origin must be finite")
    if scan_id is None:
        if origins.shape[0] > 1:
            raise ParameterError("several sensor origins need a per-point scan_id")
        return origins, None
    ids = np.asarray(scan_id)
    if ids.shape != (n,) or not np.issubdtype(ids.dtype, np.integer):
        raise ParameterError(f"scan_id must be an integer array of shape ({n},)")
    if n and (ids.min() < 0 or ids.max() >= origins.shape[0]):
        raise ParameterError(f"scan_id values must lie in 0..{origins.shape[0] - 1}")
    return origins, ids.astype(np.intp)


def _mark_boxes(
    rel: NDArray[np.float64],
    p: MixedParams,
    d: Derived,
    banded: bool,
    judge: NDArray[np.bool_] | None = None,
) -> tuple[NDArray, NDArray, int, int]:
    """The interest boxes on one scan; with ``banded`` (returns placed by their angles, not
    by GPS time; the measured cell; a quantised file) the returns the LAS scale blurs past
    the cell are judged again with the cell doubled. ``judge`` (None: all) are the returns whose marks are used.

    A return whose quantisation blur (scale / √12 / range) exceeds ``resolve`` × the cell
    is never box content. With 1 cm coordinates at a 0.037° step (report 7600: half the
    returns within 5 m) that was every return near enough to blend, and the boxes marked
    a third of the blends. The boxes then run a second time on all the returns (the
    neighbours and backgrounds lie at any range) with twice the cell, and the returns
    whose blur that cell holds keep its marks. Not doubled again: cells of four measured
    ones found no more blends and marked twice the false ones near boards at 4-6 m.
    """
    m, u, nr, nt = _mark_scan(rel, d.params, d.box_angle, d.las_scale)
    if not banded or d.geometry is None or p.cell_angle is not None or d.las_scale <= 0:
        return m, u, nr, nt
    cell = 2.0 * float(d.params.cell_angle or 0.0)
    r = np.linalg.norm(rel, axis=1)
    blur = d.las_scale / np.sqrt(12.0) / np.maximum(r, 1e-6)
    on = (blur > p.resolve * np.radians(cell / 2.0)) & (blur <= p.resolve * np.radians(cell))
    if judge is not None:
        on &= judge
    if np.count_nonzero(on) < 50:
        return m, u, nr, nt
    box = (
        None
        if d.box_angle is None
        else float(np.radians(p.box_factor * (d.geometry.footprint + cell)))
    )
    m2, u2, nr2, nt2 = _mark_scan(
        rel, d.params.model_copy(update={"cell_angle": cell}), box, d.las_scale
    )
    m[on], u[on] = m2[on], u2[on]
    return m, u, nr + nr2, nt + nt2


def _mark_scan(
    rel: NDArray[np.float64],
    p: MixedParams,
    box_angle: float | None = None,
    las_scale: float = 0.0,
) -> tuple[NDArray, NDArray, int, int]:
    """Filter one scan; ``rel`` is relative to its sensor. Returns marks, unclassified, counts.

    ``p`` has its cell angle and support tolerance resolved; the box width is
    ``box_angle`` (radians) × each box's range, or ``p.box_width`` when it is None.
    """
    if p.cell_angle is None or p.support_tol is None:
        raise ValueError("cell_angle and support_tol must be resolved first (derive_params)")
    if box_angle is None and p.box_width is None:
        raise ValueError("a box width or a box angle is needed")
    cell_angle, support_tol = p.cell_angle, p.support_tol
    n = rel.shape[0]
    marked = np.zeros(n, dtype=bool)
    unclassified = np.ones(n, dtype=bool)
    r = np.linalg.norm(rel, axis=1)
    valid = np.flatnonzero(r > 1e-6)
    if valid.size == 0:
        return marked, unclassified, 0, 0
    q, r = rel[valid], r[valid]

    # Sparse hash of angular cells; points sorted by (cell, range).
    beta = np.radians(cell_angle)
    n_az = int(np.ceil(2 * np.pi / beta))
    n_el = int(np.ceil(np.pi / beta)) + 1
    az = np.arctan2(q[:, 1], q[:, 0])
    el = np.arcsin(np.clip(q[:, 2] / r, -1.0, 1.0))
    ia = np.minimum(((az + np.pi) / beta).astype(np.int64), n_az - 1)
    ie = np.minimum(((el + np.pi / 2) / beta).astype(np.int64), n_el - 1)
    cell = ia * n_el + ie
    order = np.lexsort((r, cell))
    q, r, cell, ia, ie, az, el = (
        q[order],
        r[order],
        cell[order],
        ia[order],
        ie[order],
        az[order],
        el[order],
    )
    big = float(2 ** int(np.ceil(np.log2(r.max() + p.box_depth + 2.0))))
    key = cell * big + r

    # Lateral support: the surface through the neighbours across azimuth (elevation) continues through the point.
    sup_az = _continued(key, r, az, el, ia, ie, n_az, n_el, big, beta, support_tol, axis=0)
    sup_el = (
        _continued(key, r, el, az, ia, ie, n_az, n_el, big, beta, support_tol, axis=1)
        if p.cross_box
        else sup_az
    )
    if las_scale > 0:
        # Too near for the file's coordinate step to tell the cells apart: the
        # angle of a point jitters by scale / range, so its neighbours cannot be
        # found by cell; such points are left alone (never box content).
        blurred = las_scale / np.sqrt(12.0) / r > p.resolve * beta
        sup_az = sup_az | blurred
        sup_el = sup_el | blurred

    # Interest voxels: runs of one cell within one range step; the nearest point is the interest point.
    rbin = np.floor(r / p.voxel_size).astype(np.int64) if p.voxel_size > 0 else np.arange(r.size)
    new = np.ones(r.size, dtype=bool)
    new[1:] = (cell[1:] != cell[:-1]) | (rbin[1:] != rbin[:-1])
    first = np.flatnonzero(new)
    item_of = np.cumsum(new) - 1
    n_items = first.size
    P, r0, ia0, ie0 = q[first], r[first], ia[first], ie[first]
    bw = r0 * box_angle if box_angle is not None else np.full(n_items, float(p.box_width or 0.0))

    blind = p.blind_depth if "blind" in p.variant else 0.0
    box_votes = np.zeros(r.size, dtype=np.int64)  # boxes whose region holds the point
    win_votes = np.zeros(r.size, dtype=np.int64)  # ... beyond the blind window
    self_box = np.zeros(r.size, dtype=np.int64)  # of those, the point's own box
    self_win = np.zeros(r.size, dtype=np.int64)
    own = np.zeros(r.size, dtype=bool)  # the point's own box fired
    candidate = np.zeros(r.size, dtype=bool)
    decided = np.zeros(r.size, dtype=bool)  # a box holding enough content judged the point
    n_regions = n_triggered = 0
    rolls = [p.box_roll] + (
        [p.box_roll + 90.0 if p.box_roll <= 0 else p.box_roll - 90.0] if p.cross_box else []
    )
    for roll in rolls:
        # Box content: the points not supported across the box's width axis.
        across_az = abs(roll) < 45.0
        sup = sup_az if across_az else sup_el
        cand = np.flatnonzero(~sup)
        candidate[cand] = True
        frames = box_frames(P, np.radians(roll))
        na, ne = window_extent(P, r0, frames, bw, p.box_height, beta, n_az)
        fired = np.zeros(n_items, dtype=bool)
        counted = np.zeros(n_items, dtype=bool)
        if cand.size:
            kc = key[cand]
            img = np.bincount(cell[cand], minlength=n_az * n_el).reshape(n_az, n_el)
            look = np.flatnonzero(_window_count(img, ia0, ie0, na, ne) > 0)
            it, pc = window_pairs(
                r0[look],
                ia0[look],
                ie0[look],
                na[look],
                ne[look],
                frames[look],
                bw[look],
                p.box_height,
                beta,
                n_az,
                n_el,
                img.ravel() > 0,
            )
            it = look[it]
            lo = np.searchsorted(kc, pc * big + r0[it], side="left")
            hi = np.searchsorted(kc, pc * big + r0[it] + p.box_depth, side="right")
            nz = hi > lo  # most covered cells hold nothing within the box's range interval
            it, pc, lo, hi = it[nz], pc[nz], lo[nz], hi[nz]

            # Box moments of the content from prefix sums.
            x, y, z = q[cand, 0], q[cand, 1], q[cand, 2]
            bg = _background(
                key[sup], cell[cand], r[cand], n_el if across_az else 1, big, p.box_depth
            )
            mom = np.zeros((cand.size + 1, 11))
            np.cumsum(
                np.column_stack(
                    [np.ones_like(x), x, y, z, x * x, x * y, x * z, y * y, y * z, z * z, bg]
                ),
                axis=0,
                out=mom[1:],
            )
            diff = mom[hi] - mom[lo]
            S: NDArray = np.column_stack(
                [np.bincount(it, weights=diff[:, j], minlength=n_items) for j in range(11)]
            )
            counted = S[:, 0] >= p.min_points
            ci = np.flatnonzero(counted)
            if ci.size:
                fired[ci] = _trigger(S[ci], frames[ci], r0[ci], bw[ci], p)

            # Marking through difference arrays over the sorted content.
            sel = fired[it]
            box_c = np.cumsum(
                np.bincount(lo[sel], minlength=cand.size + 1)
                - np.bincount(hi[sel], minlength=cand.size + 1)
            )
            box_votes[cand] += box_c[:-1]
            lo_w = (
                np.searchsorted(kc, pc[sel] * big + r0[it[sel]] + blind, side="left")
                if blind > 0
                else lo[sel]
            )
            win_c = np.cumsum(
                np.bincount(lo_w, minlength=cand.size + 1)
                - np.bincount(hi[sel], minlength=cand.size + 1)
            )
            win_votes[cand] += win_c[:-1]
            behind = r[cand] - r0[item_of[cand]] >= blind
            f_own = fired[item_of[cand]]
            self_box[cand] += f_own
            self_win[cand] += f_own & behind
            decided[cand] |= counted[item_of[cand]]
        own |= fired[item_of]
        n_regions += int(counted.sum())
        n_triggered += int(fired.sum())

    # The interest voxel belongs to its own region even when it is not box content.
    region = box_votes + (own & (self_box == 0))
    if p.variant == "naive":
        m = own
    elif p.variant == "aggressive":
        m = region > 0
    elif p.variant == "accumulator":
        m = region >= p.votes
    elif p.variant == "exclusive":
        m = (box_votes - self_box) > 0
    elif p.variant == "blind_window":
        m = (win_votes > 0) | own
    else:  # exclusive_blind_window
        m = (win_votes - self_win) > 0
    # Points on a surface crossing every box are judged by that; the rest by their own box.
    unc = candidate & ~decided & ~m

    back = valid[order]
    marked[back] = m
    unclassified[back] = unc
    return marked, unclassified, n_regions, n_triggered


def _continued(
    key: NDArray[np.float64],
    r: NDArray[np.float64],
    ang: NDArray[np.float64],
    ang_other: NDArray[np.float64],
    ia: NDArray[np.int64],
    ie: NDArray[np.int64],
    n_az: int,
    n_el: int,
    big: float,
    beta: float,
    tol: float,
    axis: int,
) -> NDArray[np.bool_]:
    """Whether a surface seen on one side of each point continues through it.

    On each side along ``axis`` (0 azimuth, 1 elevation) take the point of the
    next cell nearest in range (j, within a gate of 4·tol + 2·range·cell) and,
    from j, the next cell's (k); the point is supported when the range
    extrapolated linearly in angle from k through j lands within ``tol`` of its
    own. Planes at moderate incidence pass; a mixed return, off the line from
    foreground to background, does not. (Grazing surfaces such as far ground
    curve too fast in range along elevation to pass the elevation test.)
    """
    gate = 4.0 * tol + 2.0 * r * beta
    out = np.zeros(r.size, dtype=bool)
    # The other axis: a scan line near a cell border may fall either side of it,
    # so each step looks at the cell across the nearer border too.
    other = (ang_other + (np.pi if axis == 0 else np.pi / 2)) / beta
    side = np.where(other - np.floor(other) >= 0.5, 1, -1)

    def nearest(a, e, rr, sd):
        best = np.zeros(rr.size, dtype=np.int64)
        dist = np.full(rr.size, np.inf)
        for off in (0, 1):
            aa, ee = (a, e + off * sd) if axis == 0 else (a + off * sd, e)
            aa, ee = aa % n_az, np.clip(ee, 0, n_el - 1)
            k = (aa * n_el + ee) * big + rr
            i = np.searchsorted(key, k)
            for c in (np.minimum(i, key.size - 1), np.maximum(i - 1, 0)):
                d = np.abs(key[c] - k)
                better = d < dist
                best[better], dist[better] = c[better], d[better]
        return best, dist <= gate

    for s in (1, -1):
        if axis == 0:
            ok = np.ones(r.size, dtype=bool)
            j, okj = nearest(ia + s, ie, r, side)
            k, okk = nearest(ia + 2 * s, ie, r[j], side[j])
        else:
            ok = (ie + 2 * s >= 0) & (ie + 2 * s < n_el)
            j, okj = nearest(ia, ie + s, r, side)
            k, okk = nearest(ia, ie + 2 * s, r[j], side[j])
        djk = ang[j] - ang[k]
        dij = ang - ang[j]
        if axis == 0:  # across the azimuth seam
            djk = (djk + np.pi) % (2 * np.pi) - np.pi
            dij = (dij + np.pi) % (2 * np.pi) - np.pi
        good = ok & okj & okk & (np.abs(djk) > 1e-9)
        pred = r[j] + (r[j] - r[k]) * dij / np.where(good, djk, 1.0)
        out |= good & (np.abs(pred - r) <= tol)
    return out


def _background(
    ksup: NDArray[np.float64],
    cell: NDArray[np.int64],
    r: NDArray[np.float64],
    step: int,
    big: float,
    depth: float,
) -> NDArray[np.float64]:
    """1 where a supported point (a surface) lies behind the point within ``depth``,
    in its own cell or the next one either side across the box (``step`` cells)."""
    out = np.zeros(r.size, dtype=bool)
    if ksup.size == 0:
        return out.astype(np.float64)
    for dc in (0, step, -step):
        k = (cell + dc) * big + r
        i = np.searchsorted(ksup, k, side="right")
        out |= (i < ksup.size) & (ksup[np.minimum(i, ksup.size - 1)] - k <= depth)
    return out.astype(np.float64)


def _window_count(
    img: NDArray[np.int64],
    ia: NDArray[np.int64],
    ie: NDArray[np.int64],
    na: NDArray[np.int64],
    ne: NDArray[np.int64],
) -> NDArray[np.int64]:
    """Points of ``img`` (azimuth × elevation counts) in each window; windows across the azimuth seam count as full."""
    n_az, n_el = img.shape
    sat = np.zeros((n_az + 1, n_el + 1), dtype=np.int64)
    np.cumsum(np.cumsum(img, axis=0), axis=1, out=sat[1:, 1:])
    a0, a1 = ia - na, ia + na + 1
    e0, e1 = np.maximum(ie - ne, 0), np.minimum(ie + ne + 1, n_el)
    wrap = (a0 < 0) | (a1 > n_az)
    a0, a1 = np.clip(a0, 0, n_az), np.clip(a1, 0, n_az)
    cnt = sat[a1, e1] - sat[a0, e1] - sat[a1, e0] + sat[a0, e0]
    return np.where(wrap, 1, cnt)


def _trigger(
    S: NDArray[np.float64],
    frames: NDArray[np.float64],
    r0: NDArray[np.float64],
    bw: NDArray[np.float64],
    p: MixedParams,
) -> NDArray[np.bool_]:
    """Saliency of each box from its moment sums; which boxes fire."""
    n = S[:, 0]
    mean = S[:, 1:4] / n[:, None]
    xx, xy, xz, yy, yz, zz = (S[:, 4 + j] / n for j in range(6))
    cov = np.empty((n.size, 3, 3))
    cov[:, 0, 0] = xx - mean[:, 0] ** 2
    cov[:, 0, 1] = cov[:, 1, 0] = xy - mean[:, 0] * mean[:, 1]
    cov[:, 0, 2] = cov[:, 2, 0] = xz - mean[:, 0] * mean[:, 2]
    cov[:, 1, 1] = yy - mean[:, 1] ** 2
    cov[:, 1, 2] = cov[:, 2, 1] = yz - mean[:, 1] * mean[:, 2]
    cov[:, 2, 2] = zz - mean[:, 2] ** 2
    # normal: the content lies on a thin sheet containing the ray (through the
    # sensor). The best plane constrained to contain the ray to the centroid, m,
    # leaves the spread mu across it; a plane tilted by d from containing m leaves
    # about lam2 + tan²(d)·(spread along m) — the seed's normal-to-ray angle, still
    # defined when the content is a line along the ray (a single mixed column).
    # The ground seen from a mast misses the sensor by the mast height.
    w = np.linalg.eigvalsh(cov)  # ascending
    lam2 = np.maximum(w[:, 0], 0.0)
    rbar = np.linalg.norm(mean, axis=1)
    mdir = mean / rbar[:, None]
    proj = np.eye(3)[None] - mdir[:, :, None] * mdir[:, None, :]
    wp = np.linalg.eigvalsh(proj @ cov @ proj)
    mu, mu_max = wp[:, 1], wp[:, 2]
    along = np.einsum("ij,ijk,ik->i", mdir, cov, mdir)
    # Thin: rms across the sheet under thinness × that of points filling the box
    # width, the box being the angular window of its front face, widened with range.
    fill = (bw * rbar / r0) ** 2 / 12.0
    thin = mu <= p.thinness**2 * fill
    # The content must reach along the ray (at least half as far, in rms, as across
    # it): a row of ground points across the ray lies in such a plane too.
    perp = (
        thin
        & (along >= 0.25 * mu_max)
        & (mu - lam2 <= np.tan(np.radians(p.normal_angle)) ** 2 * along)
    )
    # surfaceness: saliency in box units (each axis over the box's extent), so a
    # box filled at random is isotropic; the sheet must be the box's long plane
    # (normal along the width axis), which roll turns about the ray.
    scale = np.column_stack(
        [np.full(bw.size, 1.0 / p.box_depth), 1.0 / bw, np.full(bw.size, 1.0 / p.box_height)]
    )
    R = frames * scale[:, :, None]
    cb = R @ cov @ np.transpose(R, (0, 2, 1))
    wb, vb = np.linalg.eigh(cb)
    b2, b1, b0 = np.maximum(wb[:, 0], 0.0), wb[:, 1], wb[:, 2]
    linear, surface, random = b0 - b1, b1 - b2, b2
    along_u = np.abs(vb[:, 1, 0]) >= np.abs(vb[:, [0, 2], 0]).max(axis=1)
    surf = along_u & (surface > p.surface_ratio * np.maximum(linear, random))
    # Mixing needs a background: most of the content lies in front of a surface.
    backed = S[:, 10] >= p.background_share * n
    if p.trigger == "surfaceness":
        return backed & surf
    if p.trigger == "normal":
        return backed & perp
    return backed & surf & perp
