"""Features in the tile CRS that OGR reads with that CRS; without a CRS still written, with a warning."""

from __future__ import annotations

import json

import pyogrio
import pyproj
import pytest

from terrasift import jobs
from terrasift.synthetic.terrain import Surface, make_scene, write_las
from terrasift.workers.executors import InlineExecutor


def _job(tmp_path, crs):
    # a 120 m tile of 1 % slope holds one 100 m square of flat ground, an object to write
    # (these tests are about the files' CRS, not about which objects are found)
    surface = Surface(gx=0.01, gy=0.0, waves=())
    scene = make_scene(size=120, density=2, seed=7, n_buildings=1, surface=surface)
    tile = write_las(scene, tmp_path / "f.laz", crs=crs)
    job = tmp_path / "job"
    jobs.prepare_job(job, [tile], jobs.validate_params({}))
    names = jobs.run_job(job, InlineExecutor())
    return job / "outputs", names


@pytest.fixture(scope="module")
def utm(tmp_path_factory):
    return _job(tmp_path_factory.mktemp("vec"), "EPSG:32632")


def test_native_features_are_read_in_the_tile_crs(utm):
    out, names = utm
    assert {"features.gpkg", "features.native.geojson", "features.geojson"} <= set(names)
    for name in ("features.gpkg", "features.native.geojson"):
        info = pyogrio.read_info(out / name)
        assert pyproj.CRS.from_user_input(info["crs"]).to_epsg() == 32632, name
        assert info["features"] > 0
        xmin, ymin, _, _ = info["total_bounds"]
        assert xmin > 400_000 and ymin > 5_000_000  # UTM metres, not degrees
    gj = json.loads((out / "features.geojson").read_text())
    assert "crs" not in gj  # RFC 7946: WGS 84 lon/lat, no crs member
    lon, lat = gj["features"][0]["geometry"]["coordinates"][0][0]
    assert 5 < lon < 12 and 45 < lat < 50


def test_without_crs_features_are_written_natively_with_a_warning(tmp_path):
    out, names = _job(tmp_path, None)
    assert "features.geojson" not in names
    assert {"features.gpkg", "features.native.geojson"} <= set(names)
    assert pyogrio.read_info(out / "features.gpkg")["features"] > 0
    report = json.loads((out / "report.json").read_text())
    assert any("no CRS" in w and "features" in w for w in report["warnings"])
