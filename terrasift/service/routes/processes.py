"""Landing page, conformance, the process list and description, and execution by server paths."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, Depends, Header, Request
from fastapi.responses import JSONResponse

from terrasift.errors import ParameterError
from terrasift.service import ogc
from terrasift.service.auth import tenant
from terrasift.service.context import base_url, service
from terrasift.service.problems import PROBLEM_TYPES, Problem
from terrasift.service.schemas import ExecuteRequest, StatusInfo, problem_responses
from terrasift.service.submit import create_job, new_id, resolve_server_paths

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
    summary="Execute on server files",
    tags=["Processes"],
    status_code=201,
    response_model=StatusInfo,
    response_model_exclude_none=True,
    responses=problem_responses(400, 401, 403, 404, 413, 422),
)
def execute(
    process_id: str,
    request: Request,
    body: ExecuteRequest = Body(...),
    prefer: str | None = Header(
        None, description="`respond-async`: the only mode; honoured and echoed"
    ),
    who: str = Depends(tenant),
) -> JSONResponse:
    """Start a job on LAS/LAZ files under the input root; always asynchronous (201 + Location)."""
    _check_process(process_id)
    svc = service(request)
    inputs = dict(body.inputs)
    files = inputs.pop("files", None)
    if files is None:
        raise Problem(
            "invalid-request",
            "inputs.files is required: paths of LAS/LAZ files under the input root",
        )
    if not isinstance(files, list):
        files = [files]
    params = inputs.pop("params", None) or {}
    if not isinstance(params, dict):
        raise ParameterError("inputs.params must be an object of parameters")
    clash = sorted(set(params) & set(inputs))
    if clash:
        raise ParameterError(f"parameter(s) given both in params and as inputs: {', '.join(clash)}")
    params = {**params, **inputs}
    paths = resolve_server_paths(svc.settings, files)
    job = create_job(svc.settings, svc.store, svc.scheduler, who, new_id(), paths, params)
    base = base_url(request)
    headers = {"Location": f"{base}/jobs/{job.id}"}
    if prefer and "respond-async" in prefer.lower():
        headers["Preference-Applied"] = "respond-async"
    return JSONResponse(ogc.status_info(job, base), status_code=201, headers=headers)


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
