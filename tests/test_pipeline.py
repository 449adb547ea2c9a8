"""A job end to end without the service: outputs, accuracy, seams, resume, cancel, executors."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import laspy
import numpy as np
import pytest
import rasterio
from rio_cogeo.cogeo import cog_validate

from terrasift import jobs
from terrasift.errors import JobCancelled
from terrasift.jobs.params import stage_params
from terrasift.workers.executors import InlineExecutor, LocalExecutor

BLOCK = {"block_size": 80, "buffer": 15}


def _run(tmp_path, tile, params, name="job", executor=None):
    job = tmp_path / name
    validated = jobs.validate_params(params)
    jobs.prepare_job(job, [tile], validated)
    names = jobs.run_job(job, executor or InlineExecutor())
    return job, names


@pytest.fixture(scope="module")
def finished_job(tmp_path_factory, small_tile):
    tmp = tmp_path_factory.mktemp("pipeline")
    return _run(tmp, small_tile, BLOCK)


def test_outputs_exist_and_cogs_are_valid(finished_job):
    job, names = finished_job
    for name in ["classified.laz", "dtm.tif", "dsm.tif", "chm.tif", "report.json", "item.json"]:
        assert name in names
        assert jobs.output_path(job, name).stat().st_size > 0
    for name in ["dtm.tif", "dsm.tif", "chm.tif"]:
        valid, errors, _ = cog_validate(str(jobs.output_path(job, name)), quiet=True)
        assert valid, errors
        with rasterio.open(jobs.output_path(job, name)) as ds:
            assert ds.crs.to_epsg() == 32632
            assert ds.dtypes[0] == "float32" and ds.nodata is not None
            assert ds.overviews(1), "COG should carry overviews"


def test_classified_laz_keeps_every_point_order_and_dimension(
    finished_job, small_tile, small_scene
):
    job, _ = finished_job
    src = laspy.read(small_tile)
    out = laspy.read(jobs.output_path(job, "classified.laz"))
    assert len(out.points) == len(src.points)
    assert list(out.point_format.dimension_names) == list(src.point_format.dimension_names)
    for dim in ["X", "Y", "Z", "intensity", "return_number", "number_of_returns", "truth"]:
        assert np.array_equal(out[dim], src[dim]), dim
    assert out.header.parse_crs().to_epsg() == 32632
    classes = np.asarray(out.classification)
    assert set(np.unique(classes)) <= {1, 2, 3, 4, 5, 6, 7}
    # roofs are buildings, not vegetation; crowns are not buildings
    roof = small_scene.truth == 6
    assert np.mean(classes[roof] == 6) > 0.9
    assert np.mean(classes[np.isin(small_scene.truth, (3, 4, 5))] == 6) < 0.02
    # ground labels agree with the truth for most points
    truth_ground = small_scene.truth == 2
    agree = np.mean((classes == 2) == truth_ground)
    assert agree > 0.9
    # returns under the terrain stay out of the ground (38 % of them were
    # ground before the low-point test, 7 % with it); true ground is not class 7
    xyz = small_scene.xyz
    under = (small_scene.truth == 7) & (xyz[:, 2] < small_scene.surface(xyz[:, 0], xyz[:, 1]))
    assert np.mean(classes[under] == 2) < 0.15
    assert np.mean(classes[truth_ground] == 7) < 0.001


def _dtm_rmse(job, scene) -> float:
    """RMSE of the job's DTM against the true surface over cells holding a true ground point."""
    with rasterio.open(jobs.output_path(job, "dtm.tif")) as ds:
        dtm = ds.read(1, masked=True)
        rows, cols = np.nonzero(~np.ma.getmaskarray(dtm))
        xs, ys = rasterio.transform.xy(ds.transform, rows, cols)
        g = scene.xyz[scene.truth == 2]
        gr, gc = (np.asarray(v) for v in rasterio.transform.rowcol(ds.transform, g[:, 0], g[:, 1]))
        has_ground = np.zeros(dtm.shape, bool)
        ok = (gr >= 0) & (gr < dtm.shape[0]) & (gc >= 0) & (gc < dtm.shape[1])
        has_ground[gr[ok], gc[ok]] = True
    err = np.asarray(dtm[rows, cols]) - scene.surface(np.asarray(xs), np.asarray(ys))
    sel = has_ground[rows, cols]
    return float(np.sqrt(np.mean(err[sel] ** 2)))


