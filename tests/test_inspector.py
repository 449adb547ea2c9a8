"""Tile headers are read in disposable subprocesses: a reader that aborts, runs out of its
memory budget, spins or is starved fails only that request, with a verdict naming the file,
and the API goes on serving."""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from misbehaving_reader import misbehaving_read

from terrasift.errors import InputError, Unavailable
from terrasift.jobs.plan import header_reader
from terrasift.service.app import create_app
from terrasift.service.inspector import HeaderInspector
from terrasift.service.settings import Settings
from terrasift.tiling.lasfile import read_tile_info

PARAMS = '{"block_size": 40, "buffer": 4, "resolution": 1.0, "features": "none"}'


@pytest.fixture(scope="module")
def inspector() -> Iterator[HeaderInspector]:
    # a wall budget far above the CPU budget, so that a spinning reader reaches its CPU
    # limit first even on a loaded machine
    insp = HeaderInspector(
        2, seconds=0.5, memory=256 * 1024**2, read=misbehaving_read, wall_factor=40
    )
    yield insp
    insp.stop()


def _copy(tile: Path, folder: Path, name: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    target = folder / name
    shutil.copyfile(tile, target)
    return target


def test_a_reader_that_crashes_or_exhausts_its_budget_fails_naming_the_file(
    inspector: HeaderInspector, small_tile: Path, tmp_path: Path
) -> None:
    good = _copy(small_tile, tmp_path, "good.las")
    (info,) = inspector([good])
    assert info == read_tile_info(good)
    before = inspector.replaced
    cases = {
        "abort.las": (InputError, "SIGABRT"),
        "greedy.las": (InputError, "memory budget of 256 MiB"),
        "spin.las": (InputError, "took more than 0.5 s of CPU and was stopped"),
        "killed.las": (Unavailable, "stopped from outside (SIGKILL"),
    }
    for name, (kind, words) in cases.items():
        bad = _copy(small_tile, tmp_path, name)
        started = time.monotonic()
        with pytest.raises(kind) as caught:
            inspector([good, bad, good])
        assert str(caught.value).startswith(f"{name}: "), caught.value
        assert words in str(caught.value), caught.value
        assert time.monotonic() - started < 20
        # the next request is served by the readers left and the replacements
        assert inspector([good]) == [info]
    # every reader that crashed, overran or was killed was replaced; the memory
    # budget made the allocation fail inside the reader, which lives on
    assert inspector.replaced - before == 3
    deadline = time.monotonic() + 10  # the last replacement starts in the background
    while len(inspector.pids()) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert len(inspector.pids()) == 2


def test_a_reader_starved_of_cpu_is_the_machines_fault(small_tile: Path, tmp_path: Path) -> None:
    insp = HeaderInspector(1, seconds=0.2, read=misbehaving_read)
    try:
        sleepy = _copy(small_tile, tmp_path, "sleepy.las")
        with pytest.raises(
            Unavailable, match=r"^sleepy.las: reading its header got only .* too busy"
        ):
            insp([sleepy])
        assert insp.replaced == 1
    finally:
        insp.stop()
    with pytest.raises(Unavailable, match="shutting down"):
        insp([sleepy])


def test_an_input_error_found_in_a_reader_is_the_header_checks_own(
    inspector: HeaderInspector, tmp_path: Path
) -> None:
    bad = tmp_path / "notlas.las"
    bad.write_bytes(b"PK\x03\x04" + bytes(400))
    with pytest.raises(InputError, match=r"notlas.las: not a LAS/LAZ file"):
        inspector([bad])


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    data = tmp_path_factory.mktemp("inspected-app") / "data"
    root = tmp_path_factory.mktemp("input-root")
    settings = Settings(
        _env_file=None,
        data_dir=data,
        input_root=root,
        workers=1,
        header_readers=1,
        header_seconds=2,
        shutdown_grace=0.5,
    )
    app = create_app(settings, read_header=misbehaving_read)
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def test_an_upload_whose_header_read_aborts_is_refused_and_the_api_serves_on(
    client: TestClient, small_tile: Path, tmp_path: Path
) -> None:
    svc = client.app.state.svc  # type: ignore[attr-defined]
    assert header_reader() is svc.inspector
    readers = client.get("/health").json()["header_readers"]
    assert len(readers) == 1
    r = client.post(
        "/jobs",
        files=[("file", ("abort.las", small_tile.read_bytes()))],
        data={"params": PARAMS},
        headers={"Prefer": "respond-async"},
    )
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert detail.startswith("abort.las: reading its header crashed the reader (SIGABRT)")
    assert "Traceback" not in detail
    assert client.get("/jobs").json()["jobs"] == []  # nothing recorded
    # the API process is this one: it served on, with a new reader
    health = client.get("/health")
    assert health.status_code == 200
    assert health.json()["header_readers"] != readers
    r = client.post(
        "/jobs",
        files=[("file", ("good.las", small_tile.read_bytes()))],
        data={"params": PARAMS},
        headers={"Prefer": "respond-async"},
    )
    assert r.status_code == 201, r.text


def test_server_paths_and_survey_tiles_are_read_by_the_readers_too(
    client: TestClient, small_tile: Path
) -> None:
    root = client.app.state.settings.input_root  # type: ignore[attr-defined]
    _copy(small_tile, root, "good.las")
    _copy(small_tile, root, "greedy.las")
    _copy(small_tile, root, "sleepy.las")
    r = client.post(
        "/processes/terrain/execution",
        json={"inputs": {"files": ["greedy.las"]}},
        headers={"Prefer": "respond-async"},
    )
    assert r.status_code == 422, r.text
    assert r.json()["detail"].startswith("greedy.las: reading its header needs more than")
    # a reader starved of CPU is the machine's fault: 503 with Retry-After
    r = client.post("/surveys", json={"files": ["good.las", "sleepy.las"]})
    assert r.status_code == 503, r.text
    assert r.headers["Retry-After"]
    assert r.json()["detail"].startswith("sleepy.las: reading its header got only")
    r = client.post("/surveys", json={"files": ["good.las"]})
    assert r.status_code == 201, r.text
    survey = r.json()["id"]
    r = client.put(
        f"/surveys/{survey}/tiles/abort.las",
        content=small_tile.read_bytes(),
        headers={"Content-Type": "application/octet-stream"},
    )
    assert r.status_code == 422, r.text
    assert "abort.las: reading its header crashed the reader" in r.json()["detail"]
    assert client.get("/health").status_code == 200


def test_the_files_of_one_request_are_read_side_by_side(
    inspector: HeaderInspector, small_tile: Path, tmp_path: Path
) -> None:
    """Four files of one request go to both readers at once (their reads overlap in time),
    the answers come back in the request's order, and a wrong file among them raises
    naming it."""
    deadline = time.monotonic() + 30
    while len(inspector.pids()) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    files = [_copy(small_tile, tmp_path, f"slow{i}.las") for i in range(4)]
    infos = inspector(files)
    assert [Path(i.path).name for i in infos] == [f.name for f in files]
    reads = [Path(f"{f}.read").read_text().split() for f in files]
    by_reader: dict[str, list[tuple[float, float]]] = {}
    for pid, start, end in reads:
        by_reader.setdefault(pid, []).append((float(start), float(end)))
    assert len(by_reader) == 2, reads
    first, second = by_reader.values()
    assert any(a0 < b1 and b0 < a1 for a0, a1 in first for b0, b1 in second), reads
    bad = _copy(small_tile, tmp_path, "abort.las")
    with pytest.raises(InputError, match=r"^abort\.las: "):
        inspector([files[0], bad, files[1], files[2]])


def test_the_crs_is_parsed_by_the_reader(
    inspector: HeaderInspector,
    small_tile: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The reader gives each tile's CRS label with its WKT: checking a job's inputs in the
    API process parses no CRS when its tiles share one (pyproj's parser is made to fail
    here), and tiles whose CRS differ are still refused naming both."""
    import pyproj

    from terrasift.jobs import plan
    from terrasift.synthetic.terrain import make_scene, write_las

    a, b = _copy(small_tile, tmp_path, "a.laz"), _copy(small_tile, tmp_path, "b.laz")
    other = write_las(make_scene(size=40, density=2, seed=1), tmp_path / "c.laz", crs="EPSG:25832")
    old = plan.use_header_reader(inspector)
    try:
        with monkeypatch.context() as m:
            m.setattr(pyproj.CRS, "from_wkt", lambda *a, **k: pytest.fail("parsed in the API"))
            summary = plan.inspect_inputs([a, b], {})
        assert summary["crs"] == "EPSG:32632" and summary["tiles"] == 2
        with pytest.raises(InputError, match=r"c\.laz is EPSG:25832, the first tile is EPSG:32632"):
            plan.inspect_inputs([a, other], {})
    finally:
        plan.use_header_reader(old)
