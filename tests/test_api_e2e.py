"""End to end through the real app, pipeline and process pool: upload → poll → download → open.

Also the bad inputs of issue 2 item 8, each refused at submission with a
problem+json body that names the problem, leaving no job behind.
"""

from __future__ import annotations

import io
import json
import struct
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pytest
import rasterio
from fastapi.testclient import TestClient

from terrasift.service.app import create_app
from terrasift.service.settings import Settings
from terrasift.synthetic.terrain import make_scene, write_las

PROBLEM = "application/problem+json"
PARAMS = {"block_size": 30, "buffer": 5, "resolution": 1.0}


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    data = tmp_path_factory.mktemp("e2e") / "data"
    app = create_app(Settings(_env_file=None, data_dir=data, workers=2))
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Path]:
    scene = make_scene(size=60, density=4, seed=3)
    return scene, write_las(scene, tmp_path_factory.mktemp("tiles") / "tile.laz", extra_bytes=True)


def submit(client: TestClient, name: str, data: bytes, params: Any = None):
    form = {"params": json.dumps(params)} if params is not None else None
    return client.post("/jobs", files=[("file", (name, data))], data=form)


def wait_final(client: TestClient, job_id: str, timeout: float = 120.0) -> tuple[dict, list[int]]:
    seen: list[int] = []
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        info = client.get(f"/jobs/{job_id}").json()
        seen.append(info["progress"])
        if info["status"] not in ("accepted", "running"):
            return info, seen
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} still {info['status']} after {timeout} s")


def test_upload_poll_download_open(
    client: TestClient, scene_file: tuple[Any, Path], tmp_path: Path
) -> None:
    scene, path = scene_file
    r = submit(client, "tile.laz", path.read_bytes(), PARAMS)
    assert r.status_code == 201, r.text
    job_id = r.json()["jobID"]
    info, seen = wait_final(client, job_id)
    assert info["status"] == "successful", info
    assert info["progress"] == 100 and seen == sorted(seen)  # progress never goes back

    results = client.get(f"/jobs/{job_id}/results").json()
    for name, media in [
        ("classified.laz", "application/vnd.laszip"),
        ("dtm.tif", "image/tiff; application=geotiff; profile=cloud-optimized"),
        ("dsm.tif", "image/tiff; application=geotiff; profile=cloud-optimized"),
        ("report.json", "application/json"),
    ]:
        assert results[name]["type"] == media

    # the DTM: a GeoTIFF in the tile CRS over the tile, close to the true surface
    dtm = client.get(results["dtm.tif"]["href"])
    assert dtm.status_code == 200 and dtm.headers["content-type"].startswith("image/tiff")
    assert int(dtm.headers["content-length"]) == len(dtm.content)
    head = client.get(results["dtm.tif"]["href"], headers={"Range": "bytes=0-4095"})
    assert (
        head.status_code == 206 and head.content == dtm.content[:4096] and head.content[:2] == b"II"
    )
    (tmp_path / "dtm.tif").write_bytes(dtm.content)
    with rasterio.open(tmp_path / "dtm.tif") as ds:
        assert ds.crs.to_epsg() == 32632 and ds.dtypes[0] == "float32"
        assert ds.res == (1.0, 1.0)
        z = ds.read(1, masked=True)
        rows, cols = np.nonzero(~np.ma.getmaskarray(z) & np.isfinite(z.filled(np.nan)))
        xs, ys = rasterio.transform.xy(ds.transform, rows, cols)
        err = z.filled(np.nan)[rows, cols] - scene.surface(np.asarray(xs), np.asarray(ys))
    assert rows.size > 0.6 * (60 * 60)  # most of the 60 m × 60 m tile has ground
    assert np.median(np.abs(err)) < 0.5

    # the classified cloud: every point, in input order, extra bytes kept
    laz = client.get(results["classified.laz"]["href"])
    las = laspy.read(io.BytesIO(laz.content))
    assert len(las.points) == len(scene)
    np.testing.assert_allclose(np.column_stack([las.x, las.y, las.z]), scene.xyz, atol=0.006)
    np.testing.assert_array_equal(np.asarray(las.truth), scene.truth)
    classes = np.asarray(las.classification)
    assert set(np.unique(classes)) <= {1, 2, 3, 4, 5, 6, 7}
    truly_ground = scene.is_ground
    assert (classes[truly_ground] == 2).mean() > 0.8
    head = client.head(results["classified.laz"]["href"])
    assert (
        head.headers["content-length"] == str(len(laz.content))
        and head.headers["etag"] == laz.headers["etag"]
    )

    report = client.get(results["report.json"]["href"]).json()
    assert json.dumps(report)  # plain JSON
    assert [j["jobID"] for j in client.get("/jobs").json()["jobs"]][0] == job_id


def test_dismiss_stops_a_real_job(client: TestClient, scene_file: tuple[Any, Path]) -> None:
    _, path = scene_file
    job_id = submit(
        client, "tile.laz", path.read_bytes(), {**PARAMS, "block_size": 20, "buffer": 2}
    ).json()["jobID"]
    end = time.monotonic() + 30
    while client.get(f"/jobs/{job_id}").json()["status"] == "accepted" and time.monotonic() < end:
        time.sleep(0.05)
    assert client.delete(f"/jobs/{job_id}").json()["status"] == "dismissed"
    scheduler = client.app.state.svc.scheduler
    end = time.monotonic() + 60
    while scheduler.is_active(job_id) and time.monotonic() < end:
        time.sleep(0.1)
    assert not scheduler.is_active(job_id)
    info = client.get(f"/jobs/{job_id}").json()
    assert info["status"] == "dismissed"
    assert not scheduler.pipeline.output_path(scheduler.job_dir(job_id), "dtm.tif").exists()
    assert client.get(f"/jobs/{job_id}/results").status_code == 410


