"""Scan geometry measured from the points of one ground-based scan position.

The mixed-measurement filter works in the sensor's angle space, so its angles
and distances follow from the scanner: the angular step between beams in
azimuth and in elevation, the range noise, the LAS scale (an angular
uncertainty of scale / range at each range) and the beam footprint (a mixed
return blends what the footprint covers, so at an edge it spreads as a ramp
over about footprint / step neighbouring beams). Everything here is measured
on the points relative to the sensor; nothing assumes a scanner model beyond
beams on (locally) regular angular lines.

- LAS scale: the smallest step that divides the differences of the sorted
  coordinate values (0 when the coordinates are not quantised).
- Angular step: per point, the nearest neighbour in angle space lying along
  azimuth (resp. elevation); the median of those spacings. Only points far
  enough for the scale's angular uncertainty to stay under a tenth of a step
  take part. With GPS time, where no share of the returns shows the grid (every
  angle blurred past it), from the firing order instead (``firing_steps``).
- Range noise: residual of each point's range against the line through its
  two azimuth neighbours (a local plane seen along a scan line); a robust sd,
  then the LAS quantisation's share (scale²/12) taken out. The scatter of returns
  on a surface (``surface_sigma``) leaves out the residuals of edges and blends:
  the sd of those within ±``TRIM`` sd of their mean, iterated, corrected for the
  truncation (the median residual runs 15-50 % high at coarse steps, where edges
  and blends are a large share of the returns).
- Footprint: the scan lines are binned on the measured azimuth grid; at each
  range edge between two surfaces closer than ``max_gap`` (each flank at least
  three beams on one level: the plateau of blends before a pole narrower than the
  footprint is no surface) the number of beams
  whose range lies between the two (the ramp) is counted; the footprint is the
  mean ramp length in steps over the edges that show a ramp (at least one step),
  pooled over up to ``RAMP_SECTORS`` sectors of ``MAX_SAMPLE`` returns spread over
  the whole scan (the other values come from the middle sector alone).
  Stated when the caller knows it. Positions of one scanner (the same angular
  steps) share its beam: ``pool_footprints`` gives them the mean over all their
  ramps, since a position beside a scene sees few edges (its own mean then rests on
  the phases of a handful of edges against its beams), and gives it to a position
  that shows no ramp at all.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from .mixed_grid import box_halfwidths, column_length, pulse_numbers, time_index

MAX_SAMPLE = 60_000  # points used for the neighbour statistics (a contiguous azimuth sector)
RAMP_SECTORS = 8  # most azimuth sectors of MAX_SAMPLE points the footprint is measured on
QUERY = 12_000  # of those, points whose neighbours give the spacing and noise medians
REGULAR = 0.5  # share of neighbour spacings within 25 % of the step for a scan grid
TRIM = 2.5  # residuals within ±TRIM sd of their mean give the scatter on a surface
# sd of a standard normal cut to ±TRIM: a trimmed sd divided by it is unbiased
TRIM_SD = math.sqrt(
    1.0
    - 2.0
    * TRIM
    * math.exp(-0.5 * TRIM**2)
    / math.sqrt(2.0 * math.pi)
    / math.erf(TRIM / math.sqrt(2.0))
)


@dataclass(frozen=True)
class ScanGeometry:
    """Measured geometry of one scan position (angles in degrees, lengths in metres)."""

    step_az: float
    step_el: float
    range_noise: float  # instrument noise, quantisation removed
    range_sigma: float  # total range scatter the filter sees (noise and quantisation)
    las_scale: float  # 0 when the coordinates are not quantised
    footprint: float  # beam footprint across the scan lines
    footprint_steps: float
    n_points: int
    how: dict[str, str] = field(default_factory=dict)
    # first and last azimuth, lowest and highest elevation of the position's returns, in
    # radians at full precision (beams beyond lie outside the field of view; a block of a
    # job holds only part of it); None: the returns at hand bound it
    field_of_view: tuple[float, float, float, float] | None = None
    footprint_edges: int = 0  # ramps the footprint was measured on (0: stated or none)
    # returns whose quantisation angle stays under a tenth of the step that the steps were
    # measured on; 0 when every angle was blurred past that (the steps then rest on blurred
    # spacings) or the steps came from the firing order
    sharp_returns: int = 0
    # returns per square radian of azimuth × elevation where the returns fill the view
    # (``angular_density``); 0 when not measured. A regular grid holds 1 / (step_az · step_el)
    density: float = 0.0
    # range scatter of returns on a surface: the residuals of ``range_sigma`` within ±TRIM
    # sd of their mean, iterated, corrected for the cut (``surface_scatter``); edges and
    # blends are left out, which the median residual holds. NaN: not measured
    surface_sigma: float = float("nan")

    @property
    def step(self) -> float:
        """The coarser of the two steps: the spacing every cell must hold."""
        return max(self.step_az, self.step_el)

    def angular_uncertainty(self, r: NDArray[np.float64] | float) -> NDArray[np.float64] | float:
        """Angle (degrees) of the LAS quantisation (sd of a uniform step) at range ``r``."""
        return np.degrees(self.las_scale / np.sqrt(12.0) / np.maximum(r, 1e-6))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ScanGeometry:
        """The geometry ``to_dict`` wrote (derived keys such as ``step`` are left out)."""
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        if kw.get("field_of_view") is not None:
            kw["field_of_view"] = tuple(float(v) for v in kw["field_of_view"])
        return cls(**kw)

    def to_dict(self) -> dict[str, object]:
        d = asdict(self)
        d["step"] = self.step
        if self.field_of_view is not None:
            d["field_of_view"] = [float(v) for v in self.field_of_view]
        for k, v in d.items():
            if isinstance(v, float):
                d[k] = float(f"{v:.6g}")
        return d


def measure_scan_geometry(
    rel: NDArray[np.float64],
    *,
    footprint: float | None = None,
    las_scale: float | None = None,
    absolute: NDArray[np.float64] | None = None,
    max_gap: float = 2.5,
    sectors: Sequence[NDArray[np.float64]] | None = None,
    gps_time: NDArray[np.float64] | None = None,
    lenders: Sequence[ScanGeometry] = (),
) -> ScanGeometry | None:
    """Measure the geometry of the points ``rel`` (relative to their sensor).

    ``absolute`` (the same points in file coordinates) is where the LAS scale is
    read; ``las_scale`` and ``footprint`` (degrees) override the measurements.
    ``sectors`` (points relative to the sensor) are the azimuth sectors the footprint
    is measured on (``ramp_sectors``); None cuts them from ``rel``, the whole scan.
    ``gps_time`` (one per point of ``rel``, or None) gives the steps from the firing
    order where the angles show no grid (``firing_steps``).
    ``lenders`` (other positions of the tile, best measured first) lend their steps where
    these angles show none (``lent_steps``).
    Returns None when there are too few points to measure anything.
    """
    rel = np.asarray(rel, dtype=np.float64)
    r = np.linalg.norm(rel, axis=1)
    valid = r > 1e-6
    n_kept = np.count_nonzero(valid)
    if n_kept < 50:
        return None
    keep: NDArray[np.bool_] | slice = valid if n_kept < r.size else slice(None)  # all: views
    rel, r = rel[keep], r[keep]
    t = None if gps_time is None else np.asarray(gps_time, dtype=np.float64)[keep]
    how: dict[str, str] = {}
    if las_scale is None:
        src = rel if absolute is None else np.asarray(absolute, np.float64)[keep]
        las_scale = coordinate_scale(src)
        how["las_scale"] = "smallest step dividing the differences of sorted coordinate values"
    else:
        how["las_scale"] = "stated"

    az = np.arctan2(rel[:, 1], rel[:, 0])
    el = np.arcsin(np.clip(rel[:, 2] / r, -1.0, 1.0))
    by_az = None  # the points' order by azimuth, when sorted already
    lines = None  # azimuth, elevation and range of each sector's points
    if sectors is None:
        # the footprint on sectors spread over the whole scan, not the sample's middle one:
        # a position looking past a scene another position stands in front of may show
        # no edge there (edges may lie anywhere); their angles are those found here
        o = by_az = np.argsort(az, kind="stable")
        lines = [(az[o[a:b]], el[o[a:b]], r[o[a:b]]) for a, b in ramp_sectors(az.size)]
    az, el, r, t = _sector(az, el, r, by_az, t)
    # one order whatever order the points came in (a job reads them block by block):
    # the samples drawn below then depend on the points alone
    o = np.lexsort((r, el, az))
    az, el, r = az[o], el[o], r[o]
    t = None if t is None else t[o]

    # First pass on the farthest half (quarter, tenth: with 1 cm coordinates at a 0.06°
    # step the nearer returns blur the spacings past any regular grid), then on every
    # point whose quantisation angle stays under a tenth of the step found.
    for share in (0.5, 0.25, 0.1):
        r_far = float(np.quantile(r, 1.0 - share))
        far = r >= r_far
        sa, se = _steps(az[far], el[far])
        if np.isfinite(sa) and np.isfinite(se):
            break
    fired = False
    if (not np.isfinite(sa) or not np.isfinite(se)) and t is not None:
        # every share blurred past the grid (1 cm coordinates, all returns within about
        # 10 m at a 0.035° step): the blur is zero-mean, so the mean angle change between
        # successive pulses still gives the step
        sa, se = firing_steps(t, az, el, las_scale, r)
        fired = bool(np.isfinite(sa) and np.isfinite(se))
    lent, lender = False, ""
    if (not np.isfinite(sa) or not np.isfinite(se)) and lenders:
        sa, se, lender = lent_steps(az, el, lenders)
        lent = bool(np.isfinite(sa) and np.isfinite(se))
    if not np.isfinite(sa) or not np.isfinite(se):
        return None
    sharp = 0.0  # returns nearer than this blur past a tenth of a step
    blurred = False  # no return sharp enough: the spacing was measured on blurred angles
    n_sharp = 0
    if fired or lent:
        ok = far
        sharp = r_far
        blurred = lent
    elif las_scale > 0:
        ok = las_scale / np.sqrt(12.0) / r < 0.1 * min(sa, se)
        if np.count_nonzero(ok) >= 50:
            sharp = las_scale / np.sqrt(12.0) / (0.1 * min(sa, se))
            sa2, se2 = _steps(az[ok], el[ok])
            if np.isfinite(sa2) and np.isfinite(se2):
                sa, se = sa2, se2
                n_sharp = int(np.count_nonzero(ok))
        else:
            ok = far
            sharp = r_far
            blurred = True
    else:
        ok = np.ones(r.size, dtype=bool)
        n_sharp = r.size
    blur = las_scale / np.sqrt(12.0) / r  # sd of each angle from the coordinate step
    if fired:
        how["step"] = (
            "firing order from GPS time (the angles, blurred by the LAS scale, show no grid): "
            "mean elevation change between successive pulses of a column and azimuth change "
            "between pulses one column length apart, refitted by least squares on every "
            "return's beam (column, row) from its pulse number"
        )
    elif lent:
        how["step"] = (
            f"lent by another position of the tile ({lender}): these angles show no grid "
            "(every return blurred past it by the LAS scale), and its steps give this "
            f"position's own returns per square radian within {LEND_TOL:.0%}, as they give "
            "its own"
        )
    else:
        ra, re_ = refine_step(az, sa, blur=blur), refine_step(el, se, blur=blur)
        if blurred and (ra == sa or re_ == se):
            # every angle blurred and no grid fits within 20 % of the spacing (1 cm
            # coordinates, all returns within 41 m at 0.03°: the spacing ran 37 % long):
            # the step is sought within the octave about the spacing, on the sectors
            # spread over the whole scan, whose farthest returns blur least
            lines = lines if lines is not None else [_angles(v) for v in sectors or ()]
            oa, oe = _octave_steps(
                np.concatenate([v[0] for v in lines]),
                np.concatenate([v[1] for v in lines]),
                np.concatenate([v[2] for v in lines]),
                las_scale,
                sa,
                se,
            )
            if ra == sa and np.isfinite(oa):
                ra = oa
                how["step_az"] = "octave about the spacing (no grid within 20 %)"
            if re_ == se and np.isfinite(oe):
                re_ = oe
                how["step_el"] = "octave about the spacing (no grid within 20 %)"
        sa, se = ra, re_
        how["step"] = (
            "median spacing to the nearest neighbour along azimuth / elevation in angle space, "
            f"on {int(np.count_nonzero(ok))} points whose quantisation angle is under 0.1 step, "
            "refined to the step whose grid the angles fit best over ever wider sectors "
            "(each angle weighted by the fit its quantisation blur allows)"
        )

    sigma, surface = _range_sigma(az[ok], el[ok], r[ok], sa, se)  # NaN when no line shows
    q2 = las_scale**2 / 12.0
    noise = float(np.sqrt(max(sigma**2 - q2, 0.0))) if np.isfinite(sigma) else float("nan")
    how["range_noise"] = (
        "robust sd of range residuals against the line through the two azimuth neighbours, "
        "LAS quantisation (scale²/12) removed"
    )
    how["surface_sigma"] = (
        f"sd of the same residuals within ±{TRIM:g} sd of their mean, iterated, corrected "
        "for the cut (edges and blends left out)"
    )

    edges = 0
    if footprint is not None:
        fp = float(footprint)
        steps = fp / np.degrees(sa)
        how["footprint"] = "stated"
    else:
        jump = max(6.0 * sigma, 0.03) if np.isfinite(sigma) else 0.05
        lines = lines if lines is not None else [_angles(v) for v in sectors or ()]
        steps, edges = _ramp_steps(lines, sa, se, jump, max_gap, sharp)
        on = ""
        if not np.isfinite(steps) and las_scale > 0:
            # Coarse coordinates at a fine step: too few sharp returns show an edge (1 cm at
            # 0.05-0.08°), so returns blurred by up to 0.15, then 0.2 step take part (those
            # the blur put off their beam are left out of the lines).
            for lim in (0.15, 0.2):
                near = las_scale / np.sqrt(12.0) / (lim * min(sa, se))
                steps, edges = _ramp_steps(lines, sa, se, jump, max_gap, near)
                if np.isfinite(steps):
                    on = f", on returns whose quantisation angle is under {lim:g} step"
                    break
            if not np.isfinite(steps):
                # every return blurred past that (1 cm within 18 m at 0.1°): each return
                # whose quantisation box spans under a step in both angles is put on the
                # line nearest it, the only line its box holds
                steps, edges = _ramp_steps(lines, sa, se, jump, max_gap, scale=las_scale)
                if np.isfinite(steps):
                    on = ", on returns whose quantisation box spans under a step"
        if np.isfinite(steps):
            how["footprint"] = (
                f"mean ramp of blended returns at range edges closer than {max_gap:g} m, "
                f"in steps{on}"
            )
        else:
            steps, edges = 1.0, 0
            how["footprint"] = "no mixing edge measured: one step assumed"
        steps = max(steps, 1.0)
        fp = steps * np.degrees(sa)
    return ScanGeometry(
        step_az=float(np.degrees(sa)),
        step_el=float(np.degrees(se)),
        range_noise=noise,
        range_sigma=float(sigma),
        las_scale=float(las_scale),
        footprint=float(fp),
        footprint_steps=float(steps),
        n_points=int(r.size),
        how=how,
        footprint_edges=int(edges),
        sharp_returns=n_sharp,
        density=angular_density(az, el, sa, se),
        surface_sigma=float(surface),
    )


DENSITY_CELL = 8  # steps across a cell of ``angular_density``
LEND_TOL = 0.04  # 1 / (step_az · step_el) against returns per square radian (2 × SAME_STEP)


def angular_density(
    az: NDArray[np.float64], el: NDArray[np.float64], sa: float, se: float
) -> float:
    """Returns per square radian of azimuth × elevation where they fill the view (0: none).

    Cells of ``DENSITY_CELL`` steps (``sa``, ``se``, radians) across the azimuths of the
    returns (a contiguous sector) less two steps at either end; a cell counts where it and
    its eight neighbours hold returns (inside a surface, not at the sky's edge); the mean
    count over those within 25 % of their median (a median of whole counts runs up to 1 %
    short). A regular grid of beams that all return holds 1 / (sa · se); the LAS scale's
    blur moves returns across cell borders both ways and leaves the count. Beams without
    a return (dark surfaces) lower it.
    """
    if az.size < 50 or not (np.isfinite(sa) and np.isfinite(se)) or sa <= 0 or se <= 0:
        return 0.0
    a0, a1 = float(az.min()) + 2.0 * sa, float(az.max()) - 2.0 * sa
    na = int((a1 - a0) // (DENSITY_CELL * sa))
    if na < 1:
        return 0.0
    ca, ce = (a1 - a0) / na, DENSITY_CELL * se
    inside = (az >= a0) & (az < a1)
    ia = np.minimum(((az[inside] - a0) / ca).astype(np.int64), na - 1)
    ie = ((el[inside] - float(el.min())) / ce).astype(np.int64)
    if ie.size == 0:
        return 0.0
    img = np.zeros((na, int(ie.max()) + 1), dtype=np.int64)
    np.add.at(img, (ia, ie), 1)
    full = img > 0
    inner = full.copy()
    inner[:, 0] = inner[:, -1] = False
    inner[:, 1:-1] &= full[:, :-2] & full[:, 2:]
    # the sector's first and last cells lie inside it: their outer side counts as held
    inner[1:, 1:-1] &= full[:-1, :-2] & full[:-1, 1:-1] & full[:-1, 2:]
    inner[:-1, 1:-1] &= full[1:, :-2] & full[1:, 1:-1] & full[1:, 2:]
    v = img[inner].astype(np.float64)
    if v.size < 10:
        return 0.0
    v = v[np.abs(v / np.median(v) - 1.0) <= 0.25]
    return float(v.mean() / (ca * ce))


def lenders(geos: Sequence[ScanGeometry | None]) -> list[ScanGeometry]:
    """The measured positions that may lend their steps, best measured first (most
    returns sharp to a tenth of a step, then most returns)."""
    have = [g for g in geos if g is not None]
    return sorted(have, key=lambda g: (-g.sharp_returns, -g.n_points))


def _holds(density: float, sa: float, se: float) -> bool:
    """Whether steps (radians) agree with returns per square radian within ``LEND_TOL``."""
    return density > 0 and abs(density * sa * se - 1.0) <= LEND_TOL


def lent_steps(
    az: NDArray[np.float64], el: NDArray[np.float64], lenders: Sequence[ScanGeometry]
) -> tuple[float, float, str]:
    """Steps (radians) of the first of ``lenders`` whose grid agrees with its own returns
    per square radian and with those of the angles ``az``, ``el`` (a position whose angles
    show no grid: 1 cm coordinates, every return within 10 m at a 0.035° step), with how
    that lender was measured; NaN when none does.

    The positions of a tile are taken as one scanner (as ``pool_footprints`` does). A
    lender's steps measured on blurred angles can run off (5 mm coordinates at 0.033°: 8 %
    short in azimuth) and would set this position's cells and boxes as far off; the count
    of returns per square radian checks the product of both steps, whatever their blur.
    """
    for g in lenders:
        sa, se = np.radians(g.step_az), np.radians(g.step_el)
        if not _holds(g.density, sa, se):
            continue
        if _holds(angular_density(az, el, sa, se), sa, se):
            n = g.sharp_returns
            on = f"on {n} sharp returns" if n else "on blurred returns"
            return float(sa), float(se), f"steps {on}"
    return float("nan"), float("nan"), ""


SAME_STEP = 0.02  # relative difference of two positions' steps still taken as one scanner


def pool_footprints(geos: Sequence[ScanGeometry | None]) -> list[ScanGeometry | None]:
    """The positions' footprints pooled over positions of one scanner.

    Positions whose steps (azimuth and elevation) agree within ``SAME_STEP`` are taken
    as one scanner with one beam; each measured footprint (not stated, at least one
    ramp) becomes the mean ramp over all of their edges. A position looking past a
    scene another stands in front of sees few edges: its own mean rests on where a
    handful of edges fell between its beams, and runs short by up to a step where the
    position facing the scene, on hundreds of edges, does not. Positions with another
    step, or a stated footprint, are left as they are. A position of the same steps
    that showed no ramp (one step assumed) takes the pooled mean too: it has the same
    beam.
    """
    out = list(geos)
    measured = {
        k: g
        for k, g in enumerate(geos)
        if g is not None and g.footprint_edges > 0 and g.how.get("footprint", "").startswith("mean")
    }
    unmeasured = {
        k: g
        for k, g in enumerate(geos)
        if g is not None
        and g.footprint_edges == 0
        and g.how.get("footprint", "").startswith("no mixing")
    }
    left = sorted(measured, key=lambda k: -measured[k].footprint_edges)

    def same(a: ScanGeometry, b: ScanGeometry) -> bool:
        return (
            abs(a.step_az / b.step_az - 1.0) < SAME_STEP
            and abs(a.step_el / b.step_el - 1.0) < SAME_STEP
        )

    while left:
        g = measured[left[0]]
        group = [j for j in left if same(measured[j], g)]
        left = [j for j in left if j not in group]
        bare = [j for j in unmeasured if same(unmeasured[j], g)]
        if len(group) + len(bare) < 2:
            continue
        n = sum(measured[j].footprint_edges for j in group)
        mean = sum(measured[j].footprint_steps * measured[j].footprint_edges for j in group) / n
        steps = max(mean, 1.0)
        for j in group:
            m = measured[j]
            how = {
                **m.how,
                "footprint": f"{m.how['footprint']}; pooled over the positions "
                f"{sorted(group)} of the same angular steps (one beam) on {n} ramps "
                f"(this position alone: {m.footprint_steps:.3g} steps on {m.footprint_edges})",
            }
            out[j] = replace(m, footprint_steps=steps, footprint=steps * m.step_az, how=how)
        for j in bare:
            m = unmeasured.pop(j)
            how = {
                **m.how,
                "footprint": f"mean ramp of the positions {sorted(group)} of the same angular "
                f"steps (one beam), on {n} ramps; none measured at this position",
            }
            out[j] = replace(m, footprint_steps=steps, footprint=steps * m.step_az, how=how)
    return out


def outside_azimuth(az: NDArray[np.float64]) -> float:
    """An azimuth in the widest empty arc between the returns' azimuths (radians): the
    field of view runs from the first return after it to the last before it."""
    a = np.sort(np.asarray(az, dtype=np.float64))
    if a.size == 0:
        return float(np.pi)
    gaps = np.diff(np.append(a, a[0] + 2 * np.pi))
    i = int(np.argmax(gaps))
    return float(a[i] + 0.5 * gaps[i])


def field_of_view(
    az: NDArray[np.float64], el: NDArray[np.float64], outside: float | None = None
) -> tuple[float, float, float, float]:
    """(first azimuth, last azimuth, lowest, highest elevation) of one position's returns,
    each the angle of a return itself (radians). Azimuths count anticlockwise from
    ``outside``, an azimuth in the empty arc beyond the field of view (the widest empty
    arc when None), so a scan across ±180° keeps its extent."""
    az = np.asarray(az, dtype=np.float64)
    el = np.asarray(el, dtype=np.float64)
    if az.size == 0:
        return (-np.pi, np.pi, -np.pi / 2, np.pi / 2)
    c = outside_azimuth(az) if outside is None else outside
    from_c = (az - c) % (2 * np.pi)
    return (
        float(az[np.argmin(from_c)]),
        float(az[np.argmax(from_c)]),
        float(el.min()),
        float(el.max()),
    )


def coordinate_scale(xyz: NDArray[np.float64], sample: int = 200_000) -> float:
    """LAS-like quantisation step of the coordinates (largest over the axes), 0 if none."""
    best = 0.0
    for col in range(3):
        # sorted values with their repeats: a repeat's zero difference is dropped below
        v = np.sort(xyz[:sample, col])
        d = np.diff(v)
        d = d[d > 1e-9]
        if d.size < 10:
            continue
        s0 = float(d.min())
        found = 0.0
        for k in range(1, 11):
            s = s0 / k
            q = d / s
            if np.mean(np.abs(q - np.round(q)) < 0.01) > 0.99:
                found = s
                break
        if found == 0.0 or found < 1e-7:
            return 0.0  # one axis not quantised: floating-point coordinates
        best = max(best, float(f"{found:.6g}"))
    return best


def _sector(az, el, r, by_az=None, t=None):
    """At most MAX_SAMPLE points from one contiguous azimuth sector (neighbours stay intact);
    ``by_az``: the stable order of ``az``, when known; ``t`` (times or None) follows."""
    if az.size <= MAX_SAMPLE:
        return az, el, r, t
    o = np.argsort(az, kind="stable") if by_az is None else by_az
    mid = az.size // 2
    sl = o[mid - MAX_SAMPLE // 2 : mid + MAX_SAMPLE // 2]
    return az[sl], el[sl], r[sl], None if t is None else t[sl]


def firing_steps(
    t: NDArray[np.float64],
    az: NDArray[np.float64],
    el: NDArray[np.float64],
    las_scale: float = 0.0,
    r: NDArray[np.float64] | None = None,
) -> tuple[float, float]:
    """Steps in azimuth and elevation (radians) from the firing order, or NaN.

    Successive pulses are neighbouring beams of one column, pulses one column length
    apart neighbouring beams of one row. The LAS scale blurs each angle (by half a
    step and more for 1 cm coordinates within about 10 m at a 0.035° step), but the
    blur of a difference is zero-mean: the mean change over many pairs is the step.
    Not the median: within about 5 m of 1 cm coordinates most successive pulses share
    one quantised angle, so the median change is 0. The jump back to the first row of
    the next column is left out as any change over a quarter of the elevations' span
    (no blur reaches that on a column of more than a few rows). The column length is
    found as ``time_index`` finds it; the mean azimuth change (a few % off: the
    quantised azimuths of a sector are few values) then only starts ``time_index``,
    whose least-squares fit on every return's beam gives both steps.
    """
    b = pulse_numbers(t)
    if b is None:
        return float("nan"), float("nan")
    o = np.argsort(b, kind="stable")
    bs, es, as_ = b[o], el[o], az[o]
    de = np.diff(es)[np.diff(bs) == 1]
    de = de[np.abs(de) < 0.25 * float(np.ptp(es))]
    if de.size < 50 or float(np.mean(de)) == 0:
        return float("nan"), float("nan")
    se = float(np.mean(de))
    # (pulse - elevation in steps) is about constant along a column and jumps by about a
    # column length at the next one
    dx = np.diff(bs - es / se)
    jump = dx[dx > 8.0]
    if jump.size < 4:
        return float("nan"), float("nan")
    per_col = column_length(bs, es, float(np.median(jump)), abs(se))
    if per_col < 2:
        return float("nan"), float("nan")
    j = np.minimum(np.searchsorted(bs, bs + per_col), bs.size - 1)
    hit = bs[j] == bs + per_col
    # pairs of the middle 80 % of the pulses: the points' sector was cut by blurred
    # azimuths, which keeps the nearer of two beams more often at its ends (a step 2 %
    # short on a sector of 60 columns, 1 % inside)
    lo, hi = np.quantile(bs, [0.1, 0.9])
    hit &= (bs >= lo) & (bs + per_col <= hi)
    if np.count_nonzero(hit) < 50:
        return float("nan"), float("nan")
    # a plain mean: at 1 cm within 5 m most pairs share one quantised azimuth, so
    # the median change is 0 (no trimming about it)
    sa = float(np.mean((as_[j[hit]] - as_[hit] + np.pi) % (2 * np.pi) - np.pi))
    if sa == 0:
        return float("nan"), float("nan")
    fit = time_index(t, az, el, abs(sa), abs(se), las_scale, r)
    if fit is None:
        return float("nan"), float("nan")
    return abs(fit[2]), abs(fit[3])


_LAST_TREE: list[tuple[NDArray[np.float64], cKDTree]] = []


def _tree(pts: NDArray[np.float64]) -> cKDTree:
    """The tree of ``pts``; the last one built is used again when the points are the
    same (the step and the range noise are measured on the same points one after the
    other, and a tree is as much time as its queries)."""
    last = _LAST_TREE[0] if _LAST_TREE else None
    if last is not None and last[0].shape == pts.shape and np.array_equal(last[0], pts):
        return last[1]
    tree = cKDTree(pts)
    _LAST_TREE[:] = [(pts, tree)]
    return tree


def _neighbours(az, el, k: int = 12, sample: int = QUERY):
    """Nearest neighbours in angle space of a sample of the points (all points form the
    tree, ``sample`` of them ask): medians of spacings and residuals need no more, and
    the lookups were most of the measurement's time. Returns the asking points' indices,
    their neighbours' indices and the angle differences to them."""
    u = az * np.cos(el)
    pts = np.column_stack([u, el])
    tree = _tree(pts)
    qi = np.arange(az.size)
    if az.size > sample:
        qi = np.sort(np.random.default_rng(0).choice(az.size, sample, replace=False))
    _, j = tree.query(pts[qi], k=min(k + 1, az.size))
    j = j[:, 1:]
    da = (az[j] - az[qi, None] + np.pi) % (2 * np.pi) - np.pi
    de = el[j] - el[qi, None]
    return qi, j, da, de