@pytest.mark.parametrize("ground", ["nist", "ptd"])
def test_dtm_matches_true_surface(tmp_path, small_tile, small_scene, ground):
    job, _ = _run(tmp_path, small_tile, {**BLOCK, "ground": ground, "features": "none"})
    rmse = _dtm_rmse(job, small_scene)
    assert rmse <= 0.15, rmse


def test_report_and_stac_item(finished_job, small_scene):
    job, names = finished_job
    report = json.loads(jobs.output_path(job, "report.json").read_text())
    assert report["points"] == len(small_scene)
    assert sum(report["counts_per_class"].values()) == len(small_scene)
    # no sensor origin, so no mixed measurements: class 7 is the isolated low
    # points among the ground and the outliers the objects stage finds
    assert 0 < report["low_points"] < report["counts_per_class"].get("7", 0)
    assert report["parameters"]["block_size"] == 80
    assert report["block_buffer"] == report["parameters"]["buffer"] == 15
    method = f"ground.{report['parameters']['ground']}"
    assert report["stage_parameters"][method] == stage_params(
        report["parameters"], method
    ).model_dump(mode="json")
    assert "ground" in report["timings_seconds"]["stages_summed_over_blocks"]
    # the job's roughness gauge covers exactly the bins of its blocks
    per_block = report["roughness_per_block"]
    assert len(per_block) == report["blocks"]
    assert report["roughness"]["n_bins"] == sum(b["n_bins"] for b in per_block.values()) > 0
    veg = report["vegetation"]
    assert 0 < veg["tree_coverage"] < 1 and sum(veg["bins"].values()) > 0
    item = json.loads(jobs.output_path(job, "item.json").read_text())
    assert item["properties"]["proj:code"] == "EPSG:32632"
    assert item["assets"]["dtm.tif"]["type"].startswith(
        "image/tiff; application=geotiff; profile=cloud-optimized"
    )
    assert set(item["assets"]) == set(names) - {"item.json"}
    lon0, lat0, lon1, lat1 = item["bbox"]
    assert 7 < lon0 < lon1 < 11 and 47 < lat0 < lat1 < 50


def test_block_seams_do_not_change_labels(tmp_path, small_tile, small_scene):
    """2×2-ish 80 m blocks against one block, both with the default 20 m buffer:
    the same labels away from the tile edge (measured: 99.93 %; the few that
    differ lie within 5 m of a block edge)."""
    job_small, _ = _run(tmp_path, small_tile, {"block_size": 80}, "small")
    job_one, _ = _run(tmp_path, small_tile, {"block_size": 400}, "one")
    a = np.asarray(laspy.read(jobs.output_path(job_small, "classified.laz")).classification)
    b = np.asarray(laspy.read(jobs.output_path(job_one, "classified.laz")).classification)
    x, y = small_scene.xyz[:, 0], small_scene.xyz[:, 1]
    x0, y0, x1, y1 = small_scene.bounds
    inner = (x > x0 + 20) & (x < x1 - 20) & (y > y0 + 20) & (y < y1 - 20)
    assert np.mean(a[inner] == b[inner]) >= 0.998
    assert np.mean((a == 2)[inner] == (b == 2)[inner]) >= 0.998


