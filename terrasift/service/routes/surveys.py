"""Surveys: tiles registered once (uploads or server paths), changed one by one, run
incrementally into one current product per survey (``terrasift.jobs.survey``)."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import ValidationError
from pydantic_core import to_jsonable_python
from starlette.concurrency import run_in_threadpool

from terrasift.errors import InputError, NothingChanged, TerrasiftError
from terrasift.files import load_json
from terrasift.jobs import survey as surveys
from terrasift.jobs import validate_params
from terrasift.service import ogc
from terrasift.service.auth import tenant
from terrasift.service.context import Service, base_url, service
from terrasift.service.outputs import file_response, media_type
from terrasift.service.problems import Problem
from terrasift.service.routes.jobs import created
from terrasift.service.schemas import (
    OutputReference,
    RunRequest,
    StatusInfo,
    SurveyInfo,
    SurveyRequest,
    TileRequest,
    multipart_body,
    problem_responses,
)
from terrasift.service.store import ACTIVE, Job, Survey
from terrasift.service.submit import (
    check_inputs,
    inside_root,
    new_id,
    parse_params,
    resolve_server_paths,
)

log = logging.getLogger(__name__)
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
    summary="Run a survey (incremental by default)",
    status_code=201,
    response_model=StatusInfo,
    response_model_exclude_none=True,
    responses=problem_responses(400, 401, 404, 409, 422),
)
def run_survey(
    survey_id: str,
    request: Request,
    who: Annotated[str, Depends(tenant)],
    body: Annotated[RunRequest | None, Body()] = None,
) -> JSONResponse:
    """One job over the tiles whose content or parameters changed since the product was
    made and the neighbours their halo reaches (`{"mode": "full"}`: every tile), reading
    neighbour points for every halo; it updates the survey's product atomically.
    `params` here override the survey's. 409 when a run is in progress or nothing changed."""
    svc = service(request)
    survey = _survey(svc, survey_id, who)
    body = body or RunRequest()
    job = _submit_run(svc, survey, body.mode, {**survey.params, **body.params})
    return created(request, job)


def _submit_run(
    svc: Service, survey: Survey, mode: str, raw: dict[str, Any], after: str | None = None
) -> Job:
    """Plan a run of ``survey`` and queue its job. The service's ``max_points`` limits
    the points one run reads (its tiles and their halo), not the survey: a survey over
    it runs in batches, each queued when the one before it (``after``) has published."""
    _not_busy(svc, survey, after)
    files = _present_files(svc, survey)
    job_id = new_id()
    job_dir = svc.scheduler.job_dir(job_id)
    try:
        check_inputs(svc.settings, files, raw, svc.scheduler.pipeline, whole=False)
        params = validate_params(raw)  # the survey's planning needs every resolved field
        summary = surveys.plan_survey_run(
            job_dir,
            svc.settings.surveys_dir / survey.id,
            files,
            params,
            mode=mode,
            max_points=svc.settings.max_points,
            keep_intermediates=svc.settings.keep_intermediates,
        )
        inputs = [Path(p) for n, p in _by_name(files).items() if n in summary["sources"]]
        job = svc.store.create_job(
            job_id,
            survey.tenant,
            to_jsonable_python(params, fallback=str),
            [str(p) for p in inputs],
            survey_id=survey.id,
        )
    except BaseException:
        shutil.rmtree(job_dir, ignore_errors=True)
        raise
    svc.scheduler.wake()
    return job


def continue_batches(svc: Service, job_id: str) -> str | None:
    """When a survey run has published (before it is marked successful): queue the next
    batch if it left tiles pending, with the same parameters; returns the new job's id."""
    job = svc.store.get_job(job_id)
    if job is None or not job.survey_id:
        return None
    survey = svc.store.get_survey(job.survey_id)
    state = surveys.current_state(svc.settings.surveys_dir / job.survey_id)
    if survey is None or not state or not state.get("pending") or state.get("job") != job_id:
        return None  # done, or another run published since: that run carries the rest
    raw = load_json(svc.scheduler.job_dir(job_id) / "job.json")["params"]
    if surveys.params_key(validate_params(raw)) != state.get("params_key"):
        return None  # never loop on parameters that would not plan the same
    try:
        return _submit_run(svc, survey, "incremental", raw, after=job_id).id
    except (Problem, TerrasiftError, NothingChanged):
        log.warning("survey %s: the next batch was not queued", survey.id, exc_info=True)
        return None


