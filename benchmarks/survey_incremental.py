"""Incremental survey runs against full runs, over a family of synthetic surveys.

Each scene: a 3 × 3 survey cut from one synthetic terrain (tile size, density,
block size, seed drawn from ranges), a first full run, one change (a tile's
points lifted by a mound, a tile removed, or a tile added), an incremental
run, then a full run of the same tiles. Reported per scene and as worst /
10th percentile / median: the share of DTM cells equal within 1 mm, label,
category and feature differences, and how many tiles the incremental run redid.

    .venv/bin/python benchmarks/survey_incremental.py [--scenes 12] [--out DIR] [--one-tile]

``--feature-core M`` runs the feature search in squares of M metres (default: the
survey's ``FEATURE_CORE_M``, which holds these small surveys whole); each scene's
full product's objects are also compared with one search over its whole DTM
(``features_whole_equal``: same objects, geometry to the millimetre of the GeoJSON).

``--feature-halo M`` starts each square's search with a halo of M metres (default:
the filters' reach, which holds these small surveys whole) so windows stay small
where no object needs more; ``squares_searched`` is how many squares the
incremental run searched again, of the product's squares.

``--one-tile`` also runs each mound scene's changed tile as a job of its own
(what a client sending only changed tiles as plain jobs gets) and compares its
DTM with the full product on that tile's cells: the baseline the survey runs
replace.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np
import rasterio

from terrasift.jobs import run_job, validate_params
from terrasift.jobs.survey import current_version, plan_survey_run
from terrasift.synthetic.terrain import Surface, make_scene, write_tiles
from terrasift.workers.executors import InlineExecutor


def _product(version: Path) -> dict:
    with rasterio.open(version / "dtm.vrt") as ds:
        dtm = ds.read(1, masked=True).filled(np.nan)
    with rasterio.open(version / "categories.vrt") as ds:
        cats = ds.read()
    labels = {
        p.parent.name: np.asarray(laspy.read(p).classification)
        for p in sorted((version / "tiles").glob("*/classified.laz"))
    }
    feats = json.loads((version / "features.native.geojson").read_text())["features"]
    return {"dtm": dtm, "cats": cats, "labels": labels, "features": feats}


def _whole_features(version: Path, params: dict) -> list[dict]:
    """Objects of one search over the whole product's DTM (the survey's noise)."""
    from terrasift.jobs.finish import dtm_category_grids
    from terrasift.jobs.params import stage_params
    from terrasift.workers import features as feat

    noise = json.loads((version / "state.json").read_text())["noise"]
    cparams = stage_params(params, "categories").model_copy(update={"noise": noise})
    filters = feat.resolve_filters("all")
    with rasterio.open(version / "dtm.vrt") as ds:
        cats, stepped, _ = dtm_category_grids(ds, cparams, filters)
        dtm = ds.read(1, masked=True).filled(np.nan).astype(np.float64)
        found = feat.detect_features(
            cats, filters, ds.transform, cats.tile_size, stepped=stepped, dtm=dtm
        )
    return feat.features_geojson(found, 0, None, to_wgs84=False)["features"]


def _objects(features: list[dict]) -> list[str]:
    """Objects as comparable text: geometry, kind and tiles (ids and order aside)."""
    return sorted(
        json.dumps([f["geometry"], f["properties"]["kind"], f["properties"]["tiles"]])
        for f in features
    )


def one_tile_agreement(root: Path, tile: Path, params: dict, version: Path) -> dict:
    """The changed tile as a job of its own (no neighbours, its own density), as a client
    sending only changed tiles gets it, against the survey's full product on its cells."""
    from terrasift import jobs

    job = root / "one-tile"
    jobs.prepare_job(job, [tile], params)
    run_job(job, InlineExecutor())
    with (
        rasterio.open(jobs.output_path(job, "dtm.tif")) as a,
        rasterio.open(version / "dtm.vrt") as b,
    ):
        da = a.read(1, masked=True).filled(np.nan)
        cols, rows = np.meshgrid(np.arange(a.width) + 0.5, np.arange(a.height) + 0.5)
        x, y = a.transform * (cols.ravel(), rows.ravel())
        r, c = rasterio.transform.rowcol(b.transform, x, y)
        db = b.read(1, masked=True).filled(np.nan)[np.asarray(r), np.asarray(c)]
    db = db.reshape(da.shape)
    both = ~np.isnan(da) & ~np.isnan(db)
    d = np.abs(da - db)[both]
    return {"one_tile_within_1mm": float(np.mean(d <= 1e-3)), "one_tile_max_m": float(d.max())}


