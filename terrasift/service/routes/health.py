"""Health: the job store is sound (repaired when not) and the workers are there."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from starlette.concurrency import run_in_threadpool

from terrasift.service.context import service
from terrasift.service.problems import PROBLEM_TYPES, problem_response
from terrasift.service.schemas import problem_responses

router = APIRouter(tags=["Capabilities"])


@router.get(
    "/health",
    summary="Service health",
    responses={
        200: {"description": "healthy"},
        **problem_responses(503),
    },
)
async def health(request: Request) -> Any:
    """`store`: ok, restored or rebuilt (what the check had to do); `workers`: live worker pids;
    `header_readers`: pids of the processes that read tile headers at submission."""
    svc = service(request)
    try:
        store = await run_in_threadpool(svc.store.check, True)
    except Exception as exc:  # noqa: BLE001 - reported, not raised
        return problem_response(
            request, PROBLEM_TYPES["service-unavailable"], f"the job store is unusable: {exc}"
        )
    pool = getattr(svc.scheduler.executor, "pool", None)
    return {
        "status": "ok",
        "store": store,
        "workers": pool.worker_pids() if pool is not None else None,
        "header_readers": svc.inspector.pids() if svc.inspector is not None else None,
    }