def test_dtm_nodata_does_not_depend_on_blocks(tmp_path):
    """A lake (no returns) across block edges in a sparse scan: 80 m blocks and
    one block leave the same DTM cells empty (each block used to size its data
    reach from its own point count, so a half-empty block reached further)."""
    from terrasift.synthetic.terrain import Scene, make_scene, write_las

    s = make_scene(size=160, density=1.0, seed=4)
    x0, y0, _, _ = s.bounds
    dry = np.hypot(s.xyz[:, 0] - (x0 + 70), s.xyz[:, 1] - (y0 + 85)) >= 25
    scene = Scene(
        s.xyz[dry],
        s.truth[dry],
        s.return_number[dry],
        s.number_of_returns[dry],
        s.surface,
        s.bounds,
    )
    tile = write_las(scene, tmp_path / "lake.laz")
    masks = []
    for size in (80, 400):
        job, _ = _run(tmp_path, tile, {"block_size": size, "features": "none"}, f"b{size}")
        with rasterio.open(jobs.output_path(job, "dtm.tif")) as ds:
            masks.append(ds.read_masks(1) == 0)
    assert masks[0].sum() > 1000  # the lake is there
    assert np.array_equal(masks[0], masks[1])


def test_resume_redoes_only_missing_work(tmp_path, small_tile):
    job, names = _run(tmp_path, small_tile, BLOCK)
    before = {p.name: p.stat().st_mtime_ns for p in (job / "blocks").glob("*.npz")}
    victim = sorted(before)[1]
    (job / "blocks" / victim).unlink()
    jobs.output_path(job, "dtm.tif").unlink()
    reference = laspy.read(jobs.output_path(job, "classified.laz")).classification.copy()
    jobs.output_path(job, "classified.laz").unlink()
    jobs.run_job(job, InlineExecutor())
    after = {p.name: p.stat().st_mtime_ns for p in (job / "blocks").glob("*.npz")}
    changed = {n for n in after if after[n] != before.get(n)}
    assert changed == {victim}
    assert np.array_equal(
        laspy.read(jobs.output_path(job, "classified.laz")).classification, reference
    )
    assert jobs.output_path(job, "dtm.tif").exists()


def test_cancelled_job_stops(tmp_path, small_tile):
    job = tmp_path / "job"
    jobs.prepare_job(job, [small_tile], jobs.validate_params(BLOCK))
    jobs.request_cancel(job)
    with pytest.raises(JobCancelled):
        jobs.run_job(job, InlineExecutor())
    assert not (job / "outputs" / "classified.laz").exists()


def _labels(job) -> np.ndarray:
    return np.asarray(laspy.read(jobs.output_path(job, "classified.laz")).classification)


def test_process_pool_gives_the_same_labels(tmp_path, small_tile, finished_job):
    executor = LocalExecutor(2, start_method="spawn")
    try:
        job, _ = _run(tmp_path, small_tile, BLOCK, executor=executor)
    finally:
        executor.shutdown()
    assert np.array_equal(_labels(finished_job[0]), _labels(job))


def test_dask_cluster_gives_the_same_labels(tmp_path, small_tile, finished_job):
    distributed = pytest.importorskip("distributed")
    from terrasift.workers.executors import make_executor

    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        executor = make_executor(dask_scheduler=cluster.scheduler_address)
        try:
            assert executor.workers == 2
            job, _ = _run(tmp_path, small_tile, BLOCK, executor=executor)
        finally:
            executor.shutdown()
    assert np.array_equal(_labels(finished_job[0]), _labels(job))


