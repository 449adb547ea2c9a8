"""RFC 9457 problem responses: one table from exceptions to HTTP status and problem type.

Every error the API answers is ``application/problem+json`` with ``type``,
``title``, ``status``, ``detail`` and ``instance``. The three problems OGC API –
Processes names keep OGC's type URIs, so generic OGC clients recognise them;
terrasift's own types are relative URIs under ``/problems/`` that the app serves.
"""

from __future__ import annotations

import errno
import logging
import os
import sqlite3
from dataclasses import dataclass
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from terrasift import errors

log = logging.getLogger(__name__)

MEDIA_TYPE = "application/problem+json"
_OGC = "http://www.opengis.net/def/exceptions/ogcapi-processes-1/1.0/"


@dataclass(frozen=True)
class ProblemType:
    """A kind of problem: its slug, HTTP status and fixed title."""

    slug: str
    status: int
    title: str

    @property
    def uri(self) -> str:
        if self.slug in ("no-such-process", "no-such-job", "result-not-ready"):
            return _OGC + self.slug
        return f"/problems/{self.slug}"


PROBLEM_TYPES: dict[str, ProblemType] = {
    p.slug: p
    for p in [
        ProblemType("invalid-request", 400, "The request is malformed"),
        ProblemType("invalid-parameter", 400, "A job parameter is unknown or out of range"),
        ProblemType("invalid-filter", 400, "A feature filter does not parse"),
        ProblemType("invalid-input", 422, "An input file cannot be processed"),
        ProblemType(
            "too-many-points", 422, "The inputs hold more points than this service accepts"
        ),
        ProblemType("unauthorized", 401, "A valid bearer token is required"),
        ProblemType("forbidden-path", 403, "The path is outside the configured input root"),
        ProblemType("not-found", 404, "No such resource"),
        ProblemType("no-such-process", 404, "No such process"),
        ProblemType("no-such-job", 404, "No such job"),
        ProblemType("no-such-survey", 404, "No such survey"),
        ProblemType("no-such-output", 404, "No such output"),
        ProblemType("result-not-ready", 404, "The job has not finished"),
        ProblemType("method-not-allowed", 405, "Method not allowed"),
        ProblemType("survey-busy", 409, "A run of this survey is in progress"),
        ProblemType("survey-unchanged", 409, "Nothing changed since the survey's last run"),
        ProblemType("job-dismissed", 410, "The job was dismissed"),
        ProblemType("job-failed", 422, "The job failed"),
        ProblemType("payload-too-large", 413, "The upload exceeds the size limit"),
        ProblemType("unsupported-media-type", 415, "Unsupported media type"),
        ProblemType("range-not-satisfiable", 416, "The requested range is not satisfiable"),
        ProblemType("processing-failed", 422, "Processing failed"),
        ProblemType("internal-error", 500, "Internal server error"),
        ProblemType("service-unavailable", 503, "The service cannot take the request now"),
    ]
}

# Domain exceptions -> problem slug; the most specific class wins (walk the MRO).
EXCEPTION_PROBLEMS: dict[type[BaseException], str] = {
    errors.FilterSyntaxError: "invalid-filter",
    errors.ParameterError: "invalid-parameter",
    errors.InputError: "invalid-input",
    errors.ProcessingError: "processing-failed",
    errors.JobCancelled: "job-dismissed",
    errors.NothingChanged: "survey-unchanged",
    errors.Unavailable: "service-unavailable",
    errors.TerrasiftError: "invalid-request",
}

_STORAGE_ERRNOS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.EIO}


def _in_data_dir(request: Request, exc: Exception) -> bool:
    """An OSError on a path in the data directory (a folder replaced by a file or removed
    under the service, no file handles left): the storage, not the request, is at fault."""
    settings = getattr(request.app.state, "settings", None)
    names = [getattr(exc, "filename", None), getattr(exc, "filename2", None)]
    if settings is None or not any(isinstance(n, (str, bytes, os.PathLike)) for n in names):
        return False
    root = os.path.abspath(settings.data_dir)
    for name in names:
        if isinstance(name, (str, os.PathLike)):
            path = os.path.abspath(os.fspath(name))
            if path == root or path.startswith(root + os.sep):
                return True
    return False


_HTTP_STATUS_PROBLEMS = {
    404: "not-found",
    405: "method-not-allowed",
    413: "payload-too-large",
    415: "unsupported-media-type",
}


class Problem(Exception):
    """Raise from a route to answer with a problem of a registered type."""

    def __init__(
        self, slug: str, detail: str, *, headers: dict[str, str] | None = None, **extra: Any
    ):
        super().__init__(detail)
        self.type = PROBLEM_TYPES[slug]
        self.detail = detail
        self.headers = headers or {}
        self.extra = extra


def problem_for(exc: BaseException) -> ProblemType:
    """The problem type the table maps ``exc`` to (internal-error when none)."""
    for cls in type(exc).__mro__:
        if cls in EXCEPTION_PROBLEMS:
            return PROBLEM_TYPES[EXCEPTION_PROBLEMS[cls]]
    return PROBLEM_TYPES["internal-error"]


def problem_response(
    request: Request | None,
    ptype: ProblemType,
    detail: str,
    *,
    headers: dict[str, str] | None = None,
    **extra: Any,
) -> JSONResponse:
    """An ``application/problem+json`` response with the RFC 9457 members."""
    body: dict[str, Any] = {
        "type": ptype.uri,
        "title": ptype.title,
        "status": ptype.status,
        "detail": detail,
    }
    if request is not None:
        body["instance"] = request.url.path
    body.update(extra)
    return JSONResponse(body, status_code=ptype.status, headers=headers, media_type=MEDIA_TYPE)


def install(app: FastAPI) -> None:
    """Register the handlers that turn every error into problem+json."""

    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem) -> JSONResponse:
        return problem_response(request, exc.type, exc.detail, headers=exc.headers, **exc.extra)

    @app.exception_handler(errors.TerrasiftError)
    async def _domain(request: Request, exc: errors.TerrasiftError) -> JSONResponse:
        ptype = problem_for(exc)
        headers = {"Retry-After": "30"} if ptype.status == 503 else None
        return problem_response(request, ptype, str(exc), headers=headers)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        found = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", "")} for e in exc.errors()]
        detail = (
            "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in found)
            or "invalid request"
        )
        return problem_response(request, PROBLEM_TYPES["invalid-request"], detail, errors=found)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        slug = _HTTP_STATUS_PROBLEMS.get(exc.status_code)
        ptype = (
            PROBLEM_TYPES[slug]
            if slug
            else ProblemType("http-error", exc.status_code, "HTTP error")
        )
        return problem_response(
            request, ptype, str(exc.detail), headers=getattr(exc, "headers", None)
        )

    @app.exception_handler(OSError)
    @app.exception_handler(sqlite3.Error)
    async def _storage(request: Request, exc: Exception) -> JSONResponse:
        # the data directory or job store cannot be written: the service, not the request, is at fault
        if (
            isinstance(exc, sqlite3.Error)
            or getattr(exc, "errno", None) in _STORAGE_ERRNOS
            or _in_data_dir(request, exc)
        ):
            log.error("storage unavailable on %s %s: %s", request.method, request.url.path, exc)
            return problem_response(
                request,
                PROBLEM_TYPES["service-unavailable"],
                f"the service cannot store data now ({exc.strerror if isinstance(exc, OSError) else exc}); "
                "try again later",
                headers={"Retry-After": "60"},
            )
        return await _unexpected(request, exc)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return problem_response(
            request, PROBLEM_TYPES["internal-error"], "unexpected server error; it has been logged"
        )
