"""Surveys: register many tiles once (uploads or server paths), run them as one job."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from terrasift.service import ogc
from terrasift.service.auth import tenant
from terrasift.service.context import Service, base_url, service
from terrasift.service.problems import Problem
from terrasift.service.routes.jobs import created
from terrasift.service.schemas import (
    RunRequest,
    StatusInfo,
    SurveyInfo,
    SurveyRequest,
    multipart_body,
    problem_responses,
)
from terrasift.service.store import Survey
from terrasift.service.submit import (
    check_inputs,
    create_job,
    inside_root,
    new_id,
    parse_params,
    resolve_server_paths,
)

router = APIRouter(tags=["Surveys"])

# The same multipart form as POST /jobs, or JSON naming files under the input root.
_SURVEY_BODY = multipart_body(
    "one or more `file` fields (LAS/LAZ) and an optional `params` JSON object"
)
_SURVEY_BODY["content"]["application/json"] = {"schema": SurveyRequest.model_json_schema()}


@router.post(
    "/surveys",
    summary="Register a survey",
    status_code=201,
    response_model=SurveyInfo,
    responses=problem_responses(400, 401, 403, 413, 415, 422),
    openapi_extra={"requestBody": _SURVEY_BODY},
)
async def create_survey(request: Request, who: Annotated[str, Depends(tenant)]) -> JSONResponse:
    """Tiles as multipart `file` fields, or JSON `{"files": [paths under the input root], "params": {...}}`."""
    from terrasift.service.uploads import receive_multipart

    svc = service(request)
    survey_id = new_id()
    survey_dir = svc.settings.surveys_dir / survey_id
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    try:
        if ctype == "multipart/form-data":
            upload = await receive_multipart(
                request,
                survey_dir / "inputs",
                max_bytes=svc.settings.max_upload_bytes,
                max_files=svc.settings.max_files,
            )
            files, raw = upload.files, parse_params(upload.fields.get("params"))
        elif ctype == "application/json":
            try:
                body = SurveyRequest.model_validate_json(await request.body())
            except ValidationError as exc:
                raise RequestValidationError(exc.errors()) from None
            files = await run_in_threadpool(resolve_server_paths, svc.settings, body.files)
            raw = body.params
        else:
            raise Problem(
                "unsupported-media-type",
                "send JSON (server paths) or multipart/form-data (uploads)",
            )
        survey = await run_in_threadpool(_register, svc, who, survey_id, files, raw)
    except BaseException:
        await run_in_threadpool(shutil.rmtree, survey_dir, True)
        raise
    doc = _survey_doc(svc, survey, base_url(request))
    return JSONResponse(doc, status_code=201, headers={"Location": doc["links"][0]["href"]})


@router.get(
    "/surveys/{survey_id}",
    summary="A survey and its runs",
    response_model=SurveyInfo,
    responses=problem_responses(401, 404),
)
def get_survey(
    survey_id: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> dict[str, Any]:
    """The survey's files, parameters and the jobs it ran."""
    svc = service(request)
    return _survey_doc(svc, _survey(svc, survey_id, who), base_url(request))


@router.post(
    "/surveys/{survey_id}/runs",
    summary="Run a survey as one job",
    status_code=201,
    response_model=StatusInfo,
    response_model_exclude_none=True,
    responses=problem_responses(400, 401, 404, 422),
)
def run_survey(
    survey_id: str,
    request: Request,
    who: Annotated[str, Depends(tenant)],
    body: Annotated[RunRequest | None, Body()] = None,
) -> JSONResponse:
    """All the survey's tiles in one job; `params` here override the survey's."""
    svc = service(request)
    survey = _survey(svc, survey_id, who)
    params = {**survey.params, **(body.params if body else {})}
    files = [Path(f) for f in survey.files]
    uploads = svc.settings.surveys_dir / survey.id
    inside_root(svc.settings, [f for f in files if not f.is_relative_to(uploads)])
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise Problem(
            "invalid-input",
            f"tiles of this survey are gone from the server: {', '.join(missing[:10])}",
        )
    job = create_job(
        svc.settings, svc.store, svc.scheduler, who, new_id(), files, params, survey_id=survey.id
    )
    return created(request, job)


def _register(
    svc: Service, who: str, survey_id: str, files: list[Path], raw: dict[str, Any]
) -> Survey:
    check_inputs(svc.settings, files, raw, svc.scheduler.pipeline)
    # the client's own parameters are kept: each run validates them again merged with its own
    return svc.store.create_survey(survey_id, who, [str(f) for f in files], dict(raw))


def _survey(svc: Service, survey_id: str, who: str) -> Survey:
    survey = svc.store.get_survey(survey_id, tenant=who)
    if survey is None:
        raise Problem("no-such-survey", f"no survey {survey_id!r}")
    return survey


def _survey_doc(svc: Service, survey: Survey, base: str) -> dict[str, Any]:
    return {
        "id": survey.id,
        "created": survey.created,
        "files": [Path(f).name for f in survey.files],
        "params": survey.params,
        "jobs": [ogc.status_info(j, base) for j in svc.store.survey_jobs(survey.id)],
        "links": [
            ogc.link(f"{base}/surveys/{survey.id}", "self"),
            ogc.link(
                f"{base}/surveys/{survey.id}/runs", "runs", title="POST here to run the survey"
            ),
        ],
    }
