"""Pitch and roll along a path over a finished job's DTM (NIST §5.1)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Depends, Query, Request
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from terrasift.service.auth import tenant
from terrasift.service.context import service
from terrasift.service.routes.jobs import _finished, _job
from terrasift.service.schemas import problem_responses

router = APIRouter(tags=["Jobs"])

_EXAMPLE = {"type": "LineString", "coordinates": [[8.501, 48.751], [8.503, 48.752]]}


@router.post(
    "/jobs/{job_id}/path",
    summary="Pitch and roll profile along a GeoJSON LineString",
    responses={
        200: {
            "content": {"application/json": {}, "text/csv": {}},
            "description": "distance, x, y, z, pitch and roll",
        },
        **problem_responses(400, 401, 404),
    },
)
async def path_profile(
    job_id: str,
    request: Request,
    who: Annotated[str, Depends(tenant)],
    line: Annotated[
        dict[str, Any],
        Body(
            description="GeoJSON LineString, a Feature holding one, or a FeatureCollection of "
            "them (several lines: samples carry a `line` index)",
            examples=[_EXAMPLE],
        ),
    ],
    crs: Annotated[
        str | None,
        Query(
            description="CRS of the line: omit for the GeoJSON's `crs` member or else WGS 84 "
            "lon/lat, `native` for the tile CRS, or e.g. EPSG:32632"
        ),
    ] = None,
    spacing: Annotated[
        float | None,
        Query(gt=0, le=10_000, description="metres between samples (default terrain.spacing)"),
    ] = None,
    f: Annotated[Literal["json", "csv"], Query(description="response format")] = "json",
) -> Response:
    """Samples every `spacing` m along the line: distance, x, y (in the tile CRS, named by `crs`), z, pitch and roll in degrees."""
    job = _finished(_job(request, job_id, who))
    svc = service(request)
    job_dir = svc.scheduler.job_dir(job.id)
    from terrasift.jobs import job_path_profile

    profile = await run_in_threadpool(job_path_profile, job_dir, line, crs=crs, spacing=spacing)
    if f == "csv":
        return Response(profile.to_csv(), media_type="text/csv")
    return JSONResponse(
        {
            "job": job.id,
            "crs": profile.crs,  # of the samples' x, y: the tile CRS
            "line_crs": crs
            or (line.get("crs") or {}).get("properties", {}).get("name")
            or "EPSG:4326",
            "samples": profile.to_records(),
        }
    )