def test_multi_tile_job_has_no_seam(tmp_path, small_scene, finished_job):
    """Two tiles split down the middle give exactly the one-tile job's DTM and labels."""
    from terrasift.synthetic.terrain import Scene, write_las

    job_one, _ = finished_job
    mid = (small_scene.bounds[0] + small_scene.bounds[2]) / 2
    paths, parts = [], []
    for i, sel in enumerate([small_scene.xyz[:, 0] < mid, small_scene.xyz[:, 0] >= mid]):
        part = Scene(
            small_scene.xyz[sel],
            small_scene.truth[sel],
            small_scene.return_number[sel],
            small_scene.number_of_returns[sel],
            small_scene.surface,
            small_scene.bounds,
        )
        paths.append(write_las(part, tmp_path / f"part{i}.laz", extra_bytes=True))
        parts.append(sel)
    job = tmp_path / "job"
    jobs.prepare_job(job, paths, jobs.validate_params(BLOCK))
    names = jobs.run_job(job, InlineExecutor())
    assert {"classified-part0.laz", "classified-part1.laz", "dtm.tif"} <= set(names)
    with (
        rasterio.open(jobs.output_path(job, "dtm.tif")) as a,
        rasterio.open(jobs.output_path(job_one, "dtm.tif")) as b,
    ):
        assert a.transform == b.transform and a.shape == b.shape
        np.testing.assert_allclose(a.read(1), b.read(1), atol=1e-4)
    one = np.asarray(laspy.read(jobs.output_path(job_one, "classified.laz")).classification)
    for i, sel in enumerate(parts):
        got = np.asarray(
            laspy.read(jobs.output_path(job, f"classified-part{i}.laz")).classification
        )
        assert np.array_equal(got, one[sel])
    # Each tile's classified copy reads only the blocks under the tile: with the
    # other blocks gone, tile 0's copy comes out the same.
    from terrasift.jobs.dirs import block_results
    from terrasift.jobs.finish import write_classified
    from terrasift.tiling.blocks import BlockGrid, parse_block_name

    plan = json.loads((job / "plan.json").read_text())
    tile = plan["tiles"][0]
    under = BlockGrid(**plan["grid"]).blocks_over(tile["mins"], tile["maxs"])
    others = [p for p in block_results(job) if parse_block_name(p.stem) not in under]
    assert others and len(under) < len(block_results(job))
    for p in others:
        p.unlink()
    jobs.output_path(job, "classified-part0.laz").unlink()
    write_classified(str(job), 0)
    got = np.asarray(laspy.read(jobs.output_path(job, "classified-part0.laz")).classification)
    assert np.array_equal(got, one[parts[0]])


def test_tiles_with_different_crs_are_refused(tmp_path, small_scene):
    from terrasift.errors import InputError
    from terrasift.synthetic.terrain import write_las

    a = write_las(small_scene, tmp_path / "a.laz", crs="EPSG:32632")
    b = write_las(small_scene, tmp_path / "b.laz", crs="EPSG:25832")
    with pytest.raises(InputError, match="share a CRS"):
        jobs.inspect_inputs([a, b], jobs.validate_params({}))
    shutil.rmtree(tmp_path, ignore_errors=True)


def test_banded_slope_and_categories_equal_whole_dtm(tmp_path, small_tile, monkeypatch):
    """Slope and categories are computed over bands of DTM rows; the bands must not show."""
    from terrasift.jobs import finish as outputs
    from terrasift.jobs.params import stage_params
    from terrasift.workers import categories, terrain

    job, _ = _run(tmp_path, small_tile, {**BLOCK, "features": "none"})
    for name in ("slope.tif", "categories.tif"):
        jobs.output_path(job, name).unlink()
    monkeypatch.setattr(outputs, "BAND_CELLS", 24 * 324)  # bands of 24 rows over the 324 × 324 DTM
    outputs.write_slope(str(job))
    outputs.write_categories(str(job))
    params = jobs.load_json(job / "job.json")["params"]
    with rasterio.open(jobs.output_path(job, "dtm.tif")) as ds:
        dtm = ds.read(1, masked=True).filled(np.nan).astype(np.float64)
    tp = stage_params(params, "terrain")
    whole_slope = terrain.slope_degrees(dtm, 0.5, tp.median_size, tp.smooth)
    whole_cats = categories.compute_categories(dtm, 0.5, stage_params(params, "categories")).bands()
    with rasterio.open(jobs.output_path(job, "slope.tif")) as ds:
        np.testing.assert_allclose(
            ds.read(1, masked=True).filled(np.nan), whole_slope, atol=1e-4, equal_nan=True
        )
    with rasterio.open(jobs.output_path(job, "categories.tif")) as ds:
        assert np.array_equal(ds.read(), whole_cats)


