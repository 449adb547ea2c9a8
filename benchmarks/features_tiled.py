"""Terrain objects searched core by core against one search over the whole DTM.

Each scene: a mosaic of ``--mosaic`` × ``--mosaic`` feature-family scenes (320 m
each, seeds drawn in turn; exact surfaces plus 2 cm noise; the seams between
scenes are steps, which make more objects along core edges), cut into ``--cores``
× ``--cores`` cores. The whole DTM is searched once (``categories_for`` +
``detect_features``) and core by core (``tiled.tile_pieces`` with the default
halo, then ``merge_pieces``). Reported per scene: objects of each, how many match
one to one (kind, tiles, centroid within 1 mm), the largest Hausdorff distance
and length/width difference between matched objects, and the peak memory traced
(numpy included) of the whole search against the largest core's.

    .venv/bin/python benchmarks/features_tiled.py [--scenes 3] [--mosaic 2] [--cores 4]
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np
from rasterio import Affine

from terrasift.synthetic.feature_family import make_family_scene, surface_raster
from terrasift.workers.categories import CategoryParams, measure_noise, measure_slope_noise
from terrasift.workers.features import categories_for, detect_features, resolve_filters
from terrasift.workers.features.tiled import merge_pieces, tile_pieces

CELL = 0.5


def _key(f) -> tuple:
    c = f.geometry.centroid
    return (f.kind, f.tiles, round(c.x, 3), round(c.y, 3))


def one(seed: int, mosaic: int, cores: int) -> dict:
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
    whole = detect_features(cats, filters, t, cats.tile_size, stepped=stepped).objects
    del cats, stepped
    whole_cpu = time.process_time() - t0
    _, whole_peak = tracemalloc.get_traced_memory()
    edges = np.linspace(0, dtm.shape[0], cores + 1).astype(int)
    pieces = []
    core_peak = 0
    t0 = time.process_time()
    for i in range(cores):
        for j in range(cores):
            tracemalloc.reset_peak()
            base, _ = tracemalloc.get_traced_memory()
            core = (edges[i], edges[j], edges[i + 1], edges[j + 1])
            pieces += tile_pieces(lambda a, b, c, d: dtm[a:b, c:d], dtm.shape, t, core, filters, cp)
            core_peak = max(core_peak, tracemalloc.get_traced_memory()[1] - base)
    tiled = merge_pieces(pieces, filters, cp, CELL).objects
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
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--mosaic", type=int, default=2)
    ap.add_argument("--cores", type=int, default=4)
    args = ap.parse_args()
    rows = []
    for seed in range(args.scenes):
        r = one(seed, args.mosaic, args.cores)
        rows.append(r)
        print(
            f"scene {seed}: {r['size_m']:.0f} m in cores of {r['core_m']:.0f} m; objects whole "
            f"{r['whole']} tiled {r['tiled']} matched {r['matched']}; hausdorff "
            f"{r['hausdorff_m']:.2e} m, size diff {r['size_diff_m']:.2e} m; peak memory whole "
            f"{r['whole_peak_mib']:.0f} MiB, largest core {r['core_peak_mib']:.0f} MiB; "
            f"CPU tiled/whole {r['cpu_ratio']:.2f}",
            flush=True,
        )
    print(
        f"matched in {sum(r['matched'] for r in rows)} of {len(rows)} scenes, "
        f"{sum(r['whole'] for r in rows)} objects; worst hausdorff "
        f"{max(r['hausdorff_m'] for r in rows):.2e} m"
    )


if __name__ == "__main__":
    main()
