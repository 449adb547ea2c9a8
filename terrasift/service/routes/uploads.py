"""``POST /uploads``: files an execute request can then name by href."""

from __future__ import annotations

import datetime as dt
import shutil
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from terrasift.service.auth import tenant
from terrasift.service.context import base_url, service
from terrasift.service.outputs import file_response
from terrasift.service.problems import Problem
from terrasift.service.schemas import multipart_body, problem_responses
from terrasift.service.submit import new_id
from terrasift.service.upload_store import UploadStore
from terrasift.service.uploads import receive_multipart

router = APIRouter(tags=["Uploads"])


def upload_store(request: Request) -> UploadStore:
    settings = service(request).settings
    return UploadStore(settings.uploads_dir, settings.upload_lifetime)


@router.post(
    "/uploads",
    summary="Upload files to name in an execute request",
    status_code=201,
    responses={
        201: {
            "description": "`{href, expires}` for one file, a list of them for several; "
            "`Location` is the (first) href",
            "content": {"application/json": {}},
        },
        **problem_responses(400, 401, 413, 415),
    },
    openapi_extra={"requestBody": multipart_body("one or more `file` fields", params=False)},
)
async def post_uploads(request: Request, who: Annotated[str, Depends(tenant)]) -> JSONResponse:
    """`curl -F file=@tile.laz .../uploads` → 201 `{"href": ..., "expires": ...}`; the href
    goes into an execute request as `{"inputs": {"files": [{"href": ...}]}}`."""
    svc = service(request)
    store = upload_store(request)
    await run_in_threadpool(store.purge_expired)
    upload_id = new_id()
    dest = store.directory(upload_id)
    try:
        upload = await receive_multipart(
            request,
            dest,
            max_bytes=svc.settings.max_upload_bytes,
            max_files=svc.settings.max_files,
            text_fields=frozenset(),
        )
        if not upload.files:
            raise Problem("invalid-request", "no `file` field in the upload")
        stored = store.record(upload_id, upload.files, who)
    except BaseException:
        await run_in_threadpool(shutil.rmtree, dest, True)
        raise
    base = base_url(request)
    expires = dt.datetime.fromtimestamp(stored.expires, dt.UTC).isoformat().replace("+00:00", "Z")
    refs: list[dict[str, Any]] = [
        {"href": f"{base}/uploads/{upload_id}/{name}", "expires": expires} for name in stored.files
    ]
    body: Any = refs[0] if len(refs) == 1 else refs
    return JSONResponse(body, status_code=201, headers={"Location": refs[0]["href"]})


@router.get(
    "/uploads/{upload_id}/{name}",
    summary="An uploaded file, until its href expires",
    response_class=Response,
    responses={
        200: {"description": "the file", "content": {"application/octet-stream": {}}},
        **problem_responses(401, 404),
    },
)
def get_upload(
    upload_id: str, name: str, request: Request, who: Annotated[str, Depends(tenant)]
) -> Response:
    """The bytes that were uploaded (Range and ETag as for outputs)."""
    return file_response(request, upload_store(request).file(upload_id, name, who), name)
