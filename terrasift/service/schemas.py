"""Request and response models; responses are documented with them in the OpenAPI spec."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


class Link(BaseModel):
    href: str
    rel: str
    type: str | None = None
    title: str | None = None


class StatusInfo(BaseModel):
    """OGC API – Processes Part 1 statusInfo."""

    processID: str | None = None
    type: Literal["process"] = "process"
    jobID: str
    status: Literal["accepted", "running", "successful", "failed", "dismissed"]
    message: str | None = None
    created: str | None = None
    started: str | None = None
    finished: str | None = None
    updated: str | None = None
    progress: int | None = Field(None, ge=0, le=100)
    stage: str | None = Field(None, description="what the job does now (terrasift extension)")
    queuePosition: int | None = Field(
        None, description="jobs ahead of this accepted one (terrasift extension)"
    )
    warnings: list[str] | None = Field(
        None, description="what degraded but did not stop the job (terrasift extension)"
    )
    links: list[Link] = []


class JobList(BaseModel):
    jobs: list[StatusInfo]
    links: list[Link]


class ProblemDetails(BaseModel):
    """RFC 9457 problem details."""

    model_config = ConfigDict(extra="allow")

    type: str
    title: str
    status: int
    detail: str
    instance: str | None = None


class OutputReference(BaseModel):
    href: str
    type: str


FileRef = str | dict[str, str]


class Subscriber(BaseModel):
    """URLs the service POSTs to: results on success, statusInfo while running and on failure."""

    successUri: str | None = None
    inProgressUri: str | None = None
    failedUri: str | None = None


class ExecuteRequest(BaseModel):
    """OGC execute request: `files` and `params` (or parameters as inputs of their own)."""

    model_config = ConfigDict(extra="allow")

    inputs: dict[str, Any] = Field(
        description="`files`: hrefs from POST /uploads, `{value, encoding: base64}` qualified "
        "values, or paths under the input root; `params`: object of parameters; any other key "
        "is a parameter (plain or as `{value: ...}`)",
        examples=[
            {
                "files": [{"href": "http://127.0.0.1:8000/uploads/4f1c.../tile_01.laz"}],
                "params": {"ground": "nist", "resolution": 0.5},
            }
        ],
    )
    outputs: dict[str, Any] | None = Field(
        None,
        description="outputs to compute and list (ids from the process description); all when absent",
    )
    response: Literal["document", "raw"] | None = None
    subscriber: Subscriber | None = None


class SurveyRequest(BaseModel):
    """A survey from server paths (JSON); uploads use multipart with `file` and `params` fields instead."""

    model_config = ConfigDict(extra="forbid")

    files: list[FileRef] = Field(
        min_length=1, description="paths under the input root; a directory means its LAS/LAZ files"
    )
    params: dict[str, Any] = Field(
        default_factory=dict, description="parameters every run starts from"
    )


class RunRequest(BaseModel):
    """One survey run: incremental (default) or full; ``params`` on top of the survey's own."""

    model_config = ConfigDict(extra="forbid")

    mode: Literal["incremental", "full"] = Field(
        "incremental",
        description="incremental: the tiles whose content or parameters changed and the "
        "neighbours their halo reaches; full: every tile",
    )
    params: dict[str, Any] = Field(default_factory=dict)


class TileRequest(BaseModel):
    """A tile from a server path (JSON); a raw LAS/LAZ body uploads it instead."""

    model_config = ConfigDict(extra="forbid")

    href: str = Field(description="path under the input root")


class SurveyInfo(BaseModel):
    id: str
    created: str
    files: list[str]
    params: dict[str, Any]
    product: dict[str, Any] | None = Field(
        None,
        description="the current product: its version, the run that made it, its tiles and "
        "`pending`, the tiles later batches of a run still redo (a run reads at most "
        "the service's max_points; the next batch is queued when one publishes)",
    )
    jobs: list[StatusInfo]
    links: list[Link]


PROBLEM_REF = "#/components/schemas/ProblemDetails"


def problem_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries for problem+json answers (the schema is added by ``add_problem_schema``)."""
    content = {"application/problem+json": {"schema": {"$ref": PROBLEM_REF}}}
    return {code: {"description": "problem (RFC 9457)", "content": content} for code in codes}


def add_problem_schema(spec: dict[str, Any]) -> dict[str, Any]:
    """Put ProblemDetails into the spec's components, where `problem_responses` points."""
    schemas = spec.setdefault("components", {}).setdefault("schemas", {})
    schemas["ProblemDetails"] = ProblemDetails.model_json_schema(
        ref_template="#/components/schemas/{model}"
    )
    # FastAPI documents request validation as 422 HTTPValidationError; this API answers 400 problem+json
    for operations in spec.get("paths", {}).values():
        for op in operations.values():
            responses = op.get("responses", {})
            auto = (
                responses.get("422", {})
                .get("content", {})
                .get("application/json", {})
                .get("schema", {})
            )
            if auto.get("$ref", "").endswith("/HTTPValidationError"):
                del responses["422"]
                responses.setdefault("400", problem_responses(400)[400])
    schemas.pop("HTTPValidationError", None)
    schemas.pop("ValidationError", None)
    return spec


def multipart_body(description: str, params: bool = True) -> dict[str, Any]:
    """OpenAPI request body of the multipart upload endpoints (parsed by hand, streamed to disk)."""
    body: dict[str, Any] = {
        "required": True,
        "description": description,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file"],
                    "properties": {
                        "file": {"type": "array", "items": {"type": "string", "format": "binary"}},
                        "params": {"type": "string", "description": "JSON object of parameters"},
                    },
                },
                "encoding": {
                    "file": {"contentType": "application/octet-stream"},
                    "params": {"contentType": "application/json"},
                },
            }
        },
    }
    if not params:
        form = body["content"]["multipart/form-data"]
        del form["schema"]["properties"]["params"], form["encoding"]["params"]
    return body
