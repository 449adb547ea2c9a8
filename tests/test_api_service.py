"""The service's own behaviour through the real app, with a small pipeline double.

Scheduling, cancelling, resuming, uploads, problems and output serving do not
depend on the science; `test_api_e2e.py` runs the real pipeline end to end.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient
from service_fakes import FakePipeline, las_bytes, thread_executor, wait_for

from terrasift.errors import InputError
from terrasift.service.app import create_app
from terrasift.service.settings import Settings
from terrasift.service.store import JobStore

PROBLEM = "application/problem+json"


@contextmanager
def client_for(tmp_path: Path, fake: FakePipeline, **settings: Any) -> Iterator[TestClient]:
    settings.setdefault("data_dir", tmp_path / "data")
    app = create_app(
        Settings(_env_file=None, **settings), pipeline=fake, executor_factory=thread_executor
    )
    with TestClient(app, raise_server_exceptions=False) as client:
        # tasks held at the gate give up when the service stops, like workers that go away
        fake.abort = lambda: app.state.svc.scheduler.stopping
        yield client


def upload(client: TestClient, *files: tuple[str, bytes], params: Any = None, **kw: Any):
    data = (
        {"params": params if isinstance(params, str) else json.dumps(params)}
        if params is not None
        else None
    )
    return client.post("/jobs", files=[("file", f) for f in files], data=data, **kw)


def poll(client: TestClient, job_id: str, *statuses: str, timeout: float = 10.0) -> dict:
    return wait_for(
        lambda: (s := client.get(f"/jobs/{job_id}").json())["status"] in statuses and s, timeout
    )


def assert_problem(resp, status: int, slug: str, mention: str | None = None) -> dict:
    assert resp.status_code == status, resp.text
    assert resp.headers["content-type"] == PROBLEM
    body = resp.json()
    assert body["type"].endswith(slug) and body["status"] == status
    assert body["title"] and body["detail"] and body["instance"] == resp.request.url.path
    if mention:
        assert mention in body["detail"]
    return body


def test_capabilities(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline()) as c:
        landing = c.get("/").json()
        rels = {link["rel"] for link in landing["links"]}
        assert {
            "self",
            "service-desc",
            "http://www.opengis.net/def/rel/ogc/1.0/conformance",
        } <= rels
        conf = c.get("/conformance").json()["conformsTo"]
        assert any(u.endswith("/conf/job-list") for u in conf) and any(
            u.endswith("/conf/dismiss") for u in conf
        )
        procs = c.get("/processes").json()["processes"]
        assert [p["id"] for p in procs] == ["terrain"]
        desc = c.get("/processes/terrain").json()
        assert (
            "files" in desc["inputs"]
            and "resolution" in desc["inputs"]
            and "ground.preset" in desc["inputs"]
        )
        assert desc["outputs"]["dtm.tif"]["schema"]["contentMediaType"].startswith("image/tiff")
        assert_problem(c.get("/processes/nope"), 404, "no-such-process")
        assert c.get(desc["links"][0]["href"]).status_code == 200


def test_upload_run_download(tmp_path: Path) -> None:
    fake = FakePipeline(tasks=4)
    with client_for(tmp_path, fake) as c:
        r = upload(c, ("a.las", las_bytes()), ("b.las", las_bytes()), params={"resolution": 1.0})
        assert r.status_code == 201, r.text
        info = r.json()
        job_id = info["jobID"]
        assert r.headers["location"].endswith(f"/jobs/{job_id}")
        assert (
            info["type"] == "process"
            and info["status"] in ("accepted", "running")
            and info["progress"] >= 0
        )
        assert {link["rel"] for link in info["links"]} == {
            "self",
            "http://www.opengis.net/def/rel/ogc/1.0/results",
        }
        # the job is persisted with its uploaded inputs before the answer
        job_dir = tmp_path / "data" / "jobs" / job_id
        assert sorted(p.name for p in (job_dir / "inputs").iterdir()) == ["a.las", "b.las"]
        assert json.loads((job_dir / "job.json").read_text())["params"] == {"resolution": 1.0}

        final = poll(c, job_id, "successful", "failed")
        assert final["status"] == "successful" and final["progress"] == 100
        allowed = {
            "processID",
            "type",
            "jobID",
            "status",
            "message",
            "created",
            "started",
            "finished",
            "updated",
            "progress",
            "links",
        }
        assert {"jobID", "status", "type"} <= set(final) <= allowed
        assert all(
            final[k].endswith("Z") and "T" in final[k]
            for k in ("created", "started", "finished", "updated")
        )
        assert isinstance(final["progress"], int) and None not in final.values()
        assert final["started"] <= final["finished"] and "message" in final
        results = c.get(f"/jobs/{job_id}/results").json()
        assert set(results) == {"dtm.tif", "report.json"}
        assert (
            results["dtm.tif"]["type"] == "image/tiff; application=geotiff; profile=cloud-optimized"
        )
        body = (job_dir / "outputs" / "dtm.tif").read_bytes()

        full = c.get(results["dtm.tif"]["href"])
        assert full.status_code == 200 and full.content == body
        assert (
            full.headers["content-length"] == str(len(body))
            and full.headers["accept-ranges"] == "bytes"
        )
        etag = full.headers["etag"]

        part = c.get(f"/jobs/{job_id}/outputs/dtm.tif", headers={"Range": "bytes=100-355"})
        assert part.status_code == 206 and part.content == body[100:356]
        assert (
            part.headers["content-range"] == f"bytes 100-355/{len(body)}"
            and part.headers["content-length"] == "256"
        )
        tail = c.get(f"/jobs/{job_id}/outputs/dtm.tif", headers={"Range": "bytes=-7"})
        assert tail.status_code == 206 and tail.content == body[-7:]

        head = c.head(f"/jobs/{job_id}/outputs/dtm.tif")
        assert (
            head.status_code == 200
            and head.content == b""
            and head.headers["content-length"] == str(len(body))
        )
        assert head.headers["etag"] == etag

        assert (
            c.get(f"/jobs/{job_id}/outputs/dtm.tif", headers={"If-None-Match": etag}).status_code
            == 304
        )
        stale = c.get(
            f"/jobs/{job_id}/outputs/dtm.tif", headers={"Range": "bytes=0-9", "If-Range": '"other"'}
        )
        assert stale.status_code == 200 and len(stale.content) == len(body)
        bad = c.get(f"/jobs/{job_id}/outputs/dtm.tif", headers={"Range": f"bytes={len(body)}-"})
        assert_problem(bad, 416, "range-not-satisfiable")
        assert bad.headers["content-range"] == f"bytes */{len(body)}"
        report = c.get(f"/jobs/{job_id}/outputs/report.json")
        assert report.headers["content-type"] == "application/json" and report.json() == {
            "tasks": 4
        }
        assert_problem(c.get(f"/jobs/{job_id}/outputs/..%2Fjob.json"), 404, "not-found")
        assert_problem(c.get(f"/jobs/{job_id}/outputs/job.json"), 404, "no-such-output")
        assert_problem(c.get(f"/jobs/{job_id}/outputs/chm.tif"), 404, "no-such-output")

        listing = c.get("/jobs").json()
        assert [j["jobID"] for j in listing["jobs"]] == [job_id]


def test_results_not_ready_then_dismiss_cancels_work(tmp_path: Path) -> None:
    fake = FakePipeline(tasks=6, free_tasks=1)  # task 0 runs, the rest wait on the gate
    with client_for(tmp_path, fake) as c:
        job_id = upload(c, ("a.las", las_bytes())).json()["jobID"]
        running = wait_for(lambda: (s := c.get(f"/jobs/{job_id}").json())["progress"] > 0 and s)
        assert running["status"] == "running" and 0 < running["progress"] < 100
        assert_problem(c.get(f"/jobs/{job_id}/results"), 404, "result-not-ready")
        assert_problem(c.get(f"/jobs/{job_id}/outputs/dtm.tif"), 404, "result-not-ready")

        t0 = time.monotonic()
        gone = c.delete(f"/jobs/{job_id}")
        assert gone.status_code == 200 and gone.json()["status"] == "dismissed"
        app = c.app
        assert wait_for(lambda: not app.state.svc.scheduler.is_active(job_id), 5)
        assert time.monotonic() - t0 < 5
        # the queued tasks were cancelled or stopped at the marker: only task 0 ever ran
        assert fake.ran == [(job_id, 0)]
        assert c.get(f"/jobs/{job_id}").json()["status"] == "dismissed"
        job_dir = tmp_path / "data" / "jobs" / job_id
        assert not (job_dir / "outputs").exists() and not (job_dir / "inputs").exists()
        assert_problem(c.get(f"/jobs/{job_id}/results"), 410, "job-dismissed")
        assert c.delete(f"/jobs/{job_id}").json()["status"] == "dismissed"  # idempotent


def test_dismissing_a_queued_job(tmp_path: Path) -> None:
    fake = FakePipeline(tasks=2, free_tasks=0)
    with client_for(tmp_path, fake, max_concurrent_jobs=1) as c:
        first = upload(c, ("a.las", las_bytes())).json()["jobID"]
        second = upload(c, ("b.las", las_bytes())).json()["jobID"]
        wait_for(lambda: c.get(f"/jobs/{first}").json()["status"] == "running")
        assert c.get(f"/jobs/{second}").json()["status"] == "accepted"  # waits for a slot
        assert c.delete(f"/jobs/{second}").json()["status"] == "dismissed"
        fake.gate.set()
        assert poll(c, first, "successful")["status"] == "successful"
        time.sleep(0.3)
        assert c.get(f"/jobs/{second}").json()["status"] == "dismissed"
        assert all(job == first for job, _ in fake.ran)
        assert not (tmp_path / "data" / "jobs" / second / "inputs").exists()


def test_restart_resumes_only_missing_tasks(tmp_path: Path) -> None:
    fake = FakePipeline(tasks=5, free_tasks=2)
    with client_for(tmp_path, fake) as c:
        job_id = upload(c, ("a.las", las_bytes())).json()["jobID"]
        wait_for(lambda: len(fake.ran) == 2)
        assert c.get(f"/jobs/{job_id}").json()["status"] == "running"
        # leaving the block stops the service with the job still running
    stored = JobStore(tmp_path / "data" / "jobs.sqlite")
    assert stored.get_job(job_id).status == "running"
    stored.close()
    fake2 = FakePipeline(tasks=5)
    with client_for(tmp_path, fake2) as c:
        final = poll(c, job_id, "successful", "failed")
        assert final["status"] == "successful"
        assert sorted(i for _, i in fake2.ran) == [2, 3, 4]  # 0 and 1 were not repeated


def test_api_answers_while_workers_are_busy(tmp_path: Path) -> None:
    fake = FakePipeline(tasks=3, free_tasks=0)
    with client_for(tmp_path, fake) as c:
        job_id = upload(c, ("a.las", las_bytes())).json()["jobID"]
        wait_for(lambda: c.get(f"/jobs/{job_id}").json()["status"] == "running")
        t0 = time.monotonic()
        for _ in range(10):
            assert c.get(f"/jobs/{job_id}").status_code == 200
        assert time.monotonic() - t0 < 2.0


def test_failed_jobs_say_why(tmp_path: Path) -> None:
    with client_for(
        tmp_path, FakePipeline(tasks=1, fail=InputError("tile a.las: 12 points missing at the end"))
    ) as c:
        job_id = upload(c, ("a.las", las_bytes())).json()["jobID"]
        final = poll(c, job_id, "successful", "failed")
        assert final["status"] == "failed" and "12 points missing" in final["message"]
        assert_problem(c.get(f"/jobs/{job_id}/results"), 422, "job-failed", "12 points missing")
    with client_for(tmp_path, FakePipeline(tasks=1, fail=RuntimeError("secret internals"))) as c:
        job_id = upload(c, ("a.las", las_bytes())).json()["jobID"]
        final = poll(c, job_id, "successful", "failed")
        assert (
            final["status"] == "failed"
            and "secret" not in final["message"]
            and "log" in final["message"]
        )


def test_bad_uploads_are_problems_and_leave_nothing(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline(), max_upload_bytes=10_000) as c:
        assert_problem(upload(c, ("a.txt", b"hello world")), 422, "invalid-input", "a.txt")
        assert_problem(
            upload(c, ("a.las", las_bytes()), params={"colour": "red"}),
            400,
            "invalid-parameter",
            "colour",
        )
        assert_problem(
            upload(c, ("a.las", las_bytes()), params={"resolution": -1}),
            400,
            "invalid-parameter",
            "resolution",
        )
        assert_problem(
            upload(c, ("a.las", las_bytes()), params="{not json"),
            400,
            "invalid-parameter",
            "not JSON",
        )
        assert_problem(
            upload(c, ("a.las", las_bytes()), params="[1, 2]"), 400, "invalid-parameter", "object"
        )
        assert_problem(upload(c, ("a.las", las_bytes(20_000))), 413, "payload-too-large")
        assert_problem(
            c.post("/jobs", data={"params": "{}"}, files=[]), 415, "unsupported-media-type"
        )
        assert_problem(
            c.post("/jobs", files=[("tile", ("a.las", las_bytes()))]),
            400,
            "invalid-request",
            "tile",
        )
        assert_problem(c.post("/jobs", json={"files": []}), 415, "unsupported-media-type")
        cut = (
            b'--xx\r\nContent-Disposition: form-data; name="file"; filename="a.las"\r\n\r\nLASF'
            + bytes(50)
        )
        r = c.post(
            "/jobs", content=cut, headers={"content-type": "multipart/form-data; boundary=xx"}
        )
        assert_problem(r, 400, "invalid-request", "closing boundary")
        assert c.get("/jobs").json()["jobs"] == []
        assert list((tmp_path / "data" / "jobs").iterdir()) == []


def test_streamed_upload_over_the_limit_without_content_length(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline(), max_upload_bytes=50_000) as c:
        boundary = "zz"
        head = f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="a.las"\r\n\r\nLASF'.encode()

        def body() -> Iterator[bytes]:  # chunked: no Content-Length to trust
            yield head
            for _ in range(20):
                yield bytes(10_000)
            yield f"\r\n--{boundary}--\r\n".encode()

        r = c.post(
            "/jobs",
            content=body(),
            headers={"content-type": f"multipart/form-data; boundary={boundary}"},
        )
        assert_problem(r, 413, "payload-too-large")
        assert list((tmp_path / "data" / "jobs").iterdir()) == []


def test_unknown_job_and_validation_problems(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline()) as c:
        assert_problem(c.get("/jobs/nope"), 404, "no-such-job")
        assert_problem(c.delete("/jobs/nope"), 404, "no-such-job")
        assert_problem(c.get("/jobs?limit=0"), 400, "invalid-request", "limit")
        assert_problem(c.get("/jobs?status=sleeping"), 400, "invalid-request", "sleeping")
        assert_problem(c.get("/no/such/path"), 404, "not-found")
        assert_problem(c.put("/jobs"), 405, "method-not-allowed")
        assert c.get("/problems/invalid-input").json()["status"] == 422


def test_unexpected_errors_still_answer_problem_json(tmp_path: Path) -> None:
    fake = FakePipeline()

    def broken(paths: list[Path], params: Any) -> dict:
        raise KeyError("boom")

    fake.inspect_inputs = broken
    with client_for(tmp_path, fake) as c:
        r = upload(c, ("a.las", las_bytes()))
        body = assert_problem(r, 500, "internal-error")
        assert "boom" not in body["detail"]


def test_execution_with_server_paths(tmp_path: Path) -> None:
    root = tmp_path / "incoming"
    (root / "survey").mkdir(parents=True)
    for name in ("t1.las", "t2.laz"):
        (root / "survey" / name).write_bytes(las_bytes())
    (root / "survey" / "notes.txt").write_text("ignored in a directory")
    (tmp_path / "secret.las").write_bytes(las_bytes())
    with client_for(tmp_path, FakePipeline(tasks=1), input_root=root) as c:
        r = c.post(
            "/processes/terrain/execution",
            json={"inputs": {"files": ["survey/t1.las"], "resolution": 2.0}},
            headers={"Prefer": "respond-async"},
        )
        assert r.status_code == 201, r.text
        assert r.headers["preference-applied"] == "respond-async"
        job_id = r.json()["jobID"]
        assert r.headers["location"].endswith(f"/jobs/{job_id}")
        job = json.loads((tmp_path / "data" / "jobs" / job_id / "job.json").read_text())
        assert (
            job["inputs"] == [str((root / "survey" / "t1.las").resolve())]
            and job["params"]["resolution"] == 2.0
        )
        assert poll(c, job_id, "successful")["status"] == "successful"

        r = c.post(
            "/processes/terrain/execution",
            json={"inputs": {"files": ["survey"], "params": {}}},
            headers={"Prefer": "respond-async"},
        )
        assert r.status_code == 201
        job = json.loads((tmp_path / "data" / "jobs" / r.json()["jobID"] / "job.json").read_text())
        assert [Path(p).name for p in job["inputs"]] == ["t1.las", "t2.laz"]

        def run(inputs: dict):
            return c.post("/processes/terrain/execution", json={"inputs": inputs})

        assert_problem(run({"files": ["../secret.las"]}), 403, "forbidden-path", "../secret.las")
        assert_problem(run({"files": [str(tmp_path / "secret.las")]}), 403, "forbidden-path")
        assert_problem(run({"files": ["survey/none.las"]}), 400, "invalid-request", "none.las")
        assert_problem(run({"files": ["survey/notes.txt"]}), 422, "invalid-input", "notes.txt")
        assert_problem(run({"params": {}}), 400, "invalid-request", "files")
        assert_problem(
            run({"files": ["survey/t1.las"], "params": {"resolution": 1}, "resolution": 2}),
            400,
            "invalid-parameter",
        )
        assert_problem(
            c.post("/processes/terrain/execution", json={"nothing": 1}),
            400,
            "invalid-request",
            "inputs",
        )
        assert_problem(
            c.post("/processes/other/execution", json={"inputs": {}}), 404, "no-such-process"
        )
    with client_for(tmp_path, FakePipeline()) as c:  # no input root configured
        r = c.post("/processes/terrain/execution", json={"inputs": {"files": ["survey/t1.las"]}})
        assert_problem(r, 403, "forbidden-path", "INPUT_ROOT")


def _real_las(tmp_path: Path, seed: int) -> bytes:
    """A tiny real LAS tile: survey runs plan from the tiles' headers."""
    from terrasift.synthetic.terrain import make_scene, write_las

    path = write_las(make_scene(20.0, 1.0, n_buildings=0, seed=seed), tmp_path / f"s{seed}.las")
    return path.read_bytes()