def _las_bytes(tmp_path: Path, suffix: str, n_points: int | None = None) -> bytes:
    scene = make_scene(size=30, density=2, seed=5, n_buildings=0)
    path = write_las(scene, tmp_path / f"t{suffix}", point_format=1, version="1.2")
    data = path.read_bytes()
    if n_points is not None:  # LAS 1.2: legacy point count at byte 107
        data = data[:107] + struct.pack("<I", n_points) + data[111:]
    return data


def _empty_las(tmp_path: Path) -> bytes:
    header = laspy.LasHeader(point_format=1, version="1.2")
    las = laspy.LasData(header)
    las.write(str(tmp_path / "empty.las"))
    return (tmp_path / "empty.las").read_bytes()


def _bad_scale(tmp_path: Path) -> bytes:
    data = _las_bytes(tmp_path, ".las")
    return data[:131] + struct.pack("<d", 1e9) + data[139:]  # x scale factor


BAD_INPUTS = {
    "not-a-las": (lambda tmp: b"This is a CSV,x,y,z\n1,2,3\n" * 20, "notes.las", 422, "not a LAS"),
    "truncated-laz": (lambda tmp: _las_bytes(tmp, ".laz")[:2000], "cut.laz", 422, "truncated"),
    "zero-points": (_empty_las, "empty.las", 422, "no points"),
    "header-claims-more": (
        lambda tmp: _las_bytes(tmp, ".las", n_points=10**6),
        "liar.las",
        422,
        "claims 1000000 points",
    ),
    "absurd-scale": (_bad_scale, "scale.las", 422, "scale"),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_files_are_refused_at_submission(client: TestClient, tmp_path: Path, case: str) -> None:
    make, name, status, mention = BAD_INPUTS[case]
    before = client.get("/jobs?limit=1000").json()["jobs"]
    r = submit(client, name, make(tmp_path))
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == PROBLEM
    body = r.json()
    assert (
        body["type"] == "/problems/invalid-input"
        and body["status"] == status
        and body["instance"] == "/jobs"
    )
    assert name in body["detail"] and mention in body["detail"], body["detail"]
    assert client.get("/jobs?limit=1000").json()["jobs"] == before


@pytest.mark.parametrize(
    ("params", "mention"),
    [
        ({"colour": "red"}, "colour"),
        ({"resolution": 0}, "resolution"),
        ({"ground": "magic"}, "ground"),
        ({"buffer": 1e6}, "buffer"),
    ],
)
def test_bad_parameters_are_refused_at_submission(
    client: TestClient, scene_file: tuple[Any, Path], params: dict, mention: str
) -> None:
    _, path = scene_file
    r = submit(client, "tile.laz", path.read_bytes(), params)
    assert r.status_code == 400, r.text
    body = r.json()
    assert r.headers["content-type"] == PROBLEM and body["type"] == "/problems/invalid-parameter"
    assert mention in body["detail"]


def test_path_profile_json_csv_and_bad_line(client: TestClient, tmp_path: Path) -> None:
    scene = make_scene(
        size=60, density=4, seed=3, n_buildings=0
    )  # the profile, not the ground filter, is tested
    path = write_las(scene, tmp_path / "bare.laz")
    job_id = submit(client, "bare.laz", path.read_bytes(), {**PARAMS, "features": "none"}).json()[
        "jobID"
    ]
    info, _ = wait_final(client, job_id)
    assert info["status"] == "successful", info
    x0, y0, x1, y1 = scene.bounds
    line = {"type": "LineString", "coordinates": [[x0 + 10, y0 + 30], [x1 - 10, y0 + 30]]}
    r = client.post(f"/jobs/{job_id}/path", params={"crs": "native", "spacing": 5}, json=line)
    assert r.status_code == 200, r.text
    samples = r.json()["samples"]
    assert r.json()["crs"] == "EPSG:32632"  # the samples' x, y are in the tile CRS
    assert len(samples) == 9 and samples[-1]["distance"] == pytest.approx(40.0)
    # the scene's surface: its z along the line, and pitch from its slope toward the east
    xs = np.array([s["x"] for s in samples])
    truth = scene.surface(xs, np.full_like(xs, y0 + 30))
    assert np.abs(np.array([s["z"] for s in samples]) - truth).max() < 0.3
    csv = client.post(f"/jobs/{job_id}/path", params={"crs": "native", "f": "csv"}, json=line)
    assert csv.headers["content-type"].startswith("text/csv") and csv.text.splitlines()[
        0
    ].startswith("distance")
    bad = client.post(f"/jobs/{job_id}/path", json={"type": "Point", "coordinates": [1, 2]})
    assert bad.status_code == 400 and bad.headers["content-type"].startswith(PROBLEM)
    assert "LineString" in bad.json()["detail"]
    # a FeatureCollection as QGIS exports it, its CRS named by a crs member
    fc = {
        "type": "FeatureCollection",
        "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32632"}},
        "features": [{"type": "Feature", "properties": {}, "geometry": line}] * 2,
    }
    two = client.post(f"/jobs/{job_id}/path", params={"spacing": 5}, json=fc)
    assert two.status_code == 200, two.text
    assert {s["line"] for s in two.json()["samples"]} == {0, 1}
