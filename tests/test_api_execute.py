"""OGC execute as clients use it: uploads named by href, qualified values, output
selection, synchronous and asynchronous execution, subscriber callbacks, conformance."""

from __future__ import annotations

import base64
import json
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

from service_fakes import FakePipeline, las_bytes, wait_for
from test_api_service import assert_problem, client_for, poll

EXECUTE = "/processes/terrain/execution"
ASYNC = {"Prefer": "respond-async"}


def post_upload(c, *files: tuple[str, bytes]):
    return c.post("/uploads", files=[("file", f) for f in files])


def test_uploads_answer_hrefs_that_expire(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline(tasks=1), upload_lifetime=1.0) as c:
        r = post_upload(c, ("a.las", las_bytes()))
        assert r.status_code == 201, r.text
        one = r.json()
        assert set(one) == {"href", "expires"} and r.headers["location"] == one["href"]
        assert one["href"].endswith("/a.las") and "/uploads/" in one["href"]
        assert c.get(one["href"]).content == las_bytes()

        r = post_upload(c, ("b.las", las_bytes(10)), ("c.laz", las_bytes(20)))
        many = r.json()
        assert r.status_code == 201 and [Path(m["href"]).name for m in many] == ["b.las", "c.laz"]
        assert r.headers["location"] == many[0]["href"]

        assert_problem(c.post("/uploads", data={"x": "1"}), 415, "unsupported-media-type")
        time.sleep(1.1)
        assert_problem(c.get(one["href"]), 404, "not-found", "expired")
        r = c.post(EXECUTE, json={"inputs": {"files": [one]}}, headers=ASYNC)
        assert_problem(r, 404, "not-found", "expired")
        # expired uploads are removed when the next one arrives
        assert post_upload(c, ("d.las", las_bytes())).status_code == 201
        assert not (tmp_path / "data" / "uploads" / one["href"].split("/")[-2]).exists()


def test_execute_by_href_and_value_without_input_root(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline(tasks=2)) as c:
        href = post_upload(c, ("tile.las", las_bytes())).json()["href"]
        r = c.post(
            EXECUTE,
            json={"inputs": {"files": [{"href": href}], "resolution": {"value": 2.0}}},
            headers=ASYNC,
        )
        assert r.status_code == 201, r.text
        assert r.headers["preference-applied"] == "respond-async"
        job_id = r.json()["jobID"]
        job = json.loads((tmp_path / "data" / "jobs" / job_id / "job.json").read_text())
        assert job["params"]["resolution"] == 2.0
        assert Path(job["inputs"][0]).read_bytes() == las_bytes()  # the job's own copy
        assert Path(job["inputs"][0]).parent.name == "inputs"
        assert poll(c, job_id, "successful")["progress"] == 100
        assert set(c.get(f"/jobs/{job_id}/results").json()) == {"dtm.tif", "report.json"}

        value = {"value": base64.b64encode(las_bytes(64)).decode(), "encoding": "base64"}
        r = c.post(EXECUTE, json={"inputs": {"files": [value]}}, headers=ASYNC)
        assert r.status_code == 201, r.text
        assert_problem(
            c.post(EXECUTE, json={"inputs": {"files": [{"value": "%%%"}]}}, headers=ASYNC),
            400,
            "invalid-request",
            "base64",
        )
        bad = {"value": base64.b64encode(b"not a las file").decode()}
        assert_problem(
            c.post(EXECUTE, json={"inputs": {"files": [bad]}}, headers=ASYNC),
            422,
            "invalid-input",
        )
        r = c.post(EXECUTE, json={"inputs": {"files": [{"href": "https://example.org/t.laz"}]}})
        assert_problem(r, 400, "invalid-request", "/uploads")
        r = c.post(EXECUTE, json={"inputs": {"files": ["t.laz"]}})
        assert_problem(r, 403, "forbidden-path", "INPUT_ROOT")


def test_outputs_selection_and_sync_execution(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline(tasks=1)) as c:
        href = post_upload(c, ("tile.las", las_bytes())).json()["href"]
        files = [{"href": href}]
        # no Prefer: small inputs run synchronously and the answer is the results document
        r = c.post(EXECUTE, json={"inputs": {"files": files}, "outputs": {"dtm.tif": {}}})
        assert r.status_code == 200, r.text
        assert set(r.json()) == {"dtm.tif"}
        job_id = r.headers["location"].rsplit("/", 1)[1]
        job = json.loads((tmp_path / "data" / "jobs" / job_id / "job.json").read_text())
        assert job["outputs"] == ["dtm.tif"]
        assert_problem(c.get(f"/jobs/{job_id}/outputs/report.json"), 404, "no-such-output")

        r = c.post(
            EXECUTE,
            json={"inputs": {"files": files}, "outputs": {"report.json": {}}, "response": "raw"},
            headers={"Prefer": "respond-sync"},
        )
        assert r.status_code == 200 and r.headers["preference-applied"] == "respond-sync"
        assert r.json() == {"tasks": 1}  # the one output itself

        r = c.post(EXECUTE, json={"inputs": {"files": files}, "outputs": {"nope.tif": {}}})
        assert_problem(r, 400, "invalid-request", "nope.tif")
    # large inputs (by header point count) go asynchronous even without Prefer
    with client_for(tmp_path / "b", FakePipeline(tasks=1), sync_max_points=10) as c:
        href = post_upload(c, ("tile.las", las_bytes())).json()["href"]
        r = c.post(EXECUTE, json={"inputs": {"files": [{"href": href}]}})
        assert r.status_code == 201 and r.json()["status"] in ("accepted", "running", "successful")