def test_surveys_from_uploads_and_paths(tmp_path: Path) -> None:
    root = tmp_path / "incoming"
    root.mkdir()
    (root / "t1.las").write_bytes(las_bytes())
    x, y = _real_las(tmp_path, 1), _real_las(tmp_path, 2)
    with client_for(tmp_path, FakePipeline(tasks=1), input_root=root) as c:
        r = c.post(
            "/surveys",
            files=[("file", ("x.las", x)), ("file", ("y.las", y))],
            data={"params": json.dumps({"resolution": 1.0})},
        )
        assert r.status_code == 201, r.text
        survey = r.json()
        assert survey["files"] == ["x.las", "y.las"] and r.headers["location"].endswith(
            f"/surveys/{survey['id']}"
        )
        run = c.post(f"/surveys/{survey['id']}/runs", json={"params": {"resolution": 4.0}})
        assert run.status_code == 201, run.text
        job_id = run.json()["jobID"]
        job = json.loads((tmp_path / "data" / "jobs" / job_id / "job.json").read_text())
        assert [Path(p).name for p in job["inputs"]] == ["x.las", "y.las"] and job["params"][
            "resolution"
        ] == 4.0
        assert poll(c, job_id, "successful")["status"] == "successful"
        again = c.post(f"/surveys/{survey['id']}/runs")
        assert again.status_code == 201
        # one run at a time: the next request waits for this one to end
        assert poll(c, again.json()["jobID"], "successful")["status"] == "successful"
        assert [j["jobID"] for j in c.get(f"/surveys/{survey['id']}").json()["jobs"]] == [
            job_id,
            again.json()["jobID"],
        ]

        r = c.post("/surveys", json={"files": ["t1.las"]})
        assert r.status_code == 201 and r.json()["files"] == ["t1.las"]
        assert_problem(c.post("/surveys", json={"files": ["../x"]}), 403, "forbidden-path")
        assert_problem(c.post("/surveys", json={"files": []}), 400, "invalid-request", "files")
        assert_problem(
            c.post("/surveys", files=[("file", ("bad.las", b"nope"))]),
            422,
            "invalid-input",
            "bad.las",
        )
        assert_problem(
            c.post("/surveys", content=b"x", headers={"content-type": "text/plain"}),
            415,
            "unsupported-media-type",
        )
        assert_problem(
            c.post(f"/surveys/{survey['id']}/runs", json={"params": {"resolution": 1e9}}),
            400,
            "invalid-parameter",
        )
        assert_problem(c.post("/surveys/nope/runs"), 404, "no-such-survey")