def scene_case(i: int, rng: np.random.Generator, root: Path, one_tile: bool = False) -> dict:
    tile = float(rng.choice([20.0, 30.0, 40.0]))
    density = float(rng.uniform(2.0, 6.0))
    block = float(rng.choice([20.0, 40.0]))
    kind = ("mound", "remove", "add")[i % 3]
    hills = tuple(
        (float(rng.uniform(0, 3 * tile)), float(rng.uniform(0, 3 * tile)), 2.5, 4.0)
        for _ in range(2)
    )
    scene = make_scene(
        3 * tile,
        density,
        surface=Surface(hills=hills),
        n_buildings=int(rng.integers(0, 3)),
        seed=int(rng.integers(1 << 30)),
    )
    tiles = write_tiles(scene, root / "tiles", tile)
    target = tiles[int(rng.integers(len(tiles)))]
    params = validate_params({"block_size": block, "resolution": 0.5})
    sdir = root / "survey"
    initial = [t for t in tiles if not (kind == "add" and t == target)]
    plan_survey_run(root / "r1", sdir, initial, params, mode="full")
    run_job(root / "r1", InlineExecutor())
    now = list(tiles)
    if kind == "mound":
        las = laspy.read(target)
        cx, cy = float(np.median(las.x)), float(np.median(las.y))
        d = np.hypot(np.asarray(las.x) - cx, np.asarray(las.y) - cy)
        las.z = np.asarray(las.z) + float(rng.uniform(0.5, 3.0)) * np.clip(1 - d / 6, 0, None)
        las.write(target)
    elif kind == "remove":
        now.remove(target)
    t0 = time.perf_counter()
    inc = plan_survey_run(root / "r2", sdir, now, params)
    run_job(root / "r2", InlineExecutor())
    inc_s = time.perf_counter() - t0
    v2 = current_version(sdir)
    assert v2 is not None
    a = _product(v2)
    inc_summary = json.loads((root / "r2" / "outputs" / "survey.json").read_text())
    t0 = time.perf_counter()
    plan_survey_run(root / "r3", sdir, now, params, mode="full")
    run_job(root / "r3", InlineExecutor())
    full_s = time.perf_counter() - t0
    v3 = current_version(sdir)
    assert v3 is not None
    b = _product(v3)
    whole = _whole_features(v3, params)
    extra = one_tile_agreement(root, target, params, v3) if one_tile and kind == "mound" else {}
    same_shape = a["dtm"].shape == b["dtm"].shape
    both = ~np.isnan(a["dtm"]) & ~np.isnan(b["dtm"]) if same_shape else np.zeros(1, bool)
    within = (
        float(np.mean(np.abs(a["dtm"][both] - b["dtm"][both]) <= 1e-3))
        if same_shape and both.any()
        else 0.0
    )
    nan_diff = int((np.isnan(a["dtm"]) != np.isnan(b["dtm"])).sum()) if same_shape else -1
    label_diff = sum(
        int((a["labels"][k] != b["labels"][k]).sum()) for k in b["labels"] if k in a["labels"]
    ) + sum(1 for k in b["labels"] if k not in a["labels"])
    cat_diff = int((a["cats"] != b["cats"]).sum()) if a["cats"].shape == b["cats"].shape else -1
    return {
        "scene": i,
        "kind": kind,
        "tile_m": tile,
        "block_m": block,
        "density": round(density, 2),
        "redone": f"{len(inc['outputs'])}/{len(now)}",
        "within_1mm": within,
        "nodata_diff": nan_diff,
        "label_diff": label_diff,
        "category_diff": cat_diff,
        "features_equal": a["features"] == b["features"],
        "features_whole_equal": _objects(b["features"]) == _objects(whole),
        "objects": len(b["features"]),
        "squares_searched": f"{len(inc_summary.get('squares_searched') or [])}/"
        f"{inc_summary.get('squares', 0)}",
        "incremental_s": round(inc_s, 1),
        "full_s": round(full_s, 1),
        **extra,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=12)
    ap.add_argument("--seed", type=int, default=26)
    ap.add_argument("--out", type=Path, default=None, help="keep the scenes here")
    ap.add_argument(
        "--one-tile",
        action="store_true",
        help="also run each mound scene's changed tile as a job of its own (a baseline)",
    )
    ap.add_argument("--feature-core", type=float, default=None, help="feature squares (m)")
    ap.add_argument(
        "--feature-halo", type=float, default=None, help="feature squares' first halo (m)"
    )
    args = ap.parse_args()
    from terrasift.jobs import survey

    if args.feature_core is not None:
        survey.FEATURE_CORE_M = args.feature_core
    if args.feature_halo is not None:
        survey.FEATURE_HALO_M = args.feature_halo
    rng = np.random.default_rng(args.seed)
    base = args.out or Path(tempfile.mkdtemp(prefix="survey-bench-"))
    rows = []
    for i in range(args.scenes):
        root = base / f"scene{i:02d}"
        shutil.rmtree(root, ignore_errors=True)
        row = scene_case(i, rng, root, args.one_tile)
        rows.append(row)
        print(json.dumps(row), flush=True)
        if args.out is None:
            shutil.rmtree(root, ignore_errors=True)
    share = np.array([r["within_1mm"] for r in rows])
    print(
        f"DTM cells within 1 mm of the full run: worst {share.min():.6f}, "
        f"p10 {np.percentile(share, 10):.6f}, median {np.median(share):.6f}; "
        f"label differences: max {max(r['label_diff'] for r in rows)}; "
        f"category differences: max {max(r['category_diff'] for r in rows)}; "
        f"nodata differences: max {max(r['nodata_diff'] for r in rows)}; "
        f"features equal in {sum(r['features_equal'] for r in rows)} of {len(rows)}; "
        f"equal to one search over the whole DTM in "
        f"{sum(r['features_whole_equal'] for r in rows)} of {len(rows)} "
        f"({sum(r['objects'] for r in rows)} objects)"
    )
    if args.out is None:
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
