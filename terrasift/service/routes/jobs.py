"""Jobs: multipart submission, list, status, results, dismiss, and output files."""

from __future__ import annotations

import shutil
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from terrasift.service import jobinfo, ogc
from terrasift.service.auth import tenant
from terrasift.service.context import base_url, service
from terrasift.service.outputs import file_response
from terrasift.service.problems import Problem
from terrasift.service.schemas import (
    JobList,
    OutputReference,
    StatusInfo,
    multipart_body,
    problem_responses,
)
from terrasift.service.store import ACCEPTED, DISMISSED, FAILED, RUNNING, STATUSES, Job
from terrasift.service.submit import create_job, new_id, parse_params

router = APIRouter(tags=["Jobs"])


@router.post(
    "/jobs",
    summary="Upload tiles and start a job",
    status_code=201,
    response_model=StatusInfo,
    response_model_exclude_none=True,
    responses=problem_responses(400, 401, 413, 415, 422),
    openapi_extra={
        "requestBody": multipart_body(
            "one or more `file` fields (LAS/LAZ) and an optional `params` JSON object"
        )
    },
)
async def submit_upload(request: Request, who: Annotated[str, Depends(tenant)]) -> JSONResponse:
    """`curl -F file=@tile.laz -F 'params={"resolution": 0.5}' .../jobs` → 201 statusInfo + Location."""
    from terrasift.service.uploads import receive_multipart

    svc = service(request)
    job_id = new_id()
    job_dir = svc.scheduler.job_dir(job_id)
    try:
        upload = await receive_multipart(
            request,
            job_dir / "inputs",
            max_bytes=svc.settings.max_upload_bytes,
            max_files=svc.settings.max_files,
        )
        raw = parse_params(upload.fields.get("params"))
        job = await run_in_threadpool(
            create_job, svc.settings, svc.store, svc.scheduler, who, job_id, upload.files, raw
        )
    except BaseException:
        await run_in_threadpool(shutil.rmtree, job_dir, True)
        raise
    return created(request, job)


@router.get(
    "/jobs",
    summary="Jobs of this tenant",
    response_model=JobList,
    response_model_exclude_none=True,
    responses=problem_responses(400, 401),
)
async def list_jobs(
    request: Request,
    who: Annotated[str, Depends(tenant)],
    limit: Annotated[int, Query(ge=1, le=1000)] = 10,
    offset: Annotated[int, Query(ge=0, le=2**31)] = 0,
    status: Annotated[list[str] | None, Query(description="filter by status (repeatable)")] = None,
    processID: Annotated[
        list[str] | None, Query(description="filter by process (repeatable)")
    ] = None,  # noqa: N803 - OGC name
) -> dict[str, Any]:
    """Newest first; `next` link while more remain."""
    return jobs_doc(request, who, limit, offset, status, processID)


def jobs_doc(
    request: Request,
    who: str,
    limit: int = 10,
    offset: int = 0,
    status: list[str] | None = None,
    processID: list[str] | None = None,  # noqa: N803 - OGC name
) -> dict[str, Any]:
    """The job list document (also rendered by the HTML page)."""
    bad = sorted(set(status or []) - set(STATUSES))
    if bad:
        raise Problem(
            "invalid-request", f"unknown status {', '.join(bad)} (known: {', '.join(STATUSES)})"
        )
    svc = service(request)
    process = processID[0] if processID and len(processID) == 1 else None
    jobs = svc.store.list_jobs(
        who, statuses=status, process_id=process, limit=limit + 1, offset=offset
    )
    if processID and len(processID) > 1:
        jobs = [j for j in jobs if j.process_id in processID]
    links = [ogc.link(str(request.url), "self")]
    if len(jobs) > limit:
        links.append(
            ogc.link(
                str(request.url.include_query_params(offset=offset + limit, limit=limit)), "next"
            )
        )
    return {"jobs": [status_doc(request, j) for j in jobs[:limit]], "links": links}