def test_tokens_map_to_tenants(tmp_path: Path) -> None:
    tokens = tmp_path / "tokens"
    tokens.write_text("tok-a alice\ntok-b bob\n")
    with client_for(tmp_path, FakePipeline(tasks=1), token_file=tokens) as c:
        assert c.get("/conformance").status_code == 200  # capabilities are public
        r = upload(c, ("a.las", las_bytes()))
        assert_problem(r, 401, "unauthorized")
        assert r.headers["www-authenticate"].startswith("Bearer")
        assert_problem(
            c.get("/jobs", headers={"Authorization": "Bearer wrong"}), 401, "unauthorized"
        )
        alice, bob = {"Authorization": "Bearer tok-a"}, {"Authorization": "Bearer tok-b"}
        job_id = upload(c, ("a.las", las_bytes()), headers=alice).json()["jobID"]
        assert [j["jobID"] for j in c.get("/jobs", headers=alice).json()["jobs"]] == [job_id]
        assert c.get("/jobs", headers=bob).json()["jobs"] == []
        assert_problem(c.get(f"/jobs/{job_id}", headers=bob), 404, "no-such-job")
        assert_problem(c.delete(f"/jobs/{job_id}", headers=bob), 404, "no-such-job")
        assert c.get(f"/jobs/{job_id}", headers=alice).status_code == 200


def test_non_loopback_bind_without_tokens_refuses_jobs(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline(), host="0.0.0.0") as c:
        assert_problem(c.get("/jobs"), 401, "unauthorized")


def test_job_list_paging(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline(tasks=1)) as c:
        ids = [upload(c, (f"{i}.las", las_bytes())).json()["jobID"] for i in range(3)]
        page = c.get("/jobs?limit=2").json()
        assert [j["jobID"] for j in page["jobs"]] == ids[::-1][:2]
        nxt = next(link["href"] for link in page["links"] if link["rel"] == "next")
        rest = c.get(nxt).json()
        assert [j["jobID"] for j in rest["jobs"]] == [ids[0]] and all(
            link["rel"] != "next" for link in rest["links"]
        )
        for job_id in ids:
            poll(c, job_id, "successful")
        assert len(c.get("/jobs?status=successful&status=failed").json()["jobs"]) == 3
        assert c.get("/jobs?status=running").json()["jobs"] == []
