"""Survey runs: an incremental run after a one-tile change gives the product a full run gives.

A 3 × 3 synthetic survey (20 m tiles, 20 m blocks): a first (full) run, a
mound added to a corner tile, an incremental run, then a full run of the same
tiles. The incremental run must redo the changed tile and the neighbours its
halo reaches only, keep the other tiles' files, and leave a product equal to
the full run's: DTM cells, categories, labels and merged features.
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import laspy
import numpy as np
import pytest
import rasterio

from terrasift.errors import InputError, NothingChanged
from terrasift.jobs import run_job, validate_params
from terrasift.jobs import survey as survey_module
from terrasift.jobs.finish import dtm_category_grids
from terrasift.jobs.params import stage_params
from terrasift.jobs.survey import (
    SQUARES,
    current_version,
    plan_survey_run,
    product_files,
    publish,
)
from terrasift.synthetic.terrain import Surface, make_scene, write_tiles
from terrasift.workers import features as feat
from terrasift.workers.executors import InlineExecutor

TILE = 20.0
PARAMS = {"block_size": 20, "resolution": 0.5}


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
    """The objects one search over the whole product's DTM finds (the survey's noise)."""
    noise = json.loads((version / "state.json").read_text())["noise"]
    cparams = stage_params(params, "categories").model_copy(update={"noise": noise})
    filters = feat.resolve_filters("all")
    with rasterio.open(version / "dtm.vrt") as ds:
        cats, stepped, _ = dtm_category_grids(ds, cparams, filters)
        dtm = ds.read(1, masked=True).filled(np.nan).astype(np.float64)
        whole = feat.detect_features(
            cats, filters, ds.transform, cats.tile_size, stepped=stepped, dtm=dtm
        )
    return feat.features_geojson(whole, 0, "x", to_wgs84=False)["features"]


def _inodes(version: Path) -> dict[str, int]:
    return {p.parent.name: p.stat().st_ino for p in version.glob("tiles/*/dtm.tif")}


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> dict:
    root = tmp_path_factory.mktemp("survey")
    # a hill on the corner shared by four tiles: one object, across tile edges.
    # 3 m high: a 2.5 m hill of 4 m sigma sits at the hill filter's limit on a
    # 60 m survey (found or not as ground labels change 17 m away from it).
    scene = make_scene(
        3 * TILE, 4.0, surface=Surface(hills=((TILE, TILE, 3.0, 4.0),)), n_buildings=0, seed=3
    )
    tiles = write_tiles(scene, root / "tiles", TILE)
    params = validate_params(PARAMS)
    sdir = root / "survey"
    # the feature search core by core, one per tile here (the default squares hold the survey)
    patch = pytest.MonkeyPatch()
    patch.setattr(survey_module, "FEATURE_CORE_M", TILE)
    # a small halo up front: each square's window grows only around the objects that need
    # it, so squares far from the change keep small windows (and their pieces)
    patch.setattr(survey_module, "FEATURE_HALO_M", 8.0)
    # and a cap of 4 m: the hill (~20 m) is searched in parts, joined at the publish
    patch.setattr(survey_module, "FEATURE_CAP_M", 4.0)

    def run(name: str, mode: str = "incremental", **kw: object) -> dict:
        summary = plan_survey_run(root / name, sdir, tiles, params, mode=mode, **kw)
        assert run_job(root / name, InlineExecutor()) == ["survey.json"]
        return summary

    out: dict = {"first": run("r1")}
    v1 = current_version(sdir)
    assert v1 is not None
    out["v1"], out["inodes1"] = _product(v1), _inodes(v1)
    out["cut1"] = sum(
        p.cut is not None
        for f in (v1 / SQUARES).glob("*.pkl")
        for p in pickle.loads(f.read_bytes())["pieces"]
    )
    out["whole_features1"] = _whole_features(v1, params)
    out["files"] = product_files(v1)
    out["vrt"] = (v1 / "dtm.vrt").read_text()
    out["collection"] = json.loads((v1 / "collection.json").read_text())
    with pytest.raises(NothingChanged, match="no tile changed"):
        plan_survey_run(root / "r-none", sdir, tiles, params)
    # a 1.5 m mound in the corner tile t0_0
    las = laspy.read(tiles[0])
    d = np.hypot(np.asarray(las.x) - scene.bounds[0] - 8, np.asarray(las.y) - scene.bounds[1] - 9)
    las.z = np.asarray(las.z) + 1.5 * np.clip(1 - d / 6, 0, None)
    las.write(tiles[0])
    out["incremental"] = run("r2", keep_intermediates=True)
    out["kept"] = {
        sub: sum(1 for p in (root / "r2" / sub).rglob("*") if p.is_file())
        for sub in ("shards", "blocks", "outputs/tiles")
    }
    v2 = current_version(sdir)
    assert v2 is not None
    out["v2"], out["inodes2"] = _product(v2), _inodes(v2)
    out["inc_summary"] = json.loads((root / "r2" / "outputs" / "survey.json").read_text())
    out["squares2"] = json.loads((v2 / "state.json").read_text())["squares"]
    out["full"] = run("r3", "full")
    v3 = current_version(sdir)
    assert v3 is not None and v3 != v2
    out["v3"] = _product(v3)
    out["whole_features3"] = _whole_features(v3, params)
    # the per-tile categories against one category grid over the whole DTM mosaic
    noise = json.loads((v3 / "state.json").read_text())["noise"]
    cparams = stage_params(params, "categories").model_copy(update={"noise": noise})
    with rasterio.open(v3 / "dtm.vrt") as ds:
        out["whole_cats"] = dtm_category_grids(ds, cparams, [])[0].bands()
    # a finished run keeps only its summary: the tiles live on in the product
    out["run_left"] = sorted(
        str(p.relative_to(root / "r3")) for p in (root / "r3").rglob("*") if p.is_file()
    )
    # stopped after the switch, before its summary: publishing again finds itself current
    (root / "r3" / "outputs" / "survey.json").unlink()
    out["republished"] = publish(str(root / "r3"))
    out["v3_again"] = current_version(sdir)
    out["versions"] = sorted(p.name for p in (sdir / "product").glob("v-*"))
    patch.undo()
    return out


def test_first_run_writes_the_whole_product(survey: dict) -> None:
    first = survey["first"]
    assert first["mode"] == "full" and len(first["outputs"]) == 9
    files = survey["files"]
    for name in ("dtm", "dsm", "chm", "slope", "coverage", "categories"):
        assert f"{name}.vrt" in files
    assert {"features.geojson", "collection.json"} <= set(files)
    for stem in (f"t{c}_{r}" for c in range(3) for r in range(3)):
        for f in ("dtm.tif", "slope.tif", "categories.tif", "classified.laz", "item.json"):
            assert f"tiles/{stem}/{f}" in files
    # sources relative to the VRT, so the product reads in place anywhere
    assert 'relativeToVRT="1">tiles/t0_0/dtm.tif' in survey["vrt"] and "/tmp" not in survey["vrt"]
    items = [ln["href"] for ln in survey["collection"]["links"] if ln["rel"] == "item"]
    assert len(items) == 9 and survey["collection"]["type"] == "Collection"
    # the hill across the four tiles' shared corner is one object, not four
    hills = [f for f in survey["v1"]["features"] if f["properties"].get("kind") == "hill"]
    assert len(hills) == 1, [f["properties"] for f in survey["v1"]["features"]]


def test_incremental_run_redoes_the_tile_and_its_halo_neighbours(survey: dict) -> None:
    inc = survey["incremental"]
    assert inc["mode"] == "incremental"
    assert sorted(inc["outputs"]) == ["t0_0.laz", "t0_1.laz", "t1_0.laz", "t1_1.laz"]
    # unchanged tiles are the same files (hard links), the redone ones new
    i1, i2 = survey["inodes1"], survey["inodes2"]
    for stem in i1:
        same = f"{stem}.laz" not in inc["outputs"]
        assert (i1[stem] == i2[stem]) == same, stem
    # the product moved: the mound is in the DTM
    diff = np.abs(survey["v2"]["dtm"] - survey["v1"]["dtm"])
    assert np.nanmax(diff) > 1.0
    # only the last version is kept
    assert len(survey["versions"]) == 1


def test_an_incremental_run_reports_the_feature_squares_it_searched(survey: dict) -> None:
    summary, squares = survey["inc_summary"], survey["squares2"]
    # this 60 m survey is narrower than the filters' reach: every square's search grew
    # over the whole DTM, so every square holds changed cells and was searched again
    assert summary["squares"] == len(squares["windows"]) > 1
    assert sorted(summary["squares_searched"]) == sorted(squares["windows"])


def test_only_squares_whose_searched_window_holds_a_changed_cell_are_searched_again(
    tmp_path: Path,
) -> None:
    from terrasift.files import write_json
    from terrasift.jobs.survey import SQUARES, _stale_squares, window_bounds
    from terrasift.tiling.blocks import BlockGrid

    grid = BlockGrid(0.0, 0.0, 1.0, 100, 100, 50.0, 10.0)
    windows = {
        "a": (0, 0, 50, 50),
        "b": (0, 50, 50, 50),
        "c": (50, 0, 50, 50),
        "d": (50, 50, 50, 50),
    }
    squares = {"0_0": [0, 0, 50, 50], "0_1": [0, 50, 50, 100], "1_0": [50, 0, 100, 50]}
    squares["1_1"] = [50, 50, 100, 100]
    prev = tmp_path / "v-1"
    (prev / SQUARES).mkdir(parents=True)
    for k in squares:
        (prev / SQUARES / f"{k}.pkl").write_bytes(b"")
    searched = {k: v for k, v in squares.items()}
    searched["1_0"] = [0, 0, 100, 60]  # grew around an object reaching into "d"
    searched["0_1"] = [0, 40, 50, 100]  # a halo: still away from "d"
    state = {
        "noise": 0.1,
        "slope_noise": 0.02,
        "tiles": {n: {"cells": list(window_bounds(grid, w))} for n, w in windows.items()},
        "squares": {"extent": [0, 0, 100, 100], "side": 50, "cap": 20, "windows": searched},
    }
    write_json(prev / "state.json", state)

    def stale(
        outputs: set[str],
        noise: float = 0.1,
        slope: float = 0.02,
        extent=(0, 0, 100, 100),
        side=50,
        cap: int | None = 20,
    ) -> set:
        return _stale_squares(
            prev, grid, windows, outputs, (noise, slope), extent, side, squares, cap
        )

    assert stale({"d"}) == {"1_0", "1_1"}
    assert stale({"a"}) == {"0_0", "0_1", "1_0"}  # the halo of "0_1" reads "a"'s cells
    assert stale({"b"}) == {"0_1", "1_0"}
    assert stale(set()) == set()
    assert stale({"d"}, noise=0.2) == set(squares)  # another noise: all
    assert stale({"d"}, slope=0.03) == set(squares)  # another slope noise: all
    assert stale(set(), extent=(0, 0, 100, 150)) == set(squares)  # the mosaic grew: all
    assert stale(set(), side=40) == set(squares)
    assert stale(set(), cap=None) == set(squares)  # another cap: all
    (prev / SQUARES / "0_0.pkl").unlink()
    assert stale(set()) == {"0_0"}  # no pieces kept for it


def test_a_finished_run_keeps_only_its_records(survey: dict) -> None:
    assert survey["run_left"] == ["job.json", "outputs/survey.json", "plan.json"]


def test_retention_keeps_the_intermediates(survey: dict) -> None:
    # the incremental run was planned with keep_intermediates: shards, blocks and its tiles stay
    kept = survey["kept"]
    assert kept["shards"] > 0 and kept["blocks"] > 0, kept
    assert kept["outputs/tiles"] >= 4 * 5, kept  # 4 redone tiles x (4 rasters + classified.laz)


def test_publish_again_after_the_switch_is_a_no_op(survey: dict) -> None:
    assert survey["republished"]["version"] == survey["v3_again"].name
    assert survey["republished"]["mode"] == "full"


def test_incremental_product_equals_a_full_run(survey: dict) -> None:
    a, b = survey["v2"], survey["v3"]
    assert a["dtm"].shape == b["dtm"].shape
    assert (np.isnan(a["dtm"]) == np.isnan(b["dtm"])).all()
    both = ~np.isnan(a["dtm"])
    close = np.abs(a["dtm"][both] - b["dtm"][both]) <= 1e-3
    assert close.mean() >= 0.9999, close.mean()
    assert (a["cats"] == b["cats"]).all()
    assert a["labels"].keys() == b["labels"].keys() and len(a["labels"]) == 9
    for k in a["labels"]:
        assert (a["labels"][k] == b["labels"][k]).all(), k
    assert a["features"] == b["features"]


@pytest.fixture(scope="module")
def batched(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A 4 x 1 strip of 20 m tiles run under a limit of 80 % of its points, and in one run."""
    root = tmp_path_factory.mktemp("batched")
    scene = make_scene(
        4 * TILE,
        4.0,
        height=TILE,
        surface=Surface(hills=((2 * TILE, 10.0, 2.5, 4.0),)),
        n_buildings=0,
        seed=5,
    )
    tiles = write_tiles(scene, root / "tiles", TILE)
    params = validate_params(PARAMS)
    points = {p.name: laspy.open(p).header.point_count for p in tiles}
    limit = int(0.8 * sum(points.values()))
    out: dict = {"limit": limit, "batches": []}
    for i in range(len(tiles)):
        batch = plan_survey_run(root / f"b{i}", root / "s", tiles, params, max_points=limit)
        batch["points"] = sum(points[n] for n in batch["sources"])
        run_job(root / f"b{i}", InlineExecutor())
        out["batches"].append(batch)
        version = current_version(root / "s")
        assert version is not None
        if i == 0:
            out["mid_tiles"] = sorted(p.name for p in (version / "tiles").iterdir())
        if not batch["pending"]:
            break
    with pytest.raises(NothingChanged):  # nothing left once the last batch published
        plan_survey_run(root / "b-none", root / "s", tiles, params, max_points=limit)
    out["batched"] = _product(version)
    out["batched_state"] = json.loads((version / "state.json").read_text())
    plan_survey_run(root / "one-job", root / "one" / "s", tiles, params)  # same survey id: "s"
    run_job(root / "one-job", InlineExecutor())
    version = current_version(root / "one" / "s")
    assert version is not None
    out["one"] = _product(version)
    out["one_state"] = json.loads((version / "state.json").read_text())
    version = current_version(root / "s")
    assert version is not None
    before = {p.parent.name: p.stat().st_ino for p in version.glob("tiles/*/slope.tif")}
    # a mound on the east end tile: the tiles away from it keep their slope and categories
    east = max(tiles, key=lambda p: laspy.open(p).header.mins[0])
    las = laspy.read(east)
    d = np.hypot(
        np.asarray(las.x) - las.header.maxs[0] + 6, np.asarray(las.y) - las.header.mins[1] - 10.0
    )
    las.z = np.asarray(las.z) + 1.0 * np.clip(1 - d / 5, 0, None)
    las.write(east)
    out["east"] = east.stem
    out["inc"] = plan_survey_run(root / "inc", root / "s", tiles, params)
    run_job(root / "inc", InlineExecutor())
    version = current_version(root / "s")
    assert version is not None
    out["inc_summary"] = json.loads((root / "inc" / "outputs" / "survey.json").read_text())
    after = {p.parent.name: p.stat().st_ino for p in version.glob("tiles/*/slope.tif")}
    out["slope_same"] = sorted(n for n in before if before[n] == after[n])
    return out


