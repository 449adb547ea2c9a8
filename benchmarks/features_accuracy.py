"""Accuracy and speed of categories + feature filters.

1. Synthetic terrain with constructed objects (terrasift.synthetic.features):
   per kind recall, precision (a detection matches a truth object of its kind
   when their polygons have IoU >= 0.3) and the worst length error of matches.
   Targets: recall >= 90 %, precision >= 80 %, length within 25 %.
2. Speed: categories and all seven built-in filters on a 1 km^2 DTM
   (2000 x 2000 cells of 0.5 m = 500 x 500 tiles), one core. Target <= 10 s.

Run: PYTHONPATH=. python benchmarks/features_accuracy.py [--seeds 0 1 2] [--vegetation 0.002]
     [--noise 0.015] [--no-speed]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

from terrasift.synthetic.features import make_feature_scene  # noqa: E402
from terrasift.workers.categories import CategoryParams, compute_categories  # noqa: E402
from terrasift.workers.features import builtin_filter_names, detect_features, load_filter  # noqa: E402


def iou(a, b) -> float:
    inter = a.intersection(b).area
    return inter / (a.area + b.area - inter) if inter else 0.0


def score(scene, result, kinds):
    rows = {}
    for kind in kinds:
        truth = [t for t in scene.truth if t.kind == kind]
        det = [f for f in result.objects if f.kind == kind]
        matched_truth = set()
        matched_det = 0
        len_err = []
        for f in det:
            best = max(
                ((iou(f.geometry, t.polygon), i) for i, t in enumerate(truth)), default=(0.0, -1)
            )
            if best[0] >= 0.3:
                matched_det += 1
                if best[1] not in matched_truth:
                    len_err.append(
                        abs(f.length_m - truth[best[1]].length_m) / truth[best[1]].length_m
                    )
                matched_truth.add(best[1])
        rows[kind] = (
            len(truth),
            len(det),
            len(matched_truth),
            matched_det,
            max(len_err, default=float("nan")),
        )
    return rows


def accuracy(seeds: list[int], vegetation: float, noise: float) -> None:
    filters = [load_filter(n) for n in builtin_filter_names()]
    totals: dict[str, list[int]] = {}
    worst_len: dict[str, float] = {}
    print("seed  kind        truth  found  recall  precision  max length error")
    for seed in seeds:
        scene = make_feature_scene(seed=seed, vegetation_share=vegetation, noise=noise)
        cats = compute_categories(scene.dtm, scene.cell, CategoryParams())
        result = detect_features(cats, filters, scene.transform, cats.tile_size)
        for kind, (nt, nd, mt, md, le) in score(scene, result, scene.kinds()).items():
            rec = mt / nt if nt else 1.0
            prec = md / nd if nd else float("nan")
            print(f"{seed:4d}  {kind:10s} {nt:6d} {nd:6d}  {rec:6.0%}  {prec:9.0%}  {le:8.1%}")
            acc = totals.setdefault(kind, [0, 0, 0, 0])
            for i, v in enumerate((nt, nd, mt, md)):
                acc[i] += v
            if le == le:
                worst_len[kind] = max(worst_len.get(kind, 0.0), le)
    print("\nall seeds   truth  found  recall  precision  max length error")
    for kind, (nt, nd, mt, md) in totals.items():
        prec = md / nd if nd else float("nan")
        print(
            f"  {kind:10s} {nt:6d} {nd:6d}  {mt / nt:6.0%}  {prec:9.0%}  {worst_len.get(kind, float('nan')):8.1%}"
        )


def speed() -> None:
    scene = make_feature_scene(size=1000.0, seed=1)
    run_speed("synthetic feature terrain", scene.dtm, scene.cell, scene.transform)
    # a harder case for the search: rough random terrain, every tile inclined somewhere
    rng = np.random.default_rng(0)
    rough = ndimage.gaussian_filter(rng.normal(0, 1, scene.dtm.shape), 6) * 40
    run_speed("rough random terrain", rough, scene.cell, scene.transform)


def run_speed(label: str, dtm, cell: float, transform) -> None:
    filters = [load_filter(n) for n in builtin_filter_names()]
    t0 = time.perf_counter()
    cats = compute_categories(dtm, cell, CategoryParams())
    t1 = time.perf_counter()
    times = {}
    for f in filters:
        s = time.perf_counter()
        res = detect_features(cats, [f], transform, cats.tile_size)
        times[f.name] = (time.perf_counter() - s, len(res.objects))
    t2 = time.perf_counter()
    print(
        f"\nspeed, {label}: {dtm.shape[0]}x{dtm.shape[1]} cells -> {cats.shape[0]}x{cats.shape[1]} tiles (1 core)"
    )
    print(f"  categories        {t1 - t0:6.2f} s")
    for name, (t, n) in times.items():
        print(f"  filter {name:10s} {t:6.2f} s   {n:5d} objects")
    print(f"  total             {t2 - t0:6.2f} s   (target <= 10 s)")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument(
        "--vegetation",
        type=float,
        default=0.002,
        help="share of DTM cells with a low-vegetation bump",
    )
    ap.add_argument("--noise", type=float, default=0.015, help="DTM noise sigma, m")
    ap.add_argument("--no-speed", action="store_true")
    args = ap.parse_args()
    accuracy(args.seeds, args.vegetation, args.noise)
    if not args.no_speed:
        speed()
