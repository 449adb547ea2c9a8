"""Roads with ditches along them: are both found?

The feature family (``terrasift.synthetic.feature_family``) places roads and ditches at
least 10 m apart, but real roads very often drain into a ditch at the foot of a shoulder,
on one side or both. This draws such scenes with the family's own road and ditch profiles
(a flat top ``offset`` above or below the ground with 1.5 : 1 shoulders plus 0.5 m, and
trapezoid ditches with a floor 0.3 of their half-width) and runs the categories and every
built-in filter on the exact DTM plus noise, as ``--part rerun`` of
``features_accuracy.py`` does on job DTMs.

A road counts as found when a road detection lies half within 2 m of it; a ditch when a
ditch detection does (the family's ``_on`` rule). Controls without ditches show what the
road alone gives. Run it from each checkout to compare codes:

    python benchmarks/features_roadside.py [--noise 0.02] [--angle 23]
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np
from numpy.typing import NDArray
from rasterio import Affine
from shapely.geometry import LineString, Polygon

from terrasift.workers.features import categories_for, detect_features, resolve_filters

CELL = 0.5  # m, the job's default DTM resolution
SIZE = 240.0  # m, scene edge
LENGTH = 200.0  # m, road and ditch length
WIDTH = 5.0  # m, road top

SLOPES = (0.0, 0.03, 0.10)  # level, gentle, hillside (across the road)
OFFSETS = (0.0, 0.3, 0.8, 1.5, -0.5)  # top above (+, embankment) or below (-, cut) the ground
# ditch across the top (m), depth (m), gap from the shoulder's foot (m)
DITCHES = ((1.5, 0.4, 0.0), (3.0, 0.8, 1.0))
SIDES = ((), (1,), (-1,), (-1, 1))


def scene(
    slope: float,
    offset: float,
    sides: tuple[int, ...],
    ditch: tuple[float, float, float],
    noise: float,
    angle: float,
    seed: int,
) -> tuple[NDArray[np.float64], Polygon, list[Polygon]]:
    """DTM of one road with ``sides`` ditches, and the truth polygons (road, ditches)."""
    n = int(SIZE / CELL)
    c = (np.arange(n) + 0.5) * CELL
    x, y = np.meshgrid(c, SIZE - c)
    ux, uy = np.cos(angle), np.sin(angle)
    across = -(x - SIZE / 2) * uy + (y - SIZE / 2) * ux
    along = (x - SIZE / 2) * ux + (y - SIZE / 2) * uy
    ground = 100.0 + slope * across
    half = WIDTH / 2
    shoulder = 1.5 * (abs(offset) + slope * half) + 0.5
    t = np.clip((np.abs(across) - half) / shoulder, 0, 1)
    top = 100.0 + offset
    z = np.where(np.abs(along) <= LENGTH / 2, top + t * (ground - top), ground)
    width, depth, gap = ditch
    dh = width / 2
    ditches = []
    for sd in sides:
        mid = sd * (half + shoulder + gap + dh)
        cut = depth * np.clip((dh - np.abs(across - mid)) / (0.7 * dh), 0, 1)
        z = z - np.where(np.abs(along) <= LENGTH / 2, cut, 0.0)
        ditches.append(_strip(mid, dh, ux, uy))
    z = z + np.random.default_rng(seed).normal(0, noise, z.shape)
    return z, _strip(0.0, half, ux, uy), ditches


def _strip(mid: float, half: float, ux: float, uy: float) -> Polygon:
    """The ``LENGTH`` long strip ``half`` either side of the line ``mid`` across the centre."""
    cx, cy = SIZE / 2 - mid * uy, SIZE / 2 + mid * ux
    a = (cx - ux * LENGTH / 2, cy - uy * LENGTH / 2)
    b = (cx + ux * LENGTH / 2, cy + uy * LENGTH / 2)
    return LineString([a, b]).buffer(half, cap_style="flat")


def _on(g: Polygon, truth: Polygon) -> bool:
    return g.intersection(truth.buffer(2)).area >= 0.5 * g.area


def found(dtm: NDArray[np.float64], road: Polygon, ditches: list[Polygon]) -> tuple[bool, int]:
    """Whether the road is found, and how many of ``ditches`` are."""
    filters = resolve_filters("all")
    cats, stepped = categories_for(dtm, CELL, filters)
    transform = Affine(CELL, 0, 0, 0, -CELL, SIZE)
    objects = detect_features(
        cats, filters, transform, cats.tile_size, stepped=stepped, dtm=dtm
    ).objects
    roads = [o.geometry for o in objects if o.kind == "road"]
    mine = [o.geometry for o in objects if o.kind == "ditch"]
    return any(_on(g, road) for g in roads), sum(any(_on(g, d) for g in mine) for d in ditches)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--noise", type=float, default=0.02, help="DTM noise sd (m)")
    ap.add_argument("--angle", type=float, default=23.0, help="road's angle to the grid (°)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    t0 = time.process_time()
    tally: dict[str, list[int]] = {}
    print(f"{'slope':>5} {'offset':>6} {'ditches':>8} {'ditch':>11}  road  ditches found")
    for slope, offset, sides, ditch in itertools.product(SLOPES, OFFSETS, SIDES, DITCHES):
        if not sides and ditch != DITCHES[0]:
            continue  # one control per road
        dtm, road, ditches = scene(
            slope, offset, sides, ditch, args.noise, np.radians(args.angle), args.seed
        )
        road_found, ditches_found = found(dtm, road, ditches)
        label = "control" if not sides else "with ditch"
        t = tally.setdefault(label, [0, 0, 0, 0])
        t[0] += 1
        t[1] += int(road_found)
        t[2] += len(ditches)
        t[3] += ditches_found
        where = {(): "none", (1,): "one", (-1,): "other", (-1, 1): "both"}[sides]
        size = f"{ditch[0]:g}x{ditch[1]:g}+{ditch[2]:g}" if sides else "-"
        print(
            f"{slope:5.2f} {offset:+6.1f} {where:>8} {size:>11}  {'yes' if road_found else 'no':>4}"
            f"  {ditches_found} of {len(ditches)}"
        )
    for label, (cases, roads, truth, hits) in tally.items():
        print(f"{label}: road found in {roads} of {cases}; ditches found {hits} of {truth}")
    print(f"CPU {time.process_time() - t0:.0f} s")


if __name__ == "__main__":
    main()
