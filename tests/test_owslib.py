"""An OGC client (OWSLib) runs the whole cycle against the real app over HTTP:
landing page, process description, upload, asynchronous execute, polling,
results, download; then a synchronous execute with one output selected."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import rasterio

from terrasift.service.settings import Settings
from terrasift.synthetic.terrain import make_scene, write_las

processes = pytest.importorskip("owslib.ogcapi.processes", reason="OWSLib is not installed")
requests = pytest.importorskip("requests")

from live_server import live_server  # noqa: E402

PARAMS = {"block_size": 30, "buffer": 5, "resolution": 1.0}


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path]]:
    data = tmp_path_factory.mktemp("owslib") / "data"
    with live_server(Settings(_env_file=None, data_dir=data, workers=2)) as url:
        yield url, data


def test_owslib_cycle(server: tuple[str, Path], tmp_path: Path) -> None:
    server, data = server
    tile = write_las(make_scene(size=60, density=4, seed=3), tmp_path / "tile.laz")
    api = processes.Processes(server)
    assert any(p["id"] == "terrain" for p in api.processes())
    description = api.process("terrain")
    assert "files" in description["inputs"] and "dtm.tif" in description["outputs"]

    with tile.open("rb") as fh:
        r = requests.post(f"{server}/uploads", files={"file": ("tile.laz", fh)}, timeout=30)
    assert r.status_code == 201, r.text
    href = r.json()["href"]

    status = api.execute("terrain", {"files": [{"href": href}], **PARAMS}, async_=True)
    assert status["status"] in ("accepted", "running"), status
    job_id = status["jobID"]
    assert api.response_headers["Location"].endswith(f"/jobs/{job_id}")
    end = time.monotonic() + 180
    while status["status"] in ("accepted", "running") and time.monotonic() < end:
        time.sleep(0.5)
        status = api._request(path=f"jobs/{job_id}")
    assert status["status"] == "successful", status
    results = api._request(path=f"jobs/{job_id}/results")
    assert {"dtm.tif", "classified.laz", "report.json"} <= set(results)
    assert {"thumbnail.png", "hillshade.png", "features.png", "coverage.png"} <= set(results)
    dtm = requests.get(results["dtm.tif"]["href"], timeout=30)
    assert dtm.status_code == 200
    (tmp_path / "dtm.tif").write_bytes(dtm.content)
    with rasterio.open(tmp_path / "dtm.tif") as ds:
        assert ds.width > 0 and (ds.read(1, masked=True).count() > 0.5 * ds.width * ds.height)

    # synchronous (OWSLib sends Prefer: respond-sync), only the DTM computed and listed
    results = api.execute(
        "terrain", {"files": [{"href": href}], **PARAMS}, outputs={"dtm.tif": {}}, async_=False
    )
    assert set(results) == {"dtm.tif"}
    assert requests.head(results["dtm.tif"]["href"], timeout=30).status_code == 200
    job_id = results["dtm.tif"]["href"].split("/jobs/")[1].split("/")[0]
    written = {p.name for p in (data / "jobs" / job_id / "outputs").iterdir()}
    assert "dtm.tif" in written and not written & {"classified.laz", "chm.tif", "slope.tif"}
