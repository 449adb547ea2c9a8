"""Vegetation bins and terrain gauges: accuracy against exact truth, and cost.

    python benchmarks/vegetation_accuracy.py [--quick]

Prints one table per part:
1. synthetic forests (known trees and bushes on a bin grid): bin class agreement,
   tree and bush coverage against truth, no-go agreement after mowing at 3 m;
2. lidR MixedConifer (heights normalised, class 2 ground): tree coverage against
   the share of 1 m bins whose highest point is above 3.75 m;
3. pitch and roll along a path on a tilted plane and a sinusoid, and slope
   smoothing variants on the sinusoid with and without DTM noise;
4. time of the vegetation and roughness stages per million points.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

# One BLAS thread, as a worker process should run: stages make many tiny LAPACK
# calls (per-bin solves, scipy's Delaunay.transform), and OpenBLAS threads
# fighting over busy cores made those up to a few hundred times slower here.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from terrasift.synthetic.forest import make_forest, raster_of, sinusoid, tilted_plane  # noqa: E402
from terrasift.workers.bins import Grid, bin_statistics  # noqa: E402
from terrasift.workers.terrain import (  # noqa: E402
    gradient,
    median_smooth,
    path_profile,
    roughness,
    smoothed_gradient,
)  # noqa: E402
from terrasift.workers.vegetation import VegetationParams, classify_bins  # noqa: E402

DATA = ROOT / ".." / "shared" / "data"


def table(title: str, header: list[str], rows: list[list[object]]) -> None:
    print(f"\n## {title}")
    cells = [header] + [[f"{v:.4f}" if isinstance(v, float) else str(v) for v in r] for r in rows]
    width = [max(len(r[i]) for r in cells) for i in range(len(header))]
    for i, r in enumerate(cells):
        print("  ".join(c.rjust(w) for c, w in zip(r, width, strict=True)))
        if i == 0:
            print("  ".join("-" * w for w in width))


def forests(size: float, seeds: list[int]) -> None:
    rows = []
    for round_crowns in (False, True):
        for density in (30.0, 5.0):
            for seed in seeds:
                f = make_forest(size=size, density=density, round_crowns=round_crowns, seed=seed)
                vb = classify_bins(f.xyz, f.is_ground, f.grid, VegetationParams())
                mow = classify_bins(f.xyz, f.is_ground, f.grid, VegetationParams(mow_height=3.0))
                ok = vb.bin_class == f.truth_class
                tree, bush = f.coverage()
                rows.append(
                    [
                        "round" if round_crowns else "square",
                        density,
                        seed,
                        len(f.xyz),
                        vb.support,
                        float(ok.mean()),
                        float(ok[~f.edge].mean()),
                        100 * (vb.tree_coverage - tree),
                        100 * (vb.bush_coverage - bush),
                        100 * tree,
                        100 * bush,
                        float((mow.nogo == f.truth_nogo).mean()),
                    ]
                )
    table(
        f"Synthetic forests {size:.0f} m x {size:.0f} m, 1 m bins, default parameters "
        "(targets: agreement >= 0.95, coverage error <= 2 points)",
        [
            "crowns",
            "pulses/m2",
            "seed",
            "points",
            "support",
            "agreement",
            "agree off-edge",
            "tree err pts",
            "bush err pts",
            "tree %",
            "bush %",
            "nogo agree",
        ],
        rows,
    )


def mixed_conifer() -> None:
    path = DATA / "lidr" / "MixedConifer.laz"
    if not path.exists():
        print(f"\n## MixedConifer: skipped, {path} not found")
        return
    import laspy

    las = laspy.read(path)
    xyz = np.column_stack([las.x, las.y, las.z]).astype(np.float64)
    ground = np.asarray(las.classification) == 2
    grid = Grid.covering(xyz[:, 0], xyz[:, 1], 1.0)
    st = bin_statistics(xyz, grid)
    share = float((st.zmax[st.n > 0] > 3.75).mean())
    rows = []
    for label, p in [
        ("default (auto support)", VegetationParams()),
        ("support=5", VegetationParams(support=5)),
        ("support=1 (seed n > 20 per bin)", VegetationParams(support=1)),
        ("screen_tol=None (seed RMS only)", VegetationParams(screen_tol=None)),
        ("rms_tol=0.2", VegetationParams(rms_tol=0.2)),
    ]:
        t = time.perf_counter()
        vb = classify_bins(xyz, ground, grid, p)
        dt = time.perf_counter() - t
        rows.append(
            [
                label,
                vb.support,
                100 * vb.tree_coverage,
                100 * share,
                100 * (vb.tree_coverage - share),
                100 * vb.bush_coverage,
                f"{dt:.2f}",
            ]
        )
    table(
        f"MixedConifer ({len(xyz)} points, {len(xyz) / ((st.n > 0).sum()):.1f} per non-empty 1 m bin): "
        "tree coverage vs share of 1 m bins with max height > 3.75 m (target: within 5 points)",
        ["run", "support", "tree %", "canopy share %", "diff pts", "bush %", "s"],
        rows,
    )


def pitch_roll() -> None:
    x0, y0 = 500_000.0, 5_400_000.0
    line = np.array(
        [[x0 + 20, y0 + 30], [x0 + 280, y0 + 90], [x0 + 200, y0 + 270], [x0 + 40, y0 + 220]]
    )
    rows = []
    for name, surf in [("tilted plane", tilted_plane()), ("sinusoid", sinusoid())]:
        for cell in (1.0, 0.5):
            n = int(300 / cell)
            dtm, tr = raster_of(lambda x, y, s=surf: s(x - x0, y - y0), x0, y0 + 300, cell, n, n)
            for smooth in ("gradient", "dtm"):
                pp = path_profile(dtm, tr, line, 0.5, smooth=smooth)
                seg = np.diff(line, axis=0)
                length = np.hypot(seg[:, 0], seg[:, 1])
                k = np.clip(
                    np.searchsorted(np.r_[0, np.cumsum(length)], pp.distance, "right") - 1,
                    0,
                    len(seg) - 1,
                )
                tx, ty = seg[k, 0] / length[k], seg[k, 1] / length[k]
                zx, zy = surf.gradient(pp.x - x0, pp.y - y0)
                pitch = np.degrees(np.arctan(tx * zx + ty * zy))
                roll = np.degrees(np.arctan(ty * zx - tx * zy))
                rows.append(
                    [
                        name,
                        cell,
                        smooth,
                        pp.distance.size,
                        float(np.abs(pitch).max()),
                        float(np.abs(pp.pitch_deg - pitch).max()),
                        float(np.abs(pp.roll_deg - roll).max()),
                    ]
                )
    table(
        "Pitch and roll along a 4-vertex path, 3x3 median (target: error <= 0.5 deg)",
        [
            "surface",
            "cell m",
            "smoothing",
            "points",
            "max |pitch| deg",
            "pitch err deg",
            "roll err deg",
        ],
        rows,
    )

    rows = []
    surf = sinusoid()
    dtm, _ = raster_of(surf, 0.0, 300.0, 1.0, 300, 300)
    xs = np.arange(300) + 0.5
    ax, _ = surf.gradient(*np.meshgrid(xs, 300.0 - xs))
    rng = np.random.default_rng(0)
    for sigma in (0.0, 0.03):
        d = dtm + rng.normal(0, sigma, dtm.shape)
        for label, (gx, _gy) in [
            ("none", gradient(d, 1.0)),
            ("median of heights", gradient(median_smooth(d, 3), 1.0)),
            ("median of slopes", smoothed_gradient(d, 1.0)),
        ]:
            e = (np.degrees(np.arctan(gx)) - np.degrees(np.arctan(ax)))[2:-2, 2:-2]
            rows.append([sigma, label, float(np.abs(e).max()), float(np.sqrt((e**2).mean()))])
    table(
        "x-slope error on the sinusoid DTM (1 m cells), interior cells",
        ["DTM noise m", "smoothing", "max err deg", "rms err deg"],
        rows,
    )


def timing(size: float) -> None:
    f = make_forest(size=size, density=30.0, seed=11)
    rows = []
    for label, fn in [
        ("vegetation", lambda: classify_bins(f.xyz, f.is_ground, f.grid, VegetationParams())),
        (
            "vegetation + mow 3 m",
            lambda: classify_bins(f.xyz, f.is_ground, f.grid, VegetationParams(mow_height=3.0)),
        ),
        ("roughness (ground points)", lambda: roughness(f.xyz[f.is_ground], f.grid)),
    ]:
        best = min(_timed(fn) for _ in range(3))
        rows.append([label, len(f.xyz), f"{best:.2f}", f"{best / len(f.xyz) * 1e6:.2f}"])
    table(
        "Stage time, best of 3 (2 shared cores: compare, do not quote as throughput)",
        ["stage", "points", "s", "s per M points"],
        rows,
    )


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller forests, one seed")
    a = ap.parse_args()
    forests(80.0 if a.quick else 150.0, [0] if a.quick else [0, 1, 2])
    mixed_conifer()
    pitch_roll()
    timing(80.0 if a.quick else 150.0)


if __name__ == "__main__":
    main()