def test_a_survey_over_the_limit_runs_in_batches_into_the_full_product(batched: dict) -> None:
    batches, limit = batched["batches"], batched["limit"]
    assert len(batches) >= 2, [b["outputs"] for b in batches]
    assert all(b["points"] <= limit for b in batches)  # each run reads at most the limit
    done = [n for b in batches for n in b["outputs"]]
    assert sorted(done) == sorted(set(done)) and len(done) == 4  # every tile once
    assert batches[-1]["pending"] == []
    # between batches the product holds the tiles done so far only
    assert batched["mid_tiles"] == sorted(n.removesuffix(".laz") for n in batches[0]["outputs"])
    # the last batch's product is the product of one run over all tiles (the category
    # noise measured on the whole DTM, not on the first batch's part)
    a, b = batched["batched"], batched["one"]
    assert batched["batched_state"]["noise"] == batched["one_state"]["noise"]
    assert batched["batched_state"]["pending"] == []
    assert np.array_equal(a["dtm"], b["dtm"], equal_nan=True)
    assert (a["cats"] == b["cats"]).all()
    assert a["labels"].keys() == b["labels"].keys() and len(a["labels"]) == 4
    for k in a["labels"]:
        assert (a["labels"][k] == b["labels"][k]).all(), k
    assert a["features"] == b["features"]


