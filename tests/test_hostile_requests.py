"""Nothing a client sends gets a 5xx: deep or huge JSON, giant numbers, control characters,
out-of-range query parameters, an unwritable data directory, a symlink swapped in under
the input root."""

from __future__ import annotations

import errno
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from terrasift.service.app import create_app
from terrasift.service.guard import json_depth
from terrasift.service.settings import Settings
from terrasift.synthetic.terrain import make_scene, write_las


@pytest.fixture(scope="module")
def tile(tmp_path_factory: pytest.TempPathFactory) -> Path:
    scene = make_scene(size=40, density=2, seed=5)
    return write_las(scene, tmp_path_factory.mktemp("hostile") / "tile.las")


@pytest.fixture()
def client(tmp_path: Path, tile: Path) -> Iterator[TestClient]:
    root = tmp_path / "root"
    root.mkdir()
    (root / "tile.las").write_bytes(tile.read_bytes())
    settings = Settings(
        _env_file=None, data_dir=tmp_path / "data", workers=1, input_root=root, sync_max_points=0
    )
    app = create_app(settings, executor_factory=lambda: pytest.fail("no job should run"))
    with TestClient(app, raise_server_exceptions=False) as c:
        c.app.state.svc.scheduler.stop()  # nothing runs: only the answers matter here
        yield c


def _problem(r, status: int) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    return r.json()


def test_json_depth_ignores_brackets_in_strings() -> None:
    assert json_depth('{"a": "[[[[{{{{", "b": [1, [2]]}') == 3


@pytest.mark.parametrize(
    "body",
    [
        "[" * 100_000 + "]" * 100_000,
        '{"inputs": {"files": ["tile.las"], "params": ' + '{"a":' * 5000 + "1" + "}" * 5001 + "}}",
        '{"inputs": {"files": ["tile.las"], "resolution": ' + "9" * 5000 + "}}",
        '{"inputs": {"files": ["tile\\u0000.las"]}}',
        '{"inputs": {"files": ["tile.las"], "features": "ditch\\u0000"}}',
        '{"inputs": ',
    ],
)
def test_hostile_execute_bodies_get_400(client: TestClient, body: str) -> None:
    r = client.post(
        "/processes/terrain/execution",
        content=body,
        headers={"Content-Type": "application/json"},
    )
    _problem(r, 400)


def test_oversized_json_gets_413(client: TestClient) -> None:
    body = json.dumps({"inputs": {"files": ["tile.las"], "pad": "x" * 2_000_000}})
    r = client.post(
        "/processes/terrain/execution", content=body, headers={"Content-Type": "application/json"}
    )
    _problem(r, 413)


@pytest.mark.parametrize(
    "params",
    [
        '{"a":' * 5000 + "1" + "}" * 5000,
        '{"resolution": ' + "1" * 5000 + "}",
        '{"features": "ditch\\u0000"}',
    ],
)
def test_hostile_multipart_params_get_4xx(client: TestClient, tile: Path, params: str) -> None:
    r = client.post(
        "/jobs", files=[("file", ("t.las", tile.read_bytes()))], data={"params": params}
    )
    assert 400 <= r.status_code < 500, r.text
    assert not list((client.app.state.settings.jobs_dir).iterdir())  # nothing left behind


@pytest.mark.parametrize(
    "url",
    [
        "/jobs?offset=254357068941219463168",
        "/jobs?limit=-1",
        "/jobs?limit=99999999999999999999999",
        "/jobs/%00",
        "/jobs?status=%00",
        "/jobs/abc/outputs/dtm%00.tif",
    ],
)
def test_hostile_urls_get_4xx(client: TestClient, url: str) -> None:
    r = client.get(url)
    assert 400 <= r.status_code < 500, r.text


def test_unwritable_data_directory_is_503(
    client: TestClient, tile: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    jobs = client.app.state.settings.jobs_dir
    if os.geteuid() == 0:  # root writes anywhere: refuse as a read-only disk would
        real_mkdir = Path.mkdir

        def mkdir(self: Path, *args, **kwargs) -> None:
            if self.is_relative_to(jobs):
                raise PermissionError(errno.EROFS, "Read-only file system", str(self))
            real_mkdir(self, *args, **kwargs)

        monkeypatch.setattr(Path, "mkdir", mkdir)
    jobs.chmod(0o500)
    try:
        r = client.post("/jobs", files=[("file", ("t.las", tile.read_bytes()))])
        body = _problem(r, 503)
        assert "cannot store data" in body["detail"]
        r = client.post("/processes/terrain/execution", json={"inputs": {"files": ["tile.las"]}})
        _problem(r, 503)
    finally:
        jobs.chmod(0o700)


def test_a_symlink_swapped_in_after_registration_is_refused(
    client: TestClient, tmp_path: Path, tile: Path
) -> None:
    r = client.post("/surveys", json={"files": ["tile.las"]})
    assert r.status_code == 201, r.text
    survey = r.json()["id"]
    outside = tmp_path / "outside.las"
    outside.write_bytes(tile.read_bytes())
    registered = client.app.state.settings.input_root / "tile.las"
    registered.unlink()
    registered.symlink_to(outside)
    body = _problem(client.post(f"/surveys/{survey}/runs"), 403)
    assert "outside the input root" in body["detail"]


def test_every_response_carries_the_apps_own_time(client: TestClient) -> None:
    for r in (client.get("/conformance"), client.get("/jobs/nope"), client.get("/jobs/%00")):
        timing = r.headers["server-timing"]
        assert timing.startswith("app;dur=") and 0 <= float(timing.split("=")[1]) < 10_000


@pytest.mark.parametrize("damage", ["file", "removed"])
def test_a_data_directory_broken_under_the_service_is_503_not_500(
    client: TestClient, tile: Path, damage: str
) -> None:
    """The job folder replaced by a file (as root, whom permissions do not stop) or
    removed under the running service: the storage is at fault, so 503 or the job is
    stored (the folder made again), never an internal error."""
    jobs = client.app.state.settings.jobs_dir
    aside = jobs.with_name("jobs.aside")
    jobs.rename(aside)
    if damage == "file":
        jobs.write_text("not a folder")
    try:
        r = client.post("/jobs", files=[("file", ("t.las", tile.read_bytes()))])
        if damage == "file":
            assert "Not a directory" in _problem(r, 503)["detail"]
        else:
            assert r.status_code in (201, 503), r.text
    finally:
        if jobs.is_file():
            jobs.unlink()
        elif jobs.is_dir():
            shutil.rmtree(jobs)
        aside.rename(jobs)


@pytest.mark.parametrize("name", ["a" * 300 + ".las", "d/" * 3000 + "tile.las", "loop/tile.las"])
def test_server_paths_the_file_system_cannot_take_are_400(client: TestClient, name: str) -> None:
    """A name longer than the file system takes (a 500 before), a path longer than PATH_MAX,
    a symlink loop: a 400 naming the path, for execute and for a survey."""
    root = client.app.state.settings.input_root
    if not (root / "loop").is_symlink():
        (root / "loop").symlink_to(root / "loop")
    r = client.post("/processes/terrain/execution", json={"inputs": {"files": [name]}})
    assert "cannot be used" in _problem(r, 400)["detail"]
    r = client.post("/surveys", json={"files": [name]})
    assert "cannot be used" in _problem(r, 400)["detail"]
