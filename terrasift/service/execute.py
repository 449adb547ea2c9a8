"""An OGC execute request taken apart: input files, parameters, output selection, mode.

Files come as hrefs from ``POST /uploads``, as qualified values (base64 bytes)
or as paths under the configured input root; parameters as plain or qualified
values (``{"value": ...}``). Uploads and values are put into the job's own
input directory, so the job never depends on an upload that may expire.
"""

from __future__ import annotations

import base64
import binascii
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from terrasift.errors import ParameterError
from terrasift.service import ogc
from terrasift.service.problems import Problem
from terrasift.service.schemas import ExecuteRequest
from terrasift.service.settings import Settings
from terrasift.service.submit import resolve_server_paths
from terrasift.service.upload_store import UploadStore, link_or_copy

ASYNC, SYNC = "async", "sync"


@dataclass
class Execution:
    """What an execute request asks for, after validation of its shape."""

    files: list[Any]
    params: dict[str, Any]
    outputs: list[str] | None
    subscriber: dict[str, str]


def unwrap(value: Any) -> Any:
    """A qualified value ``{"value": v, ...}`` as ``v``; anything else as it is."""
    if isinstance(value, Mapping) and "value" in value and "href" not in value:
        return value["value"]
    return value


def parse(body: ExecuteRequest) -> Execution:
    """Split the request into files, parameters, selected outputs and callbacks."""
    inputs = dict(body.inputs)
    files = inputs.pop("files", None)
    if files is None:
        raise Problem(
            "invalid-request",
            "inputs.files is required: hrefs from POST /uploads, {value, encoding: base64} "
            "or paths under the input root",
        )
    if not isinstance(files, list):
        files = [files]
    params = unwrap(inputs.pop("params", None)) or {}
    if not isinstance(params, dict):
        raise ParameterError("inputs.params must be an object of parameters")
    inputs = {k: unwrap(v) for k, v in inputs.items()}
    clash = sorted(set(params) & set(inputs))
    if clash:
        raise ParameterError(f"parameter(s) given both in params and as inputs: {', '.join(clash)}")
    outputs = None
    if body.outputs is not None:
        outputs = list(body.outputs)
        unknown = sorted(set(outputs) - set(ogc.OUTPUTS))
        if unknown or not outputs:
            raise Problem(
                "invalid-request",
                f"unknown output(s) {', '.join(unknown) or '(none selected)'}; "
                f"outputs of {ogc.PROCESS_ID}: {', '.join(ogc.OUTPUTS)}",
            )
    subscriber = {}
    if body.subscriber is not None:
        subscriber = {k: v for k, v in body.subscriber.model_dump().items() if v}
        for key, url in subscriber.items():
            if urlsplit(url).scheme not in ("http", "https") or not urlsplit(url).netloc:
                raise Problem("invalid-request", f"subscriber.{key} must be an http(s) URL")
    return Execution(files, {**params, **inputs}, outputs, subscriber)


def stage_files(
    settings: Settings, uploads: UploadStore, tenant: str, items: list[Any], dest: Path
) -> list[Path]:
    """The job's input files in request order: uploads and values placed in ``dest``, server paths as they are."""
    if not items:
        raise Problem("invalid-request", "`files` must name at least one file")
    out: list[Path] = []
    value_bytes = 0
    for i, item in enumerate(items):
        if isinstance(item, Mapping) and "value" in item:
            data = _decode(item, i)
            value_bytes += len(data)
            if value_bytes > settings.max_upload_bytes:
                raise Problem(
                    "payload-too-large",
                    f"inline values exceed {settings.max_upload_bytes} bytes; POST to /uploads",
                )
            suffix = ".las" if "vnd.las" in str(item.get("mediaType", "")) else ".laz"
            target = dest / f"value-{i}{suffix}"
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
            out.append(target)
            continue
        href = item.get("href") if isinstance(item, Mapping) else item
        if not isinstance(href, str) or not href:
            raise Problem(
                "invalid-request",
                f"a file must be {{'href': ...}}, {{'value': ...}} or a path string, not {item!r}",
            )
        uploaded = uploads.resolve(href, tenant)
        if uploaded is not None:
            out.append(link_or_copy(uploaded, dest / f"{i:04d}-{uploaded.name}"))
        elif urlsplit(href).scheme in ("http", "https"):
            raise Problem(
                "invalid-request",
                f"cannot fetch {href}: this service reads only hrefs from its own POST /uploads "
                "and paths under its input root",
            )
        else:
            out.extend(resolve_server_paths(settings, [href]))
    if len(out) > settings.max_files:
        raise Problem("invalid-request", f"{len(out)} files; the limit is {settings.max_files}")
    return out


def _decode(item: Mapping[str, Any], index: int) -> bytes:
    value, encoding = item["value"], str(item.get("encoding", "base64")).lower()
    if encoding != "base64" or not isinstance(value, str):
        raise Problem(
            "invalid-request",
            f"files[{index}]: a file value must be a base64 string (encoding: base64)",
        )
    try:
        return base64.b64decode(value, validate=True)
    except (binascii.Error, ValueError):
        raise Problem("invalid-request", f"files[{index}]: value is not valid base64") from None


def mode(prefer: str | None, points: int, settings: Settings) -> str:
    """``async`` when asked (Prefer: respond-async) or the inputs are large, else ``sync``."""
    wanted = {p.strip().lower() for p in (prefer or "").split(",")}
    if "respond-async" in wanted or points > settings.sync_max_points:
        return ASYNC
    return SYNC
