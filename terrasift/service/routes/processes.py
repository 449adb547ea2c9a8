"""Landing page, conformance, the process list and description, and execution."""

from __future__ import annotations

import shutil
import time
from typing import Any

from fastapi import APIRouter, Body, Depends, Header, Request
from fastapi.responses import JSONResponse, Response

from terrasift.service import execute as execution
from terrasift.service import ogc
from terrasift.service.auth import tenant
from terrasift.service.context import base_url, service
from terrasift.service.outputs import file_response
from terrasift.service.problems import PROBLEM_TYPES, Problem
from terrasift.service.schemas import ExecuteRequest, StatusInfo, problem_responses
from terrasift.service.store import ACCEPTED, DISMISSED, FAILED, RUNNING
from terrasift.service.submit import create_job, new_id
from terrasift.service.upload_store import UploadStore

router = APIRouter()


@router.get("/", summary="Landing page", tags=["Capabilities"])
def landing(request: Request) -> dict[str, Any]:
    """Links to the API definition, conformance, processes and jobs."""
    return ogc.landing(base_url(request))


@router.get("/conformance", summary="Conformance classes", tags=["Capabilities"])
def conformance() -> dict[str, Any]:
    """The OGC API – Processes conformance classes this service implements."""
    return {"conformsTo": ogc.CONFORMANCE}


@router.get("/processes", summary="Processes", tags=["Processes"])
def processes(request: Request) -> dict[str, Any]:
    """The one process this service offers, `terrain`."""
    base = base_url(request)
    return {
        "processes": [ogc.process_summary(base)],
        "links": [ogc.link(f"{base}/processes", "self")],
    }


@router.get(
    "/processes/{process_id}",
    summary="Process description",
    tags=["Processes"],
    responses=problem_responses(404),
)
def process_description(process_id: str, request: Request) -> dict[str, Any]:
    """Inputs (files and every parameter, with its schema) and outputs of the process."""
    _check_process(process_id)
    return ogc.process_description(base_url(request), ogc.parameter_inputs())


@router.post(
    "/processes/{process_id}/execution",
    summary="Execute: uploads, values or server files",
    tags=["Processes"],
    status_code=201,
    response_model=StatusInfo,
    response_model_exclude_none=True,
    responses={
        200: {
            "description": "synchronous execution: the results document (or, with "
            "`response: raw` and one output selected, that output)",
            "content": {"application/json": {}},
        },
        **problem_responses(400, 401, 403, 404, 413, 422),
    },
)
def execute(
    process_id: str,
    request: Request,
    body: ExecuteRequest = Body(...),
    prefer: str | None = Header(
        None,
        description="`respond-async`: 201 + Location at once; `respond-sync` or none: "
        "wait and answer the results when the inputs are small",
    ),
    who: str = Depends(tenant),
) -> Response:
    """Start a job on uploaded, inline or server files; synchronous for small inputs unless
    `Prefer: respond-async`."""
    _check_process(process_id)
    svc = service(request)
    ex = execution.parse(body)
    job_id = new_id()
    job_dir = svc.scheduler.job_dir(job_id)
    uploads = UploadStore(svc.settings.uploads_dir, svc.settings.upload_lifetime)
    try:
        paths = execution.stage_files(svc.settings, uploads, who, ex.files, job_dir / "inputs")
        job = create_job(
            svc.settings,
            svc.store,
            svc.scheduler,
            who,
            job_id,
            paths,
            ex.params,
            outputs=ex.outputs,
        )
    except BaseException:
        shutil.rmtree(job_dir, ignore_errors=True)
        raise
    base = base_url(request)
    if ex.subscriber:
        request.app.state.notifier.subscribe(job.id, ex.subscriber, base)
    headers = {"Location": f"{base}/jobs/{job.id}"}
    points = 0
    if "respond-async" not in (prefer or "").lower():
        summary = svc.scheduler.pipeline.inspect_inputs(paths, job.params)
        points = int(summary.get("points", 0)) if isinstance(summary, dict) else 0
    if execution.mode(prefer, points, svc.settings) == execution.ASYNC:
        if prefer and "respond-async" in prefer.lower():
            headers["Preference-Applied"] = "respond-async"
        return JSONResponse(ogc.status_info(job, base), status_code=201, headers=headers)
    deadline = time.monotonic() + svc.settings.sync_timeout
    while job.status in (ACCEPTED, RUNNING) and time.monotonic() < deadline:
        time.sleep(0.1)
        job = svc.store.get_job(job.id) or job
    if job.status in (ACCEPTED, RUNNING):  # too slow after all: answer as an asynchronous job
        return JSONResponse(ogc.status_info(job, base), status_code=201, headers=headers)
    if job.status == FAILED:
        raise Problem("job-failed", job.message or "the job failed")
    if job.status == DISMISSED:
        raise Problem("job-dismissed", f"job {job.id} was dismissed")
    if prefer and "respond-sync" in prefer.lower():
        headers["Preference-Applied"] = "respond-sync"
    if body.response == "raw" and len(job.outputs) == 1:
        name = job.outputs[0]
        path = svc.scheduler.pipeline.output_path(job_dir, name)
        response = file_response(request, path, name)
        response.headers.update(headers)
        return response
    return JSONResponse(ogc.results(job, base), status_code=200, headers=headers)


@router.get(
    "/problems/{slug}",
    summary="Problem type",
    tags=["Capabilities"],
    responses=problem_responses(404),
)
def problem_type(slug: str) -> dict[str, Any]:
    """What a problem `type` of this service means."""
    ptype = PROBLEM_TYPES.get(slug)
    if ptype is None:
        raise Problem("not-found", f"no problem type {slug!r}")
    return {"type": ptype.uri, "title": ptype.title, "status": ptype.status}


def _check_process(process_id: str) -> None:
    if process_id != ogc.PROCESS_ID:
        raise Problem(
            "no-such-process", f"no process {process_id!r}; this service offers {ogc.PROCESS_ID!r}"
        )