@contextmanager
def receiver(fail_first: int = 0) -> Iterator[tuple[str, list[tuple[str, Any]]]]:
    """A loopback HTTP server recording POSTs; the first ``fail_first`` answer 503
    (and are recorded with the path prefixed by ``refused:``)."""
    got: list[tuple[str, Any]] = []
    failures = [fail_first]

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:  # noqa: N802 - http.server API
            body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
            if failures[0] > 0:
                failures[0] -= 1
                got.append(("refused:" + self.path, body))
                self.send_response(503)
            else:
                got.append((self.path, body))
                self.send_response(204)
            self.end_headers()

        def log_message(self, *args: Any) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", got
    finally:
        server.shutdown()
        server.server_close()


def test_subscriber_callbacks_with_retries(tmp_path: Path) -> None:
    fake = FakePipeline(tasks=3, free_tasks=1)
    with receiver(fail_first=1) as (url, got), client_for(tmp_path, fake) as c:
        href = post_upload(c, ("tile.las", las_bytes())).json()["href"]
        subscriber = {
            "successUri": f"{url}/ok",
            "inProgressUri": f"{url}/progress",
            "failedUri": f"{url}/failed",
        }
        r = c.post(
            EXECUTE,
            json={"inputs": {"files": [{"href": href}]}, "subscriber": subscriber},
            headers=ASYNC,
        )
        job_id = r.json()["jobID"]
        # the first POST (in progress) meets a 503 and is retried
        wait_for(lambda: any(p == "/progress" for p, _ in got), timeout=15)
        fake.gate.set()
        wait_for(lambda: any(p == "/ok" for p, _ in got), timeout=15)
        progress = [b for p, b in got if p == "/progress"]
        assert progress[0]["jobID"] == job_id and progress[0]["status"] == "running"
        assert got[0] == ("refused:/progress", progress[0])  # the same document, sent again
        results = next(b for p, b in got if p == "/ok")
        assert results["dtm.tif"]["href"].endswith(f"/jobs/{job_id}/outputs/dtm.tif")
        assert not any(p == "/failed" for p, _ in got)

        r = c.post(
            EXECUTE,
            json={"inputs": {"files": [{"href": href}]}, "subscriber": {"successUri": "ftp://x"}},
        )
        assert_problem(r, 400, "invalid-request", "subscriber.successUri")


def test_failed_job_calls_failed_uri(tmp_path: Path) -> None:
    from terrasift.errors import ProcessingError

    with (
        receiver() as (url, got),
        client_for(tmp_path, FakePipeline(tasks=1, fail=ProcessingError("bad block"))) as c,
    ):
        href = post_upload(c, ("tile.las", las_bytes())).json()["href"]
        r = c.post(
            EXECUTE,
            json={"inputs": {"files": [{"href": href}]}, "subscriber": {"failedUri": url}},
            headers=ASYNC,
        )
        assert r.status_code == 201
        wait_for(lambda: got, timeout=15)
        assert got[0][1]["status"] == "failed" and "bad block" in got[0][1]["message"]
        # synchronous execution of a failing job answers the failure
        r = c.post(EXECUTE, json={"inputs": {"files": [{"href": href}]}})
        assert_problem(r, 422, "job-failed", "bad block")


def test_conformance_matches_what_is_served(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline(tasks=1)) as c:
        classes = c.get("/conformance").json()["conformsTo"]
        assert not any(cls.endswith("/oas30") for cls in classes)
        assert c.get("/openapi.json").json()["openapi"].startswith("3.1")
        for name in ("core", "json", "job-list", "dismiss", "callback", "html"):
            assert any(cls.endswith(f"/conf/{name}") for cls in classes), name
        desc = c.get("/processes/terrain").json()
        assert {"sync-execute", "async-execute"} <= set(desc["jobControlOptions"])
        landing = c.get("/").json()
        (desc_link,) = [ln for ln in landing["links"] if ln["rel"] == "service-desc"]
        assert desc_link["type"].endswith("version=3.1")


def test_events_stream_status_until_final(tmp_path: Path) -> None:
    fake = FakePipeline(tasks=3, free_tasks=1)
    with client_for(tmp_path, fake) as c:
        href = post_upload(c, ("tile.las", las_bytes())).json()["href"]
        job_id = c.post(EXECUTE, json={"inputs": {"files": [href]}}, headers=ASYNC).json()["jobID"]
        events: list[dict] = []
        with c.stream("GET", f"/jobs/{job_id}/events") as r:
            assert r.headers["content-type"].startswith("text/event-stream")
            for line in r.iter_lines():
                if line.startswith("data: "):
                    events.append(json.loads(line[6:]))
                    if len(events) == 1:
                        fake.gate.set()
        statuses = [e["status"] for e in events]
        assert statuses[-1] == "successful" and len(events) >= 2
        progress = [e["progress"] for e in events]
        assert progress == sorted(progress) and progress[-1] == 100
        assert_problem(c.get("/jobs/nope/events"), 404, "no-such-job")