@router.get(
    "/jobs/{job_id}",
    summary="Job status",
    response_model=StatusInfo,
    response_model_exclude_none=True,
    responses=problem_responses(401, 404),
)
async def job_status(
    job_id: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> JSONResponse:
    """statusInfo: integer progress of the work done (points × measured stage cost), the
    current stage and counts in `message`, plus `stage`, `warnings` and `queuePosition`."""
    return JSONResponse(status_doc(request, _job(request, job_id, who)))


@router.delete(
    "/jobs/{job_id}",
    summary="Dismiss a job",
    response_model=StatusInfo,
    response_model_exclude_none=True,
    responses=problem_responses(401, 404),
)
def dismiss(job_id: str, request: Request, who: Annotated[str, Depends(tenant)]) -> JSONResponse:
    """Cancel queued and running tasks, mark the job dismissed and delete its outputs."""
    svc = service(request)
    _job(request, job_id, who)
    job = svc.store.dismiss(job_id)
    if job is None:  # deleted since the check above
        raise Problem("no-such-job", f"no job {job_id!r}")
    svc.scheduler.cancel(job_id)
    return JSONResponse(ogc.status_info(job, base_url(request)))


@router.get(
    "/jobs/{job_id}/results",
    summary="Job results",
    response_model=dict[str, OutputReference],
    responses=problem_responses(401, 404, 410, 422),
)
async def job_results(
    job_id: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> dict[str, Any]:
    """Each output by reference (href and media type) once the job is successful."""
    return results_doc(request, job_id, who)


def results_doc(request: Request, job_id: str, who: str) -> dict[str, Any]:
    """The results document (also rendered by the HTML page)."""
    job = _finished(_job(request, job_id, who))
    return ogc.results(job, base_url(request))


_OUTPUT_DOC: dict[str, Any] = dict(
    response_class=Response,
    responses={
        200: {"description": "the file", "content": {"application/octet-stream": {}}},
        206: {"description": "one byte range of the file"},
        304: {"description": "not modified (If-None-Match)"},
        **problem_responses(401, 404, 410, 416, 422),
    },
)


@router.get("/jobs/{job_id}/outputs/{name}", summary="Download an output", **_OUTPUT_DOC)
def get_output(
    job_id: str, name: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> Response:
    """The file, or one `Range` of it (206); `ETag`/`If-None-Match` for revalidation."""
    return _output(request, job_id, name, who)


@router.head("/jobs/{job_id}/outputs/{name}", summary="Output size and ETag", **_OUTPUT_DOC)
def head_output(
    job_id: str, name: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> Response:
    """Headers of the GET, without the body."""
    return _output(request, job_id, name, who)


def status_doc(request: Request, job: Job) -> dict[str, Any]:
    """The statusInfo of ``job`` with terrasift's extra members."""
    svc = service(request)
    extra = jobinfo.extras(svc.store, job)
    return ogc.status_info(job, base_url(request), extra)


def created(request: Request, job: Job) -> JSONResponse:
    """201 with the statusInfo and `Location` of a new job."""
    base = base_url(request)
    return JSONResponse(
        status_doc(request, job), status_code=201, headers={"Location": f"{base}/jobs/{job.id}"}
    )


def _job(request: Request, job_id: str, who: str) -> Job:
    job = service(request).store.get_job(job_id, tenant=who)
    if job is None:
        raise Problem("no-such-job", f"no job {job_id!r}")
    return job


def _finished(job: Job) -> Job:
    if job.status in (ACCEPTED, RUNNING):
        raise Problem(
            "result-not-ready",
            f"job {job.id} is {job.status} ({job.progress} %); poll /jobs/{job.id}",
        )
    if job.status == FAILED:
        raise Problem("job-failed", job.message or "the job failed")
    if job.status == DISMISSED:
        raise Problem("job-dismissed", f"job {job.id} was dismissed; its outputs are gone")
    return job


def _output(request: Request, job_id: str, name: str, who: str) -> Response:
    job = _finished(_job(request, job_id, who))
    if name not in job.outputs:
        raise Problem(
            "no-such-output",
            f"job {job_id} has no output {name!r} (it has: {', '.join(job.outputs)})",
        )
    svc = service(request)
    return file_response(
        request, svc.scheduler.pipeline.output_path(svc.scheduler.job_dir(job_id), name), name
    )
