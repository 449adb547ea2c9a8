"""`path` takes a LineString, a Feature or a FeatureCollection (QGIS exports), and
names the CRS of the coordinates it returns; `classify` writes LAS for .las."""

from __future__ import annotations

import json

import laspy
import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from terrasift.cli import main
from terrasift.errors import ParameterError
from terrasift.jobs import dtm_path_profile
from terrasift.synthetic.terrain import make_scene, write_las

X0, Y0 = 500_000.0, 5_400_000.0


@pytest.fixture(scope="module")
def plane_dtm(tmp_path_factory):
    """z = 0.1 x on a 1 m grid, EPSG:32632."""
    path = tmp_path_factory.mktemp("dtm") / "dtm.tif"
    xs = np.arange(100) + 0.5
    z = np.tile(0.1 * xs, (100, 1)).astype(np.float32)
    with rasterio.open(
        path, "w", driver="GTiff", width=100, height=100, count=1, dtype="float32",
        crs="EPSG:32632", transform=from_origin(X0, Y0 + 100, 1.0, 1.0), nodata=-9999,
    ) as ds:  # fmt: skip
        ds.write(z, 1)
    return path


def _line(y):
    return {"type": "LineString", "coordinates": [[X0 + 10, Y0 + y], [X0 + 60, Y0 + y]]}


def test_feature_collection_with_crs_member_is_read_in_its_crs(plane_dtm):
    fc = {
        "type": "FeatureCollection",
        "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32632"}},
        "features": [
            {"type": "Feature", "properties": {}, "geometry": _line(20)},
            {"type": "Feature", "properties": {}, "geometry": _line(70)},
        ],
    }
    prof = dtm_path_profile(plane_dtm, fc, spacing=5)
    assert prof.crs == "EPSG:32632"
    recs = prof.to_records()
    assert {r["line"] for r in recs} == {0, 1}
    pitch = np.array([r["pitch_deg"] for r in recs if r["pitch_deg"] is not None])
    assert np.allclose(pitch, np.degrees(np.arctan(0.1)), atol=0.3)
    assert prof.to_csv().splitlines()[0].endswith(",line")


def test_single_feature_and_wgs84_line(plane_dtm):
    prof = dtm_path_profile(plane_dtm, {"type": "Feature", "geometry": _line(50)}, crs="native")
    assert "line" not in prof.to_records()[0] and prof.crs == "EPSG:32632"
    from pyproj import Transformer

    tr = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
    lonlat = [list(tr.transform(x, y)) for x, y in _line(50)["coordinates"]]
    prof84 = dtm_path_profile(plane_dtm, {"type": "LineString", "coordinates": lonlat})
    assert prof84.profiles[0].x[0] == pytest.approx(X0 + 10, abs=0.01)


def test_non_lines_are_refused(plane_dtm):
    with pytest.raises(ParameterError, match="LineString"):
        dtm_path_profile(plane_dtm, {"type": "FeatureCollection", "features": [
            {"type": "Feature", "geometry": {"type": "Point", "coordinates": [X0, Y0]}}]})  # fmt: skip


def test_cli_path_takes_a_feature_collection_file(tmp_path, plane_dtm, capsys):
    f = tmp_path / "route.geojson"
    f.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": _line(30)}]}))  # fmt: skip
    assert main(["path", str(plane_dtm), str(f), "--crs", "EPSG:32632", "--format", "json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["crs"] == "EPSG:32632" and out["samples"][0]["x"] == pytest.approx(X0 + 10)


def test_classify_writes_las_for_las(tmp_path):
    scene = make_scene(size=40, density=2, seed=2, n_buildings=0)
    src = write_las(scene, tmp_path / "in.las")
    dst = tmp_path / "out.las"
    assert main(["classify", str(src), str(dst), "--quiet", "--param", "workers=1"]) == 0
    with laspy.open(dst) as r:
        assert not r.header.are_points_compressed
        assert r.header.point_count == len(scene)
    with open(dst, "rb") as fh:
        assert fh.read(4) == b"LASF"