@router.put(
    "/surveys/{survey_id}/tiles/{name}",
    summary="Add or replace a tile",
    response_model=SurveyInfo,
    responses={
        201: {"description": "the tile was added", "model": SurveyInfo},
        **problem_responses(400, 401, 403, 404, 409, 413, 415, 422),
    },
    openapi_extra={
        "requestBody": {
            "content": {
                "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
                "application/json": {"schema": TileRequest.model_json_schema()},
            }
        }
    },
)
async def put_tile(
    survey_id: str, name: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> JSONResponse:
    """The LAS/LAZ file as the raw body, or JSON `{"href": path under the input root}`
    (its file name must be `name`). The next incremental run redoes it and its neighbours."""
    svc = service(request)
    survey = _survey(svc, survey_id, who)
    _check_name(name)
    _not_busy(svc, survey)
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    inputs = svc.settings.surveys_dir / survey.id / "inputs"
    # received under its own name (in a folder of its own): messages about it name the tile
    incoming = inputs / f".incoming-{new_id()}"
    tmp = incoming / name
    try:
        if ctype == "application/json":
            try:
                ref = TileRequest.model_validate_json(await request.body())
            except ValidationError as exc:
                raise RequestValidationError(exc.errors()) from None
            (path,) = await run_in_threadpool(resolve_server_paths, svc.settings, [ref.href])
            if path.name != name:
                raise Problem("invalid-request", f"{ref.href!r} is not named {name!r}")
        elif ctype in ("application/octet-stream", "application/vnd.laszip", "application/vnd.las"):
            await _receive_body(request, tmp, svc.settings.max_upload_bytes)
            path = tmp
        else:
            raise Problem(
                "unsupported-media-type",
                "send the tile as application/octet-stream, or JSON naming a server path",
            )
        await run_in_threadpool(
            check_inputs, svc.settings, [path], survey.params, svc.scheduler.pipeline
        )
        if path == tmp:
            path = inputs / name
            os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            incoming.rmdir()
    files = [f for f in survey.files if Path(f).name != name]
    old = [f for f in survey.files if Path(f).name == name]
    for f in old:
        if Path(f).resolve() != path.resolve():
            _forget_upload(svc, survey, Path(f))
    updated = svc.store.set_survey_files(survey.id, [*files, str(path)])
    assert updated is not None
    return JSONResponse(
        _survey_doc(svc, updated, base_url(request)), status_code=200 if old else 201
    )


@router.delete(
    "/surveys/{survey_id}/tiles/{name}",
    summary="Remove a tile",
    response_model=SurveyInfo,
    responses=problem_responses(401, 404, 409),
)
def delete_tile(
    survey_id: str, name: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> dict[str, Any]:
    """The next incremental run drops it from the product and redoes the neighbours it reached."""
    svc = service(request)
    survey = _survey(svc, survey_id, who)
    _not_busy(svc, survey)
    old = [f for f in survey.files if Path(f).name == name]
    if not old:
        raise Problem("not-found", f"survey {survey_id} has no tile {name!r}")
    for f in old:
        _forget_upload(svc, survey, Path(f))
    updated = svc.store.set_survey_files(
        survey.id, [f for f in survey.files if Path(f).name != name]
    )
    assert updated is not None
    return _survey_doc(svc, updated, base_url(request))


@router.get(
    "/surveys/{survey_id}/results",
    summary="The survey's current product",
    response_model=dict[str, OutputReference],
    responses=problem_responses(401, 404),
)
def survey_results(
    survey_id: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> dict[str, Any]:
    """VRT mosaics over per-tile COGs, merged features, per-tile classified LAZ and STAC
    Items, and `collection.json`; each by reference. The product changes only when a
    run finishes, all at once."""
    svc = service(request)
    survey = _survey(svc, survey_id, who)
    version = _version(svc, survey)
    base = f"{base_url(request)}/surveys/{survey.id}/outputs"
    return {
        name: {"href": f"{base}/{name}", "type": media_type(name)}
        for name in surveys.product_files(version)
    }


_OUTPUT_DOC: dict[str, Any] = dict(
    response_class=Response,
    responses={
        200: {"description": "the file", "content": {"application/octet-stream": {}}},
        206: {"description": "one byte range of the file"},
        304: {"description": "not modified (If-None-Match)"},
        **problem_responses(401, 404, 416),
    },
)


@router.get(
    "/surveys/{survey_id}/outputs/{path:path}", summary="Download a product file", **_OUTPUT_DOC
)
def get_product_file(
    survey_id: str, path: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> Response:
    """A file of the current product, or one `Range` of it (VRTs and COGs read in place)."""
    return _product_file(request, survey_id, path, who)


@router.head(
    "/surveys/{survey_id}/outputs/{path:path}", summary="Product file size and ETag", **_OUTPUT_DOC
)
def head_product_file(
    survey_id: str, path: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> Response:
    """Headers of the GET, without the body."""
    return _product_file(request, survey_id, path, who)


_TILE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}\.(las|laz)", re.IGNORECASE)


def _check_name(name: str) -> None:
    if not _TILE_NAME.fullmatch(name):
        raise Problem(
            "invalid-request",
            f"tile name {name!r}: letters, digits, '.', '_' or '-', ending .las or .laz",
        )


def _by_name(files: list[Path]) -> dict[str, Path]:
    return {surveys.tile_name(f): f for f in files}


def _present_files(svc: Service, survey: Survey) -> list[Path]:
    files = [Path(f) for f in survey.files]
    uploads = svc.settings.surveys_dir / survey.id
    inside_root(svc.settings, [f for f in files if not f.is_relative_to(uploads)])
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise Problem(
            "invalid-input",
            f"tiles of this survey are gone from the server: {', '.join(missing[:10])}",
        )
    return files


def _not_busy(svc: Service, survey: Survey, finishing: str | None = None) -> None:
    """409 while a run of the survey (other than ``finishing``, which has published) is active."""
    active = [
        j.id for j in svc.store.survey_jobs(survey.id) if j.status in ACTIVE and j.id != finishing
    ]
    if active:
        raise Problem(
            "survey-busy",
            f"run {active[0]} of this survey is in progress; wait for it or dismiss it",
        )


def _forget_upload(svc: Service, survey: Survey, path: Path) -> None:
    """Remove an uploaded tile's file (server paths are the owner's, never removed)."""
    if path.resolve().is_relative_to((svc.settings.surveys_dir / survey.id).resolve()):
        path.unlink(missing_ok=True)


async def _receive_body(request: Request, dest: Path, max_bytes: int) -> None:
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > max_bytes:
        raise Problem(
            "payload-too-large", f"the request declares {declared} bytes; the limit is {max_bytes}"
        )
    dest.parent.mkdir(parents=True, exist_ok=True)
    size = 0
    with open(dest, "wb") as fh:
        async for chunk in request.stream():
            size += len(chunk)
            if size > max_bytes:
                raise Problem("payload-too-large", f"the tile exceeds {max_bytes} bytes")
            await run_in_threadpool(fh.write, chunk)
    if size == 0:
        raise Problem("invalid-request", "the request body is empty: send the LAS/LAZ file")


def _version(svc: Service, survey: Survey) -> Path:
    version = surveys.current_version(svc.settings.surveys_dir / survey.id)
    if version is None:
        raise Problem(
            "result-not-ready",
            f"survey {survey.id} has no product yet; POST /surveys/{survey.id}/runs",
        )
    return version


def _product_file(request: Request, survey_id: str, path: str, who: str) -> Response:
    svc = service(request)
    version = _version(svc, _survey(svc, survey_id, who))
    parts = Path(path).parts
    if (
        not parts
        or any(p in ("..", "") or p.startswith(".") for p in parts)
        or path == "state.json"
    ):
        raise Problem("no-such-output", f"the product has no file {path!r}")
    target = (version / path).resolve()
    if not target.is_relative_to(version) or not target.is_file():
        raise Problem("no-such-output", f"the product has no file {path!r}")
    return file_response(request, target, path)


def _register(
    svc: Service, who: str, survey_id: str, files: list[Path], raw: dict[str, Any]
) -> Survey:
    names = [surveys.tile_name(f) for f in files]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(f"tiles of a survey need distinct file names: {', '.join(twice[:10])}")
    check_inputs(svc.settings, files, raw, svc.scheduler.pipeline, whole=False)
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
        "product": _product_info(svc, survey),
        "jobs": [ogc.status_info(j, base) for j in svc.store.survey_jobs(survey.id)],
        "links": [
            ogc.link(f"{base}/surveys/{survey.id}", "self"),
            ogc.link(
                f"{base}/surveys/{survey.id}/runs", "runs", title="POST here to run the survey"
            ),
            ogc.link(f"{base}/surveys/{survey.id}/results", "results", title="the current product"),
        ],
    }


def _product_info(svc: Service, survey: Survey) -> dict[str, Any] | None:
    state = surveys.current_state(svc.settings.surveys_dir / survey.id)
    if state is None:
        return None
    return {
        "version": state["version"],
        "job": state["job"],
        "tiles": len(state["tiles"]),
        "pending": len(state.get("pending", [])),
    }
