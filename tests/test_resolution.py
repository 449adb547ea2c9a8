"""Any resolution from 0.1 to 10 m by itself: sizes follow it, contradictions are refused together."""

from __future__ import annotations

import pytest
import rasterio

from terrasift import jobs
from terrasift.errors import ParameterError
from terrasift.synthetic.terrain import make_scene, write_las
from terrasift.workers.executors import InlineExecutor

RESOLUTIONS = (0.1, 0.3, 0.75, 1.5, 2, 3, 5, 10)


@pytest.fixture(scope="module")
def tiny_tile(tmp_path_factory):
    scene = make_scene(size=60, density=2, seed=11, n_buildings=1, building_size=(10, 15))
    return write_las(scene, tmp_path_factory.mktemp("res") / "tiny.laz")


@pytest.mark.parametrize("resolution", RESOLUTIONS)
def test_resolution_alone_runs_a_whole_job(tmp_path, tiny_tile, resolution):
    params = jobs.validate_params({"resolution": resolution})
    cells = {k: params[k] / resolution for k in ("vegetation.cell", "terrain.cell")}
    assert all(abs(c - round(c)) < 1e-6 and round(c) >= 1 for c in cells.values())
    tiles = params["categories.tile_size"] / resolution
    assert abs(tiles - round(tiles)) < 1e-6 and round(tiles) >= 2
    job = tmp_path / "job"
    jobs.prepare_job(job, [tiny_tile], params)
    names = jobs.run_job(job, InlineExecutor())
    assert {"dtm.tif", "coverage.tif", "categories.tif", "slope.tif"} <= set(names)
    with rasterio.open(job / "outputs" / "dtm.tif") as ds:
        assert ds.res == pytest.approx((resolution, resolution))
    with rasterio.open(job / "outputs" / "coverage.tif") as ds:
        assert ds.res[0] == pytest.approx(params["vegetation.cell"])
    with rasterio.open(job / "outputs" / "categories.tif") as ds:
        assert ds.res[0] == pytest.approx(params["categories.tile_size"])


def test_explicit_sizes_that_follow_the_resolution_are_kept():
    params = jobs.validate_params(
        {"resolution": 2, "vegetation.cell": 4, "categories.tile_size": 8}
    )
    assert params["vegetation.cell"] == 4
    assert params["categories.tile_size"] == 8
    assert params["terrain.cell"] == 2


def test_every_contradiction_is_named_at_once():
    with pytest.raises(ParameterError) as err:
        jobs.validate_params(
            {
                "resolution": 2,
                "vegetation.cell": 1,
                "terrain.cell": 3,
                "categories.tile_size": 2,
            }
        )
    msg = str(err.value)
    for key in ("vegetation.cell", "terrain.cell", "categories.tile_size"):
        assert key in msg


def test_fixed_parameter_errors_are_reported_together():
    with pytest.raises(ParameterError) as err:
        jobs.validate_params({"resolution": -1, "block_size": 1})
    assert "resolution" in str(err.value) and "block_size" in str(err.value)
