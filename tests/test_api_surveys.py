"""The /surveys API over the real pipeline: register, run, change a tile, run again, read the product."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import laspy
import numpy as np
import pytest
import rasterio
from fastapi.testclient import TestClient

from terrasift.service.app import create_app
from terrasift.service.settings import Settings
from terrasift.synthetic.terrain import make_scene, write_tiles

PARAMS = {"block_size": 20, "resolution": 0.5, "features": "hill"}


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    data = tmp_path_factory.mktemp("surveys") / "data"
    app = create_app(Settings(_env_file=None, data_dir=data, workers=1))
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def _wait(client: TestClient, job_id: str, timeout: float = 120.0) -> dict:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        info = client.get(f"/jobs/{job_id}").json()
        if info["status"] not in ("accepted", "running"):
            return info
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} still running after {timeout} s")


def _problem(r, status: int, slug: str) -> None:
    assert r.status_code == status, r.text
    assert r.json()["type"].endswith(slug), r.text


def _run(client: TestClient, sid: str, body: dict | None = None) -> dict:
    r = client.post(f"/surveys/{sid}/runs", json=body or {})
    assert r.status_code == 201, r.text
    job_id = r.json()["jobID"]
    # one run at a time: the survey refuses changes and runs until this one ends
    _problem(client.post(f"/surveys/{sid}/runs", json={}), 409, "survey-busy")
    _problem(
        client.delete(f"/surveys/{sid}/tiles/t0_0.laz"),
        409,
        "survey-busy",
    )
    info = _wait(client, job_id)
    assert info["status"] == "successful", info
    return client.get(f"/jobs/{job_id}/outputs/survey.json").json()


def test_survey_lifecycle(client: TestClient, tmp_path: Path) -> None:
    scene = make_scene(40.0, 4.0, n_buildings=0, seed=5)
    paths = write_tiles(scene, tmp_path / "tiles", 20.0)
    r = client.post(
        "/surveys",
        files=[("file", (p.name, p.read_bytes())) for p in paths],
        data={"params": json.dumps(PARAMS)},
    )
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    _problem(client.get(f"/surveys/{sid}/results"), 404, "result-not-ready")

    first = _run(client, sid)
    assert first["mode"] == "full" and len(first["outputs"]) == 4
    assert client.get(f"/surveys/{sid}").json()["product"]["tiles"] == 4
    _problem(client.post(f"/surveys/{sid}/runs", json={}), 409, "survey-unchanged")

    results = client.get(f"/surveys/{sid}/results").json()
    for name in ("dtm.vrt", "dsm.vrt", "chm.vrt", "slope.vrt", "coverage.vrt", "categories.vrt"):
        assert results[name]["type"] == "application/xml", name
    assert "collection.json" in results and "features.geojson" in results
    assert "tiles/t0_0/classified.laz" in results and "state.json" not in results
    # download the product as served and open the mosaic: its relative paths resolve
    local = tmp_path / "product"
    for name, ref in results.items():
        target = local / name
        target.parent.mkdir(parents=True, exist_ok=True)
        resp = client.get(ref["href"])
        assert resp.status_code == 200, name
        target.write_bytes(resp.content)
    with rasterio.open(local / "dtm.vrt") as ds:
        dtm = ds.read(1, masked=True)
        assert 80 <= ds.width <= 84 and 80 <= ds.height <= 84  # 40 m, up to one 2 m step more
        assert dtm.count() > 0.9 * dtm.size
    with rasterio.open(local / "categories.vrt") as ds:
        assert ds.count == 4
    # a COG reads by byte range, as GDAL's /vsicurl/ does
    part = client.get(results["tiles/t0_0/dtm.tif"]["href"], headers={"Range": "bytes=0-99"})
    assert part.status_code == 206 and len(part.content) == 100
    for bad in ("state.json", "%2E%2E/record.json", "tiles/%2E%2E/state.json", ".lock"):
        assert client.get(f"/surveys/{sid}/outputs/{bad}").status_code == 404, bad

    # replace a tile (raw body): the next run is incremental and redoes it
    las = laspy.read(paths[0])
    las.z = np.asarray(las.z) + 0.5
    changed = tmp_path / "t0_0.laz"
    las.write(changed)
    r = client.put(
        f"/surveys/{sid}/tiles/t0_0.laz",
        content=changed.read_bytes(),
        headers={"content-type": "application/octet-stream"},
    )
    assert r.status_code == 200, r.text
    second = _run(client, sid)
    assert second["mode"] == "incremental" and "t0_0.laz" in second["outputs"]
    after = tmp_path / "after.tif"
    after.write_bytes(client.get(results["tiles/t0_0/dtm.tif"]["href"]).content)
    with rasterio.open(local / "tiles/t0_0/dtm.tif") as a, rasterio.open(after) as b:
        lift = b.read(1, masked=True) - a.read(1, masked=True)
    assert abs(float(np.ma.median(lift)) - 0.5) < 0.05

    # a new tile by upload (201), then removed again
    r = client.put(
        f"/surveys/{sid}/tiles/x.laz",
        content=b"not a las file",
        headers={"content-type": "application/octet-stream"},
    )
    _problem(r, 422, "invalid-input")
    _problem(client.put(f"/surveys/{sid}/tiles/x.txt", content=b"x"), 400, "invalid-request")
    r = client.delete(f"/surveys/{sid}/tiles/t1_1.laz")
    assert r.status_code == 200 and "t1_1.laz" not in r.json()["files"]
    _problem(client.delete(f"/surveys/{sid}/tiles/t1_1.laz"), 404, "not-found")
    third = _run(client, sid)
    assert third["mode"] == "incremental" and "t1_1.laz" not in third["outputs"]
    results = client.get(f"/surveys/{sid}/results").json()
    assert not [n for n in results if n.startswith("tiles/t1_1/")]
    collection = client.get(results["collection.json"]["href"]).json()
    assert len([ln for ln in collection["links"] if ln["rel"] == "item"]) == 3
    # adding a tile answers 201; its first run will redo it and its neighbours
    r = client.put(
        f"/surveys/{sid}/tiles/t1_1.laz",
        content=paths[3].read_bytes(),
        headers={"content-type": "application/octet-stream"},
    )
    assert r.status_code == 201 and "t1_1.laz" in r.json()["files"], r.text


def test_a_survey_over_the_point_limit_runs_in_batches(tmp_path: Path) -> None:
    # a 4 x 1 strip over the service's max_points: accepted, and run in batches queued
    # one after the other, each reading at most max_points (its tiles and their halo)
    scene = make_scene(80.0, 4.0, height=20.0, n_buildings=0, seed=5)
    paths = write_tiles(scene, tmp_path / "tiles", 20.0)
    total = sum(laspy.open(p).header.point_count for p in paths)
    limit = int(0.8 * total)
    settings = Settings(_env_file=None, data_dir=tmp_path / "data", workers=1, max_points=limit)
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        r = client.post(
            "/surveys",
            files=[("file", (p.name, p.read_bytes())) for p in paths],
            data={"params": json.dumps(PARAMS)},
        )
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        assert client.post(f"/surveys/{sid}/runs", json={}).status_code == 201
        end = time.monotonic() + 240
        while True:
            doc = client.get(f"/surveys/{sid}").json()
            busy = [j for j in doc["jobs"] if j["status"] in ("accepted", "running")]
            if not busy and doc["product"] and doc["product"]["pending"] == 0:
                break
            assert all(j["status"] != "failed" for j in doc["jobs"]), doc["jobs"]
            assert time.monotonic() < end, doc
            time.sleep(0.3)
        jobs = doc["jobs"]
        assert len(jobs) >= 2 and all(j["status"] == "successful" for j in jobs), jobs
        done = []
        for j in jobs:
            summary = client.get(f"/jobs/{j['jobID']}/outputs/survey.json").json()
            done += summary["outputs"]
            job_points = sum(
                laspy.open(tmp_path / "tiles" / n).header.point_count for n in summary["sources"]
            )
            assert job_points <= limit
        assert sorted(done) == sorted(p.name for p in paths)
        assert doc["product"]["tiles"] == 4
        _problem(client.post(f"/surveys/{sid}/runs", json={}), 409, "survey-unchanged")
