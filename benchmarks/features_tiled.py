"""Terrain objects searched core by core against one search over the whole DTM.

Each scene: a mosaic of ``--mosaic`` × ``--mosaic`` feature-family scenes (320 m
each, seeds drawn in turn; exact surfaces plus 2 cm noise; the seams between
scenes are steps, which make more objects along core edges), cut into ``--cores``
× ``--cores`` cores. The whole DTM is searched once (``categories_for`` +
``detect_features``) and core by core (``tiled.search_core`` with the default
halo, then ``merge_pieces``). Reported per scene: objects of each, how many match
one to one (kind, tiles, centroid within 1 mm), the largest Hausdorff distance
and length/width difference between matched objects, and the peak memory traced
(numpy included) of the whole search against the largest core's, and the largest
window a core's search read (a share of the DTM).

    .venv/bin/python benchmarks/features_tiled.py [--scenes 3] [--mosaic 2] [--cores 4]
        [--cap M] [--simplify T]

``--cap`` searches with a capped window (``tiled.search_core``'s cap, metres): objects
larger than it are searched in parts and joined. Each object of the whole search is
then also paired with the tiled object of its kind it overlaps most: the worst
Hausdorff distance, area difference (share of the object) and length difference
over the pairs, and the objects left unpaired on either side. ``--simplify``: the
outlines' simplification in tiles (default 0.5; 0 compares the exact tile outlines).
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np
from rasterio import Affine

from terrasift.synthetic.feature_family import make_family_scene, surface_raster
from terrasift.workers.categories import CategoryParams, measure_noise, measure_slope_noise
from terrasift.workers.features import (
    DtmHeights,
    FeatureParams,
    categories_for,
    detect_features,
    resolve_filters,
)
from terrasift.workers.features.tiled import merge_pieces, search_core

CELL = 0.5


def _key(f) -> tuple:
    c = f.geometry.centroid
    return (f.kind, f.tiles, round(c.x, 3), round(c.y, 3))


def _paired(whole: list, tiled: list) -> dict:
    """Each whole-search object with the tiled one of its kind it overlaps most."""
    hd = da = dl = 0.0
    used: set[int] = set()
    for x in whole:
        best, area = None, 0.0
        for k, y in enumerate(tiled):
            if y.kind == x.kind and k not in used:
                a = x.geometry.intersection(y.geometry).area
                if a > area:
                    best, area = k, a
        if best is None:
            continue
        used.add(best)
        y = tiled[best]
        hd = max(hd, x.geometry.hausdorff_distance(y.geometry))
        da = max(da, x.geometry.symmetric_difference(y.geometry).area / x.geometry.area)
        dl = max(dl, abs(x.length_m - y.length_m), abs(x.width_m - y.width_m))
    return {
        "paired": len(used),
        "unpaired_whole": len(whole) - len(used),
        "unpaired_tiled": len(tiled) - len(used),
        "pair_hausdorff_m": hd,
        "pair_area_diff": da,
        "pair_size_diff_m": dl,
    }


def one(
    seed: int, mosaic: int, cores: int, cap_m: float | None = None, simplify: float = 0.5
) -> dict:
    seeds = [seed * mosaic * mosaic + i for i in range(mosaic * mosaic)]
    parts = [surface_raster(make_family_scene(s), CELL) for s in seeds]
    dtm = np.concatenate(
        [np.concatenate(parts[i * mosaic : (i + 1) * mosaic], axis=1) for i in range(mosaic)]
    )
    dtm = dtm + np.random.default_rng(seed).normal(0, 0.02, dtm.shape)
    t = Affine(CELL, 0, 500_000.0, 0, -CELL, 5_400_000.0)
    filters = resolve_filters("all")
    cp = CategoryParams()
    cp = cp.model_copy(
        update={
            "noise": measure_noise(dtm, CELL, cp),
            "slope_noise": measure_slope_noise(dtm, CELL, cp),
        }
    )
    tracemalloc.start()
    t0 = time.process_time()
    cats, stepped = categories_for(dtm, CELL, filters, cp)
    fp = FeatureParams(simplify_tiles=simplify)
    cap = None if cap_m is None else int(round(cap_m / CELL))
    whole = detect_features(cats, filters, t, cats.tile_size, fp, stepped=stepped, dtm=dtm).objects
    del cats, stepped
    whole_cpu = time.process_time() - t0
    _, whole_peak = tracemalloc.get_traced_memory()
    edges = np.linspace(0, dtm.shape[0], cores + 1).astype(int)
    pieces = []
    core_peak = 0
    windows: list[float] = []
    t0 = time.process_time()
    for i in range(cores):
        for j in range(cores):
            tracemalloc.reset_peak()
            base, _ = tracemalloc.get_traced_memory()
            core = (edges[i], edges[j], edges[i + 1], edges[j + 1])
            found, seen = search_core(
                lambda a, b, c, d: dtm[a:b, c:d], dtm.shape, t, core, filters, cp, fp, cap=cap
            )
            pieces += found
            windows.append((seen[2] - seen[0]) * (seen[3] - seen[1]) / dtm.size)
            core_peak = max(core_peak, tracemalloc.get_traced_memory()[1] - base)
    cut = sum(p.cut is not None for p in pieces)
    tiled = merge_pieces(pieces, filters, cp, CELL, fp, dtm=DtmHeights.of(dtm, t)).objects
    tiled_cpu = time.process_time() - t0
    tracemalloc.stop()
    a, b = sorted(whole, key=_key), sorted(tiled, key=_key)
    ka, kb = [_key(f) for f in a], [_key(f) for f in b]
    matched = ka == kb
    hd = dl = 0.0
    if matched:
        hd = max(
            (x.geometry.hausdorff_distance(y.geometry) for x, y in zip(a, b, strict=True)),
            default=0.0,
        )
        dl = max(
            (
                max(abs(x.length_m - y.length_m), abs(x.width_m - y.width_m))
                for x, y in zip(a, b, strict=True)
            ),
            default=0.0,
        )
    return {
        "seed": seed,
        "size_m": dtm.shape[0] * CELL,
        "core_m": dtm.shape[0] * CELL / cores,
        "whole": len(a),
        "tiled": len(b),
        "matched": matched,
        "hausdorff_m": hd,
        "size_diff_m": dl,
        "whole_peak_mib": whole_peak / 2**20,
        "core_peak_mib": core_peak / 2**20,
        "cpu_ratio": tiled_cpu / max(whole_cpu, 1e-9),
        "cut_pieces": cut,
        "largest_window": max(windows),
        "cores_within": sum(w < 1.0 for w in windows),
        **_paired(a, b),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--start", type=int, default=0, help="first scene (seed)")
    ap.add_argument("--mosaic", type=int, default=2)
    ap.add_argument("--cores", type=int, default=4)
    ap.add_argument("--cap", type=float, default=None, help="metres (default: none)")
    ap.add_argument("--simplify", type=float, default=0.5, help="tiles")
    args = ap.parse_args()
    rows = []
    for seed in range(args.start, args.start + args.scenes):
        r = one(seed, args.mosaic, args.cores, args.cap, args.simplify)
        rows.append(r)
        print(
            f"scene {seed}: {r['size_m']:.0f} m in cores of {r['core_m']:.0f} m; objects whole "
            f"{r['whole']} tiled {r['tiled']} matched {r['matched']}; hausdorff "
            f"{r['hausdorff_m']:.2e} m, size diff {r['size_diff_m']:.2e} m; peak memory whole "
            f"{r['whole_peak_mib']:.0f} MiB, largest core {r['core_peak_mib']:.0f} MiB; "
            f"CPU tiled/whole {r['cpu_ratio']:.2f}; {r['cut_pieces']} pieces searched in parts; "
            f"largest window {100 * r['largest_window']:.0f} % of the DTM, "
            f"{r['cores_within']} of {args.cores**2} cores' windows within it; "
            f"paired {r['paired']} (unpaired whole {r['unpaired_whole']}, tiled "
            f"{r['unpaired_tiled']}): hausdorff {r['pair_hausdorff_m']:.2f} m, area diff "
            f"{100 * r['pair_area_diff']:.2f} %, size diff {r['pair_size_diff_m']:.2f} m",
            flush=True,
        )
    print(
        f"matched in {sum(r['matched'] for r in rows)} of {len(rows)} scenes, "
        f"{sum(r['whole'] for r in rows)} objects; worst hausdorff "
        f"{max(r['hausdorff_m'] for r in rows):.2e} m"
    )
    for k, unit, f in (
        ("pair_hausdorff_m", "m", 1.0),
        ("pair_area_diff", "%", 100.0),
        ("pair_size_diff_m", "m", 1.0),
    ):
        v = np.array([r[k] for r in rows]) * f
        print(
            f"paired {k}: worst {v.max():.3f} {unit}, p90 {np.percentile(v, 90):.3f}, "
            f"median {np.median(v):.3f} over {len(rows)} scenes"
        )
    print(
        f"unpaired: whole {sum(r['unpaired_whole'] for r in rows)}, "
        f"tiled {sum(r['unpaired_tiled'] for r in rows)}"
    )


if __name__ == "__main__":
    main()