def _steps(az, el) -> tuple[float, float]:
    """Median nearest spacing along azimuth and along elevation (radians)."""
    if az.size < 20:
        return np.nan, np.nan
    qi, _, da, de = _neighbours(az, el)
    du = np.abs(da) * np.cos(el[qi])[:, None]
    adu, ade = np.abs(du), np.abs(de)
    along_a = adu > 2.0 * ade
    along_e = ade > 2.0 * adu
    # The nearest neighbour on one side only: the least of two noisy spacings runs short.
    sa = np.where(along_a & (da > 0), da, np.inf).min(axis=1)
    se = np.where(along_e & (de > 0), de, np.inf).min(axis=1)
    sa, se = sa[np.isfinite(sa) & (sa > 0)], se[np.isfinite(se) & (se > 0)]
    if sa.size < 10 or se.size < 10:
        return np.nan, np.nan
    ma, me = float(np.median(sa)), float(np.median(se))
    # Beams on scan lines: most spacings sit at the step. Scattered points (no
    # scanner grid, e.g. merged or resampled clouds) spread widely: no step.
    regular = min(np.mean(np.abs(sa / ma - 1) < 0.25), np.mean(np.abs(se / me - 1) < 0.25))
    if regular < REGULAR:
        return np.nan, np.nan
    return ma, me


