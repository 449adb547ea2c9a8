"""HTML pages by content negotiation; queue position and stage in statusInfo."""

from __future__ import annotations

from pathlib import Path

from service_fakes import FakePipeline, las_bytes
from test_api_service import client_for, poll, upload

BROWSER = {"Accept": "text/html,application/xhtml+xml,application/xml;q=0.9,*/*;q=0.8"}


def test_negotiation_by_accept_and_f(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline(tasks=1)) as c:
        for path in ("/", "/conformance", "/processes", "/processes/terrain", "/jobs"):
            page = c.get(path, headers=BROWSER)
            assert page.headers["content-type"].startswith("text/html"), path
            assert page.text.startswith("<!doctype html>") and "<script src" not in page.text
            assert c.get(path).headers["content-type"] == "application/json", path
            assert c.get(path + "?f=json", headers=BROWSER).headers["content-type"] == (
                "application/json"
            )
            assert c.get(path + "?f=html").headers["content-type"].startswith("text/html")
        assert c.get("/", headers={"Accept": "application/json, text/html;q=0.5"}).json()
        desc = c.get("/processes/terrain?f=html").text
        assert "resolution" in desc and "dtm.tif" in desc and 'name="file"' in desc
        # a problem is a page for a browser, problem+json for everyone else
        r = c.get("/jobs/nope", headers=BROWSER)
        assert r.status_code == 404 and r.headers["content-type"].startswith("text/html")
        assert "No such job" in r.text and "nope" in r.text
        r = c.get("/jobs/nope")
        assert r.status_code == 404 and r.headers["content-type"] == "application/problem+json"
        r = c.post("/jobs", files=[("file", ("a.las", b"nonsense"))], headers=BROWSER)
        assert r.status_code == 422 and "not a LAS/LAZ file" in r.text
        assert r.headers["content-type"].startswith("text/html")


def test_form_upload_goes_to_the_job_page(tmp_path: Path) -> None:
    with client_for(tmp_path, FakePipeline(tasks=1)) as c:
        r = c.post(
            "/jobs",
            files=[("file", ("a.las", las_bytes()))],
            data={"params": ""},
            headers=BROWSER,
            follow_redirects=False,
        )
        assert r.status_code == 303
        job_id = r.headers["location"].rsplit("/", 1)[1]
        poll(c, job_id, "successful")
        page = c.get(f"/jobs/{job_id}", headers=BROWSER).text
        assert 'id="status">successful<' in page
        assert f'href="jobs/{job_id}/outputs/dtm.tif"' in page and "10.2 kB" in page
        assert '<base href="http://testserver/">' in page
        assert job_id[:12] in c.get("/jobs?f=html").text
        results = c.get(f"/jobs/{job_id}/results", headers=BROWSER).text
        assert f"/jobs/{job_id}/outputs/report.json" in results
    # behind a proxy that serves the API under a path prefix, links follow the public URL
    with client_for(tmp_path / "p", FakePipeline(tasks=1), public_url="https://x.example/ts") as c:
        page = c.get("/jobs", headers=BROWSER).text
        assert '<base href="https://x.example/ts/">' in page and 'action="jobs"' in page


def test_queue_position_and_stage(tmp_path: Path) -> None:
    fake = FakePipeline(tasks=2, free_tasks=0)
    with client_for(tmp_path, fake, max_concurrent_jobs=1) as c:
        first = upload(c, ("a.las", las_bytes())).json()["jobID"]
        poll(c, first, "running")
        second = upload(c, ("b.las", las_bytes())).json()["jobID"]
        third = upload(c, ("c.las", las_bytes())).json()["jobID"]
        assert "queuePosition" not in c.get(f"/jobs/{first}").json()
        assert c.get(f"/jobs/{second}").json()["queuePosition"] == 0
        assert c.get(f"/jobs/{third}").json()["queuePosition"] == 1
        assert "position 1 in the queue" in c.get(f"/jobs/{third}?f=html").text
        fake.gate.set()
        final = poll(c, third, "successful")
        assert "queuePosition" not in final and "stage" not in final


class _StagedPipeline(FakePipeline):
    """Reports a stage and a warning before its gated tasks, as the real pipeline does."""

    def run_job(self, job_dir: Path, executor: object, progress: object = None) -> list[str]:
        if callable(progress):
            info = {"stage": "blocks", "message": "block 0 of 2", "warnings": ["a.las: no CRS"]}
            progress(0, 2, info)
        return super().run_job(job_dir, executor, progress)


def test_stage_and_warnings_come_from_the_store(tmp_path: Path) -> None:
    fake = _StagedPipeline(tasks=2, free_tasks=0)
    with client_for(tmp_path, fake) as c:
        job_id = upload(c, ("a.las", las_bytes())).json()["jobID"]
        poll(c, job_id, "running")
        for _ in range(200):
            doc = c.get(f"/jobs/{job_id}").json()
            if doc.get("stage"):
                break
        assert doc["stage"] == "blocks" and doc["warnings"] == ["a.las: no CRS"]
        listed = c.get("/jobs").json()["jobs"][0]
        assert listed["stage"] == "blocks" and listed["warnings"] == ["a.las: no CRS"]
        # nothing but the store answers: the job directory holds no progress file
        assert not list(tmp_path.rglob("progress.json"))
        fake.gate.set()
        final = poll(c, job_id, "successful")
        assert "stage" not in final and final["warnings"] == ["a.las: no CRS"]