def test_pool_forks_only_a_single_threaded_process():
    """Forking a process with other threads can deadlock a child on a held lock."""
    import threading

    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        executor = LocalExecutor(1)
        executor.shutdown()
    finally:
        stop.set()
        other.join()
    assert executor.start_method == "spawn"


@pytest.mark.skipif(sys.platform != "linux", reason="workers are forked on Linux only")
def test_forked_pool_of_the_command_line_gives_the_same_labels(tmp_path, small_tile, finished_job):
    """A fresh single-threaded process forks its workers; the labels do not change."""
    code = (
        "import sys\n"
        "from terrasift import cli\n"
        "from terrasift.workers import executors\n"
        "init = executors.LocalExecutor.__init__\n"
        "def traced(self, *a, **k):\n"
        "    init(self, *a, **k)\n"
        "    print('start method', self.start_method, file=sys.stderr)\n"
        "executors.LocalExecutor.__init__ = traced\n"
        "sys.exit(cli.main(sys.argv[1:]))\n"
    )
    args = ["classify", str(small_tile), str(tmp_path / "out.laz"), "--quiet"]
    args += [f"--param={k}={v}" for k, v in {**BLOCK, "workers": 2}.items()]
    out = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    assert "start method fork" in out.stderr
    labels = np.asarray(laspy.read(tmp_path / "out.laz").classification)
    assert np.array_equal(_labels(finished_job[0]), labels)


def test_job_measures_one_occupied_area_density_for_the_ground_stage(finished_job, small_scene):
    from terrasift.jobs.params import block_models, with_ground_density
    from terrasift.workers.ground.nist import point_spacing

    job, _ = finished_job
    plan = json.loads((job / "plan.json").read_text())
    xy = small_scene.xyz[:, :2]
    own = 1.0 / point_spacing(xy - xy.min(axis=0)) ** 2
    assert abs(plan["ground_density"] / own - 1) < 0.03
    models = with_ground_density(block_models(jobs.validate_params(BLOCK)), 2.5)
    assert models.ground_params.density == 2.5
    assert models.rotation_ground_params.density == 2.5
    # A density the job sets itself stays.
    given = jobs.validate_params({**BLOCK, "ground.nist.density": 4.0})
    assert with_ground_density(block_models(given), 2.5).ground_params.density == 4.0


def test_job_gives_data_anchored_ground_bins_one_anchor():
    """With ``bin_anchor="data"`` (the default) every block of a job bins from one anchor:
    its survey's, else the centre of its tiles' bounds; absolute bins and an anchor the job
    sets stay."""
    from terrasift.jobs.params import block_models, job_anchor, with_ground_anchor

    plan = {
        "tiles": [
            {"mins": [512.5, 40.0, 1.0], "maxs": [600.25, 100.0, 9.0]},
            {"mins": [500.25, 60.0, 0.0], "maxs": [580.0, 140.0, 5.0]},
        ]
    }
    assert job_anchor({}, plan) == (550.25, 90.0)
    assert job_anchor({"survey": {"anchor": [10.0, 20.0]}}, plan) == (10.0, 20.0)
    data = block_models(jobs.validate_params({**BLOCK, "ground.nist.bin_anchor": "data"}))
    models = with_ground_anchor(data, job_anchor({}, plan))
    assert models.ground_params.anchor == (550.25, 90.0)
    assert models.rotation_ground_params.anchor == (550.25, 90.0)
    assert block_models(jobs.validate_params(BLOCK)).ground_params.bin_anchor == "data"
    plain = block_models(jobs.validate_params({**BLOCK, "ground.nist.bin_anchor": "absolute"}))
    assert with_ground_anchor(plain, (1.0, 2.0)).ground_params.anchor is None
    given = jobs.validate_params(
        {**BLOCK, "ground.nist.bin_anchor": "data", "ground.nist.anchor": [3.0, 4.0]}
    )
    assert with_ground_anchor(block_models(given), (1.0, 2.0)).ground_params.anchor == (3.0, 4.0)


