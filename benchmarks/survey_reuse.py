"""Feature squares searched again after one tile of a wide survey changes.

A survey of ``--grid`` x ``--grid`` tiles of ``--tile`` metres (wider than two
feature squares and their halos), feature squares of ``--core`` metres: a full
run, a mound raised on one corner tile, an incremental run, then a full run of
the same tiles. Prints how many squares the incremental run searched again (of
the product's squares), the largest window a square's search read (as a share
of the mosaic), and whether the incremental product equals the full run's
(DTM within 1 mm, labels, categories, features). ``--waves`` keeps the default
terrain's long waves (ridges and valleys running across the whole survey);
without it the terrain is a slope with hills (objects of bounded size).

    .venv/bin/python benchmarks/survey_reuse.py [--grid 5] [--tile 128] [--core 128]
        [--density 1.5] [--waves] [--corner 0]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from survey_incremental import _product  # noqa: E402

from terrasift.jobs import run_job, validate_params  # noqa: E402
from terrasift.jobs import survey as surveys  # noqa: E402
from terrasift.synthetic.terrain import Surface, make_scene, write_tiles  # noqa: E402
from terrasift.workers.executors import InlineExecutor  # noqa: E402


def _windows(version: Path) -> tuple[int, float]:
    """Squares of a version and the largest window one searched, as a share of the mosaic."""
    state = json.loads((version / surveys.STATE).read_text())
    sq = state["squares"]
    e = sq["extent"]
    area = (e[2] - e[0]) * (e[3] - e[1])
    share = max((w[2] - w[0]) * (w[3] - w[1]) / area for w in sq["windows"].values())
    return len(sq["windows"]), share


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=5, help="tiles a side")
    ap.add_argument("--tile", type=float, default=128.0, help="tile side, m")
    ap.add_argument("--core", type=float, default=128.0, help="feature square side, m")
    ap.add_argument("--density", type=float, default=1.5, help="pulses per m²")
    ap.add_argument("--waves", action="store_true", help="keep the long waves of the terrain")
    ap.add_argument("--corner", type=int, default=0, help="index of the changed tile")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", type=Path, help="keep the survey here")
    args = ap.parse_args()
    surveys.FEATURE_CORE_M = args.core
    rng = np.random.default_rng(args.seed)
    size = args.grid * args.tile
    hills = tuple(
        (float(rng.uniform(0, size)), float(rng.uniform(0, size)), 3.0, float(rng.uniform(5, 12)))
        for _ in range(args.grid * args.grid)
    )
    surface = Surface(hills=hills) if args.waves else Surface(waves=(), hills=hills)
    root = args.out or Path(tempfile.mkdtemp(prefix="survey-reuse-"))
    try:
        scene = make_scene(size, args.density, surface=surface, n_buildings=2 * args.grid)
        tiles = write_tiles(scene, root / "tiles", args.tile)
        params = validate_params({"resolution": 0.5})
        sdir = root / "survey"
        surveys.plan_survey_run(root / "r1", sdir, tiles, params, mode="full")
        run_job(root / "r1", InlineExecutor())
        target = tiles[args.corner]
        las = laspy.read(target)
        cx, cy = float(np.median(las.x)), float(np.median(las.y))
        d = np.hypot(np.asarray(las.x) - cx, np.asarray(las.y) - cy)
        las.z = np.asarray(las.z) + 2.0 * np.clip(1 - d / 8, 0, None)
        las.write(target)
        t0 = time.perf_counter()
        inc = surveys.plan_survey_run(root / "r2", sdir, tiles, params)
        run_job(root / "r2", InlineExecutor())
        inc_s = time.perf_counter() - t0
        v2 = surveys.current_version(sdir)
        assert v2 is not None
        summary = json.loads((root / "r2" / "outputs" / "survey.json").read_text())
        n_squares, share = _windows(v2)
        a = _product(v2)
        t0 = time.perf_counter()
        surveys.plan_survey_run(root / "r3", sdir, tiles, params, mode="full")
        run_job(root / "r3", InlineExecutor())
        full_s = time.perf_counter() - t0
        v3 = surveys.current_version(sdir)
        assert v3 is not None
        b = _product(v3)
        both = ~np.isnan(a["dtm"]) & ~np.isnan(b["dtm"])
        row = {
            "survey_m": size,
            "tiles": len(tiles),
            "points": int(len(scene.xyz)),
            "square_m": args.core,
            "waves": args.waves,
            "tiles_redone": f"{len(inc['outputs'])}/{len(tiles)}",
            "squares_searched": f"{len(summary.get('squares_searched') or [])}/{n_squares}",
            "largest_window_share": round(share, 3),
            "dtm_within_1mm": float(np.mean(np.abs(a["dtm"][both] - b["dtm"][both]) <= 1e-3)),
            "label_diff": sum(int((a["labels"][k] != b["labels"][k]).sum()) for k in b["labels"]),
            "category_diff": int((a["cats"] != b["cats"]).sum()),
            "features_equal": a["features"] == b["features"],
            "objects": len(b["features"]),
            "incremental_s": round(inc_s, 1),
            "full_s": round(full_s, 1),
        }
        print(json.dumps(row), flush=True)
    finally:
        if args.out is None:
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