def test_a_tile_whose_halo_alone_exceeds_the_limit_is_refused(tmp_path: Path) -> None:
    scene = make_scene(2 * TILE, 4.0, height=TILE, n_buildings=0, seed=6)
    tiles = write_tiles(scene, tmp_path / "tiles", TILE)
    with pytest.raises(InputError, match="a run takes at most 2500"):
        plan_survey_run(
            tmp_path / "j", tmp_path / "s", tiles, validate_params(PARAMS), max_points=2500
        )


def test_per_tile_categories_equal_one_grid_over_the_survey(survey: dict) -> None:
    assert np.array_equal(survey["v3"]["cats"], survey["whole_cats"])


def test_per_tile_features_equal_one_search_over_the_survey(survey: dict) -> None:
    def objects(features: list[dict]) -> list[str]:
        return sorted(
            json.dumps([f["geometry"], {k: f["properties"][k] for k in ("kind", "tiles")}])
            for f in features
        )

    assert survey["v1"]["features"], "the scene's hill is an object"
    assert survey["cut1"] >= 2  # searched in parts (the cap), joined at the publish
    for v in ("1", "3"):
        assert objects(survey[f"v{v}"]["features"]) == objects(survey[f"whole_features{v}"])


def test_a_publish_redoes_slope_and_categories_near_changed_cells_only(batched: dict) -> None:
    summary = batched["inc_summary"]
    derived = {n.removesuffix(".laz") for n in summary["derived"]}
    redone = {n.removesuffix(".laz") for n in summary["outputs"]}
    assert batched["east"] in redone
    assert redone <= derived and len(derived) < 4, summary
    # the tiles away from the change keep the previous version's files (same inodes)
    assert batched["slope_same"] == sorted({f"t{i}_0" for i in range(4)} - derived)
