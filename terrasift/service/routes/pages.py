"""HTML representations of the landing page, processes, job list and jobs.

These routes match only requests that want HTML (``f=html`` or a browser's
``Accept``); every other request falls through to the JSON routes of the same
paths. A browser's upload form posts to ``/jobs`` like curl does and is sent
on to the new job's page (303).
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from html import escape
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from fastapi.routing import APIRoute
from starlette.routing import Match
from starlette.types import Scope

from terrasift.errors import TerrasiftError
from terrasift.service import html, ogc
from terrasift.service.auth import tenant
from terrasift.service.context import base_url, service
from terrasift.service.outputs import media_type
from terrasift.service.problems import Problem, ProblemType, problem_for
from terrasift.service.routes import jobs as job_routes
from terrasift.service.routes import processes as process_routes
from terrasift.service.store import SUCCESSFUL


class HtmlRoute(APIRoute):
    """A route that matches only when the request wants HTML; its problems are pages too."""

    def matches(self, scope: Scope) -> tuple[Match, Scope]:
        if scope.get("type") == "http" and not html.wants_html(scope):
            return Match.NONE, {}
        return super().matches(scope)

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        inner = super().get_route_handler()

        async def handler(request: Request) -> Response:
            try:
                return await inner(request)
            except Problem as exc:
                return _error(request, exc.type, exc.detail, exc.headers)
            except TerrasiftError as exc:
                return _error(request, problem_for(exc), str(exc), None)

        return handler


def _error(
    request: Request, ptype: ProblemType, detail: str, headers: dict[str, str] | None
) -> HTMLResponse:
    """The problem as a page, with the same status and headers as its JSON."""
    page = _page(request, html.problem_page(ptype.status, ptype.title, detail))
    page.status_code = ptype.status
    page.headers.update(headers or {})
    return page


router = APIRouter(route_class=HtmlRoute, include_in_schema=False)


@router.get("/")
def landing(request: Request, who: Annotated[str, Depends(tenant)]) -> HTMLResponse:
    doc = ogc.landing(base_url(request))
    recent = service(request).store.list_jobs(who, limit=10)
    table = html.jobs_table([job_routes.status_doc(request, j) for j in recent])
    return _page(request, html.landing_page(doc, table))


def _page(request: Request, text: str) -> HTMLResponse:
    """The page with its links based on the service's base URL."""
    base = escape(base_url(request) + "/")
    return HTMLResponse(text.replace('<base href="/">', f'<base href="{base}">', 1))


@router.get("/conformance")
def conformance(request: Request) -> HTMLResponse:
    return _page(request, html.conformance_page(process_routes.conformance()))


@router.get("/processes")
def processes(request: Request) -> HTMLResponse:
    return _page(request, html.processes_page(process_routes.processes(request)))


@router.get("/processes/{process_id}")
def process(process_id: str, request: Request) -> HTMLResponse:
    return _page(
        request, html.process_page(process_routes.process_description(process_id, request))
    )


@router.get("/jobs")
def jobs(
    request: Request, who: Annotated[str, Depends(tenant)], limit: int = 50, offset: int = 0
) -> HTMLResponse:
    doc = job_routes.jobs_doc(request, who, min(max(limit, 1), 1000), max(offset, 0))
    return _page(request, html.jobs_page(doc))


@router.get("/jobs/{job_id}")
def job(job_id: str, request: Request, who: Annotated[str, Depends(tenant)]) -> HTMLResponse:
    svc = service(request)
    j = job_routes._job(request, job_id, who)
    outputs: list[tuple[str, int, str]] = []
    if j.status == SUCCESSFUL:
        for name in j.outputs:
            path = svc.scheduler.pipeline.output_path(svc.scheduler.job_dir(j.id), name)
            if path.exists():
                outputs.append((name, path.stat().st_size, media_type(name)))
    doc = job_routes.status_doc(request, j)
    return _page(request, html.job_page(doc, outputs, f"jobs/{j.id}/outputs"))


@router.get("/jobs/{job_id}/results")
def results(job_id: str, request: Request, who: Annotated[str, Depends(tenant)]) -> HTMLResponse:
    return _page(request, html.results_page(job_id, job_routes.results_doc(request, job_id, who)))


@router.post("/jobs")
async def upload_form(request: Request, who: Annotated[str, Depends(tenant)]) -> Response:
    """The upload form of the pages: the same as `POST /jobs`, then on to the job's page."""
    created = await job_routes.submit_upload(request, who)
    return RedirectResponse(created.headers["location"], status_code=303)
