"""item.json: a valid STAC Item (core schema shipped by pystac, extension schemas
under tests/schemas), offline, whose assets describe the files as they are."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import rasterio

from terrasift import jobs
from terrasift.synthetic.terrain import make_scene, write_las
from terrasift.workers.executors import InlineExecutor

SCHEMAS = Path(__file__).parent / "schemas"


def _validator():
    jsonschema = pytest.importorskip("jsonschema")
    pystac = pytest.importorskip("pystac")
    from referencing import Registry, Resource
    from referencing.jsonschema import DRAFT7

    root = Path(pystac.__file__).parent / "validation" / "jsonschemas"
    resources = []
    for path in (root / "stac-spec" / "v1.1.0").glob("*.json"):
        url = f"https://schemas.stacspec.org/v1.1.0/item-spec/json-schema/{path.name}"
        resources.append((url, Resource.from_contents(json.loads(path.read_text()), DRAFT7)))
    for path in (root / "geojson").glob("*.json"):
        url = f"https://geojson.org/schema/{path.name}"
        resources.append((url, Resource.from_contents(json.loads(path.read_text()), DRAFT7)))
    registry = Registry().with_resources(resources)
    core_url = "https://schemas.stacspec.org/v1.1.0/item-spec/json-schema/item.json"
    ext = {}
    for path in SCHEMAS.glob("*.json"):
        schema = json.loads(path.read_text())
        ext[schema["$id"]] = schema

    def validate(item: dict) -> None:
        core = registry.contents(core_url)
        jsonschema.Draft7Validator(core, registry=registry).validate(item)
        for url in item.get("stac_extensions", []):
            assert url in ext, f"no schema kept for {url}"
            jsonschema.Draft7Validator(ext[url]).validate(item)

    return validate


def _job(tmp_path, crs):
    scene = make_scene(size=70, density=3, seed=31, n_buildings=2, building_size=(10, 15))
    tile = write_las(scene, tmp_path / "t.laz", crs=crs)
    job = tmp_path / "job"
    params = {"features": "none"} if crs is None else {}
    jobs.prepare_job(job, [tile], jobs.validate_params(params))
    jobs.run_job(job, InlineExecutor())
    return job, json.loads((job / "outputs" / "item.json").read_text())


@pytest.fixture(scope="module")
def with_crs(tmp_path_factory):
    return _job(tmp_path_factory.mktemp("stac"), "EPSG:32632")


def test_item_is_valid_stac(with_crs):
    _, item = with_crs
    _validator()(item)


def test_raster_assets_carry_their_own_grid_and_bands(with_crs):
    job, item = with_crs
    for name, asset in item["assets"].items():
        if not name.endswith(".tif"):
            continue
        with rasterio.open(job / "outputs" / name) as ds:
            assert asset["proj:shape"] == [ds.height, ds.width], name
            assert asset["proj:transform"] == pytest.approx(list(ds.transform)[:6]), name
            bands = asset["raster:bands"]
            assert len(bands) == ds.count
            assert bands[0]["data_type"] == ds.dtypes[0]
            assert bands[0]["nodata"] == ds.nodata
    assert item["assets"]["coverage.tif"]["raster:bands"][0]["nodata"] == 255
    assert item["assets"]["dtm.tif"]["raster:bands"][0]["unit"] == "m"
    assert item["assets"]["slope.tif"]["raster:bands"][0]["unit"] == "deg"
    dtm, cov = item["assets"]["dtm.tif"], item["assets"]["categories.tif"]
    assert dtm["proj:transform"][0] != cov["proj:transform"][0]  # 0.5 m against 2 m


def test_pointcloud_links_footprint_and_time(with_crs):
    _, item = with_crs
    laz = item["assets"]["classified.laz"]
    assert laz["pc:count"] > 0 and laz["pc:encoding"] == "LASzip"
    assert {"X", "Y", "Z", "classification"} <= {s["name"] for s in laz["pc:schemas"]}
    rels = {link["rel"] for link in item["links"]}
    assert {"self", "parent"} <= rels
    assert item["geometry"]["type"] in ("Polygon", "MultiPolygon")
    lon0, lat0, lon1, lat1 = item["bbox"]
    assert 7 < lon0 < lon1 < 11 and 47 < lat0 < lat1 < 50
    assert "created" in item["properties"]


def test_item_without_crs_is_valid(tmp_path):
    job, item = _job(tmp_path, None)
    assert item["geometry"] is None and "bbox" not in item
    _validator()(item)


def test_rasters_describe_themselves(with_crs):
    job, _ = with_crs
    out = job / "outputs"
    for name, unit in (("dtm", "m"), ("dsm", "m"), ("chm", "m"), ("slope", "deg")):
        with rasterio.open(out / f"{name}.tif") as ds:
            assert ds.units[0] == unit and ds.descriptions[0], name
    with rasterio.open(out / "coverage.tif") as ds:
        assert ds.descriptions[0] == "vegetation bin class"
        cmap = ds.colormap(1)
        assert cmap[3] != cmap[4]  # tree and building differ
        assert ds.tags(1)["CLASS_4"] == "building"
    with rasterio.open(out / "categories.tif") as ds:
        assert ds.descriptions == ("inclination", "orientation", "state", "height_x10")
        assert ds.units[3] == "dm"
        assert "E" in ds.tags(1)["CLASSES"] and "ridge" in ds.tags(3)["CLASSES"]