def test_square_by_square_features_equal_one_search_over_the_dtm(tmp_path, monkeypatch):
    """A job's objects are searched square by square (40 m squares here: 4 × 4 over the
    160 m DTM, a halo grown around objects across their edges); they must be the
    objects of one search over the whole DTM's category grids."""
    from terrasift.jobs import finish
    from terrasift.synthetic.terrain import Surface, make_scene, write_las
    from terrasift.workers import features as feat

    # hills on the corners the squares share
    hills = tuple(
        (x, y, 3.0, 4.0) for x, y in ((40, 40), (80, 80), (120, 120), (40, 120), (120, 40))
    )
    scene = make_scene(160, 4.0, surface=Surface(hills=hills), n_buildings=0, seed=7)
    tile = write_las(scene, tmp_path / "hills.laz")
    first, _ = _run(tmp_path, tile, BLOCK, "first")
    job = tmp_path / "job"
    shutil.copytree(first, job)
    for p in (job / "outputs").glob("features*"):
        p.unlink()
    monkeypatch.setattr(finish, "FEATURE_CORE_M", 40.0)
    finish.write_categories(str(job))
    params = jobs.load_json(job / "job.json")["params"]
    filters = feat.resolve_filters("all")
    with rasterio.open(jobs.output_path(job, "dtm.tif")) as ds:
        cats, stepped, _ = finish.dtm_category_grids(
            ds, stage_params(params, "categories"), filters
        )
        dtm = ds.read(1, masked=True).filled(np.nan).astype(np.float64)
        whole = feat.detect_features(
            cats, filters, ds.transform, cats.tile_size, stepped=stepped, dtm=dtm
        )

    def objects(features: list[dict]) -> list[str]:
        return sorted(
            json.dumps([f["geometry"], {k: f["properties"][k] for k in ("kind", "tiles")}])
            for f in features
        )

    expected = objects(feat.features_geojson(whole, 0, "x", to_wgs84=False)["features"])
    for j in (job, first):  # 40 m squares, and the default squares
        found = json.loads((j / "outputs" / "features.native.geojson").read_text())["features"]
        assert objects(found) == expected
    assert len(expected) >= 2, len(expected)


def test_the_job_reads_the_dtm_around_an_object_as_the_whole_array_holds_it(tmp_path):
    """The road filter's ``edges`` reads the job's DTM window by window
    (``finish.dtm_heights(ds).window``): heights and geotransform of the window equal
    the whole array's cells there, and the window is cut at the DTM's edges."""
    from rasterio.transform import from_origin

    from terrasift.jobs import finish

    z = np.arange(40 * 60, dtype=np.float32).reshape(40, 60)
    t = from_origin(1000.0, 2000.0, 0.5, 0.5)
    path = tmp_path / "dtm.tif"
    with rasterio.open(
        path, "w", driver="GTiff", width=60, height=40, count=1, dtype="float32", transform=t
    ) as ds:
        ds.write(z, 1)
    with rasterio.open(path) as ds:
        read = finish.dtm_heights(ds).window
        win, wt = read((1005.0, 1990.0, 1010.0, 1995.0))  # x 10-20 cells, y 10-20 rows down
        assert (wt.c, wt.f) == (1005.0, 1995.0)
        assert np.array_equal(win, z[10:20, 10:20])
        win, wt = read((990.0, 1990.0, 1002.0, 2010.0))  # past the west and north edges
        assert (wt.c, wt.f) == (1000.0, 2000.0) and np.array_equal(win, z[:20, :4])