def _range_sigma(az, el, r, sa, se) -> tuple[float, float]:
    """Robust sd of range about the line through the azimuth neighbours either side, and
    the scatter of returns on a surface (``surface_scatter``) of the same residuals."""
    nan = float("nan")
    if az.size < 20:
        return nan, nan
    qi, j, da, de = _neighbours(az, el, k=8)
    same_line = np.abs(de) < 0.25 * se
    left = np.where(same_line & (da < 0) & (da > -1.6 * sa), -da, np.inf)
    right = np.where(same_line & (da > 0) & (da < 1.6 * sa), da, np.inf)
    il, ir = left.argmin(axis=1), right.argmin(axis=1)
    rows = np.arange(qi.size)
    good = np.isfinite(left[rows, il]) & np.isfinite(right[rows, ir])
    if np.count_nonzero(good) < 20:
        return nan, nan
    jl, jr = j[rows, il][good], j[rows, ir][good]
    a_l, a_r = -left[rows, il][good], right[rows, ir][good]
    w = -a_l / (a_r - a_l)  # weight of the right neighbour at the point's angle
    pred = (1 - w) * r[jl] + w * r[jr]
    res = (r[qi][good] - pred) / np.sqrt(1.0 + w**2 + (1 - w) ** 2)
    mad = float(1.4826 * np.median(np.abs(res - np.median(res))))
    return mad, surface_scatter(res, mad)


