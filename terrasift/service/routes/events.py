"""``GET /jobs/{id}/events``: the job's statusInfo pushed as server-sent events.

One ``status`` event whenever the job row changes (progress, message, status),
checked a few times a second; the stream ends after the final status. A
client that only polls ``/jobs/{id}`` sees the same documents.
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from typing import Annotated

import anyio
from fastapi import APIRouter, Depends, Request
from fastapi.responses import StreamingResponse

from terrasift.service.auth import tenant
from terrasift.service.context import service
from terrasift.service.problems import Problem
from terrasift.service.routes.jobs import status_doc
from terrasift.service.schemas import problem_responses
from terrasift.service.store import ACTIVE

router = APIRouter(tags=["Jobs"])

POLL_SECONDS = 0.25
KEEPALIVE_SECONDS = 15.0


@router.get(
    "/jobs/{job_id}/events",
    summary="Job status as server-sent events",
    response_class=StreamingResponse,
    responses={
        200: {
            "description": "`event: status` with the statusInfo as `data`, at each change, "
            "until the job is final",
            "content": {"text/event-stream": {}},
        },
        **problem_responses(401, 404),
    },
)
async def job_events(
    job_id: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> StreamingResponse:
    """`curl -N .../jobs/ID/events`: a `status` event at every change of the job."""
    store = service(request).store
    if store.get_job(job_id, tenant=who) is None:
        raise Problem("no-such-job", f"no job {job_id!r}")

    async def stream() -> AsyncIterator[str]:
        last = None
        quiet = 0.0
        while True:
            job = await anyio.to_thread.run_sync(store.get_job, job_id)
            if job is None:
                return
            state = (job.status, job.progress, job.message, job.updated)
            if state != last:
                last, quiet = state, 0.0
                doc = await anyio.to_thread.run_sync(status_doc, request, job)
                yield f"event: status\nid: {job.updated}\ndata: {json.dumps(doc)}\n\n"
                if job.status not in ACTIVE:
                    return
            elif quiet >= KEEPALIVE_SECONDS:
                quiet = 0.0
                yield ": keep-alive\n\n"
            if await request.is_disconnected():
                return
            await anyio.sleep(POLL_SECONDS)
            quiet += POLL_SECONDS

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
    )