def surface_scatter(res: NDArray[np.float64], sd: float, rounds: int = 8) -> float:
    """Sd of the residuals ``res`` on surfaces: those within ±TRIM × ``sd`` (a first
    estimate) of their mean, the mean and sd taken again on those kept until the sd
    settles (0.01 %), the sd divided by ``TRIM_SD`` (a normal cut to ±TRIM has that sd).

    Residuals at edges and of blends lie far out: the median absolute residual counts them
    as large ones and runs high (by 1.2× when 15 % of the returns have a neighbour across
    an edge), the trimmed sd leaves them out. ``sd`` when under 20 residuals are kept."""
    mid, s = float(np.median(res)), sd
    for _ in range(rounds):
        keep = res[np.abs(res - mid) < TRIM * s]
        if keep.size < 20:
            break
        mid, new = float(np.mean(keep)), float(np.std(keep)) / TRIM_SD
        done = abs(new - s) < 1e-4 * s
        s = new
        if done:
            break
    return s


def ramp_sectors(n: int) -> list[tuple[int, int]]:
    """Ranks (by azimuth) of the returns in the sectors the footprint is measured on:
    the scan cut into contiguous sectors of at most MAX_SAMPLE returns, up to
    RAMP_SECTORS of them spread evenly over it (a job takes the same ranks)."""
    m = max(1, int(np.ceil(n / MAX_SAMPLE)))
    bounds = np.linspace(0, n, m + 1).astype(np.int64)
    pick = np.unique(np.round(np.linspace(0, m - 1, min(m, RAMP_SECTORS))).astype(np.int64))
    return [(int(bounds[i]), int(bounds[i + 1])) for i in pick]


def _angles(rel: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
    """Azimuth, elevation and range of points relative to the sensor."""
    r = np.linalg.norm(rel, axis=1)
    keep = r > 1e-6
    rel, r = rel[keep], r[keep]
    return np.arctan2(rel[:, 1], rel[:, 0]), np.arcsin(np.clip(rel[:, 2] / r, -1.0, 1.0)), r


def _ramp_steps(
    sectors: Sequence[tuple[NDArray, NDArray, NDArray]],
    sa: float,
    se: float,
    jump: float,
    max_gap: float,
    nearest: float = 0.0,
    scale: float = 0.0,
) -> tuple[float, int]:
    """Mean number of beams blended between two surfaces at azimuth edges (NaN if fewer
    than 5 edges show one) and the number of edges, pooled over azimuth sectors (each with its own grid phase,
    so a step refined on one sector does not drift off the lines of a far one); returns
    nearer than ``nearest`` (blurred by the LAS scale) are left out. ``scale`` > 0: the
    returns placed by their quantisation boxes instead (``_ramps``)."""
    found = []
    for az, el, r in sectors:
        sel = r >= nearest
        found.append(_ramps(az[sel], el[sel], r[sel], sa, se, jump, max_gap, scale))
    ramps = np.concatenate(found) if found else np.zeros(0)
    if ramps.size < 5:
        return float("nan"), 0
    return float(np.mean(ramps)), int(ramps.size)


def _ramps(
    az, el, r, sa, se, jump: float, max_gap: float, scale: float = 0.0
) -> NDArray[np.float64]:
    """Numbers of beams blended between two surfaces at the azimuth edges of one sector.

    ``scale`` > 0: the returns whose LAS quantisation box spans under a step in both
    angles (half-widths ``box_halfwidths`` under half a step) are put on their nearest
    lines, the only ones their boxes hold; the grid's phase and the 80 % test are taken
    on those whose boxes span under half a step."""
    none = np.zeros(0)
    if scale > 0:
        ha, he = box_halfwidths(az, el, r, scale)
        placed = (ha < 0.5 * sa) & (he < 0.5 * se)
        az, el, r = az[placed], el[placed], r[placed]
        fine = (ha[placed] < 0.25 * sa) & (he[placed] < 0.25 * se)
    else:
        fine = np.ones(az.size, dtype=bool)
    if az.size < 3 or np.count_nonzero(fine) < 3:
        return none
    phase_a = _phase(az[fine], sa)
    phase_e = _phase(el[fine], se)
    ca = np.round((az - phase_a) / sa).astype(np.int64)
    ce = np.round((el - phase_e) / se).astype(np.int64)
    on_grid = (np.abs((az - phase_a) / sa - ca) < 0.25) & (np.abs((el - phase_e) / se - ce) < 0.25)
    if np.count_nonzero(on_grid & fine) < 0.8 * np.count_nonzero(fine):
        return none  # not a regular grid: ramps cannot be followed along lines
    if scale > 0:
        on_grid = np.ones(az.size, dtype=bool)
    ca, ce, r = ca[on_grid], ce[on_grid], r[on_grid]
    o = np.lexsort((ca, ce))
    ca, ce, r = ca[o], ce[o], r[o]
    adj = (ce[1:] == ce[:-1]) & (ca[1:] == ca[:-1] + 1)
    J = np.where(adj, np.diff(r), 0.0)
    big = np.abs(J) > jump
    sgn = np.sign(J) * big
    # Runs of consecutive same-sign big jumps: a ramp of (length - 1) blended returns.
    start = big & np.r_[True, sgn[1:] != sgn[:-1]]
    run_id = np.cumsum(start) - 1
    ids = run_id[big]
    if ids.size == 0:
        return none
    length = np.bincount(ids)
    total = np.abs(np.bincount(ids, weights=J[big]))
    first = np.flatnonzero(start)
    last = first + length - 1
    # Flanks: the jumps just before and after the run are small (surfaces either side).
    lim = 0.3 * total / length
    before, after = np.maximum(first - 1, 0), np.minimum(last + 1, J.size - 1)
    ok_flank = (first > 0) & (last < J.size - 1)
    ok_flank &= (np.abs(J[before]) < lim) & (np.abs(J[after]) < lim)
    ok_flank &= adj[before] & adj[after]
    # Each flank a surface of at least three beams (two small jumps): a pole narrower
    # than the footprint shows a plateau of blends about footprint - width + 1 beams wide
    # between ramps about its width long, which ran the mean short (0.74-0.84 of the
    # true footprint on seen scans at 0.11-0.12° steps)
    b2, a2 = np.maximum(first - 2, 0), np.minimum(last + 2, J.size - 1)
    ok_flank &= (first >= 2) & (last + 2 <= J.size - 1)
    ok_flank &= (np.abs(J[b2]) < lim) & (np.abs(J[a2]) < lim) & adj[b2] & adj[a2]
    # Edges with no blended beam are left out: there a third surface far behind (ground
    # or nothing) shared the footprint and the nearest surface answered alone, which
    # says nothing about the footprint's width (counting them ran 10–55 % short).
    edges = ok_flank & (total > 0.2) & (total < max_gap) & (length >= 2) & (length <= 8)
    return (length[edges] - 1).astype(np.float64)


def refine_step(
    a: NDArray[np.float64],
    s0: float,
    sample: int = 20_000,
    blur: NDArray[np.float64] | float = 0.0,
    weight: NDArray[np.float64] | None = None,
    width: float = 0.2,
) -> float:
    """The step of the regular grid the angles ``a`` (radians) fit best, within 20 % of ``s0``.

    The fit of a grid is the coherence |mean exp(2πi a/s)|, whose peak narrows as
    1/(number of lines covered): a step off by 0.5 % drifts a whole line over 200
    lines. So the step is searched on ever wider sectors around the median angle,
    each search within the previous one's resolution. ``blur`` (the sd of each angle,
    radians: the LAS scale over range) weights each angle by the coherence its blur
    leaves, exp(-2π²(blur/s)²): with 1 cm coordinates at a 0.06° step the near points
    are blurred by a third of a step and the nearest-neighbour spacing ``s0`` runs up to
    8 % long. Returns ``s0`` when no grid fits. ``weight`` (one per angle) replaces the
    weights from ``blur``; ``width`` is the first search's half-width (relative).
    """
    a = np.asarray(a, dtype=np.float64)
    if a.size < 50 or not np.isfinite(s0) or s0 <= 0:
        return s0
    if weight is None:
        w = np.exp(-2.0 * np.pi**2 * (np.broadcast_to(blur, a.shape) / s0) ** 2)
    else:
        w = np.asarray(weight, dtype=np.float64)
    use = w > 0.2  # angles blurred by more than 0.29 step carry no grid
    if np.count_nonzero(use) < 50:
        return s0
    a, w = a[use], w[use]
    if a.size > sample:
        pick = np.random.default_rng(0).choice(a.size, sample, replace=False)
        a, w = a[pick], w[pick]
    c = float(np.median(a))
    s = s0
    span = float(np.max(np.abs(a - c)))
    covered = False
    for lines in (50, 500, 5_000, 50_000, 500_000):
        inside = np.abs(a - c) <= lines * s / 2
        sel, ws = a[inside], w[inside]
        if sel.size < 50:
            continue
        # candidates evenly spaced in frequency
        freq = (1.0 + np.linspace(-width, width, 81)) / s
        coh = _coherence(sel - c, ws, freq)
        best = int(np.argmax(coh))
        if coh[best] < 0.3:
            return s0
        s, width = float(1.0 / freq[best]), 1.0 / lines
        if covered:
            break
        # once the sector holds every angle, one more search within this one's resolution
        covered = lines * s / 2 >= span
    return s


def _coherence(
    x: NDArray[np.float64], w: NDArray[np.float64], freq: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Weighted coherence |Σ w exp(2πi x f)| / Σ w of the angles ``x`` at each of the
    evenly spaced frequencies ``freq``: exp(2πi x f) at the next frequency is the last
    one times exp(2πi x df), a product instead of an exponential."""
    z = w * np.exp(2j * np.pi * x * freq[0])  # weighted: the product keeps the weight
    dz = np.exp(2j * np.pi * x * (freq[1] - freq[0]))
    coh = np.empty(freq.size)
    total = float(w.sum())
    for k in range(freq.size):
        coh[k] = abs(z.sum()) / total
        z *= dz
    return coh


def octave_step(
    a: NDArray[np.float64],
    s0: float,
    per_metre: NDArray[np.float64],
    scale: float,
    lines: int = 50,
    sample: int = 20_000,
) -> float:
    """The step (radians) in the octave [s0/√2, s0·√2] whose grid the angles ``a`` fit
    best on the ``lines`` lines about their median, or NaN when none fits.

    Where every angle is blurred (1 cm coordinates, all returns within about 40 m at a
    0.03° step) the nearest-neighbour spacing ``s0`` runs 7-40 % off, past the 20 % that
    ``refine_step`` searches. A grid of step S also fits S/2, S/3 ... (each of its lines
    is one of theirs) and no multiple k·S (its lines fall on every phase of those): an
    octave holds S and neither S/2 nor 2·S, so its best fit is the step wherever s0 lies
    within √2 of it. Every angle is weighted by the coherence its quantisation box keeps
    at the octave's finest step (``box_weights`` from ``per_metre``, the angle's change
    per metre of each coordinate), so that each angle kept carries the grid whichever
    step in the octave is the true one, and left out under 0.2 as in ``refine_step``.
    Candidates lie a quarter of the fit's peak width (1/lines, relative) apart.
    """
    f0, f1 = 1.0 / (np.sqrt(2.0) * s0), np.sqrt(2.0) / s0
    w = box_weights(per_metre, scale, 1.0 / f1)  # at the finest candidate
    use = w > 0.2
    if np.count_nonzero(use) < 50:
        return float("nan")
    a, w = a[use], w[use]
    if a.size > sample:
        pick = np.random.default_rng(0).choice(a.size, sample, replace=False)
        a, w = a[pick], w[pick]
    c = float(np.median(a))
    inside = np.abs(a - c) <= lines * s0 / 2
    x, w = a[inside] - c, w[inside]
    if x.size < 50:
        return float("nan")
    freq = np.linspace(f0, f1, int(np.ceil(4.0 * lines * (f1 - f0) * s0)) + 1)
    coh = _coherence(x, w, freq)
    best = int(np.argmax(coh))
    return float(1.0 / freq[best]) if coh[best] >= 0.3 else float("nan")


def _octave_steps(
    az: NDArray[np.float64],
    el: NDArray[np.float64],
    r: NDArray[np.float64],
    scale: float,
    sa: float,
    se: float,
) -> tuple[float, float]:
    """Both steps where every angle is blurred: ``octave_step`` from the spacings, then
    ``refine_step`` within that search's resolution, each angle weighted by its box's
    coherence at the step found. NaN for an axis whose octave shows no grid."""
    out = []
    for a, s0, g in ((az, sa, _per_metre_az(az, el, r)), (el, se, _per_metre_el(az, el, r))):
        s1 = octave_step(a, s0, g, scale)
        if not np.isfinite(s1):
            out.append(float("nan"))
            continue
        out.append(refine_step(a, s1, weight=box_weights(g, scale, s1), width=1.0 / 50))
    return out[0], out[1]


def _per_metre_az(az, el, r) -> NDArray[np.float64]:
    """Change of azimuth (radians) per metre of x and of y: |sin az|/ρ, |cos az|/ρ."""
    rho = np.maximum(r * np.cos(el), 1e-6)
    return np.column_stack([np.abs(np.sin(az)) / rho, np.abs(np.cos(az)) / rho])


def _per_metre_el(az, el, r) -> NDArray[np.float64]:
    """Change of elevation (radians) per metre of z, x and y: cos el/r,
    |sin el|·|cos az|/r, |sin el|·|sin az|/r."""
    rr = np.maximum(r, 1e-6)
    se_ = np.abs(np.sin(el))
    return np.column_stack(
        [np.cos(el) / rr, se_ * np.abs(np.cos(az)) / rr, se_ * np.abs(np.sin(az)) / rr]
    )


def box_weights(per_metre: NDArray[np.float64], scale: float, s: float) -> NDArray[np.float64]:
    """Coherence |E exp(2πi δ/s)| an angle keeps at step ``s`` under the LAS rounding of
    its coordinates (``per_metre``: the angle's change per metre of each coordinate).

    Each coordinate is off by a uniform error of width ``scale``, whose coherence is
    sinc(scale·g/s) for an angle moving by g per metre of it; the errors are independent,
    so the coherences multiply. Negative past one step (a box wider than the step keeps
    no grid). The Gaussian exp(-2π²(σ/s)²) of the same sd is up to twice as high where
    the box spans most of a step (20-30 m for 1 cm at 0.03°): it weighted those returns
    as if they carried the grid.
    """
    return np.prod(np.sinc(scale * per_metre / s), axis=1)


def _phase(a: NDArray[np.float64], s: float) -> float:
    """Offset of a regular angular grid of step ``s`` (circular mean of a mod s)."""
    t = 2 * np.pi * a / s
    return float(np.angle(np.mean(np.exp(1j * t))) / (2 * np.pi) * s)
