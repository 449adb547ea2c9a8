"""Turning a request into a recorded job: validate, inspect headers, prepare, persist.

Everything here runs in a worker thread (never the event loop) and raises
before anything is recorded, so a bad request leaves no job behind. The job
row is committed before the caller answers 201.
"""

from __future__ import annotations

import inspect
import shutil
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic_core import to_jsonable_python

from terrasift.errors import ParameterError
from terrasift.service.guard import CONTROL_CHARS, RequestRefused, load_json
from terrasift.service.problems import Problem
from terrasift.service.scheduler import Scheduler
from terrasift.service.settings import Settings
from terrasift.service.store import Job, JobStore

LAS_SUFFIXES = (".las", ".laz")


def new_id() -> str:
    return uuid.uuid4().hex


def parse_params(text: str | None) -> dict[str, Any]:
    """The multipart ``params`` field: a JSON object of parameters (absent = none)."""
    if text is None or not text.strip():
        return {}
    try:
        value = load_json(text, "params")
    except RequestRefused as exc:
        if exc.slug == "invalid-request":
            raise ParameterError(str(exc)) from None
        raise Problem(exc.slug, str(exc)) from None
    if not isinstance(value, dict):
        raise ParameterError(
            f"params must be a JSON object of parameters, not {type(value).__name__}"
        )
    return value


def resolve_server_paths(settings: Settings, items: list[Any]) -> list[Path]:
    """Paths a client named, checked to lie inside the input root; a directory means its LAS/LAZ files."""
    root = settings.input_root
    if root is None:
        raise Problem(
            "forbidden-path",
            "this service has no input root (TERRASIFT_INPUT_ROOT); upload the files to /jobs instead",
        )
    if not items:
        raise Problem("invalid-request", "`files` must name at least one file")
    root_real = root.resolve()
    out: list[Path] = []
    for item in items:
        text = item.get("href") if isinstance(item, Mapping) else item
        if not isinstance(text, str) or not text:
            raise Problem(
                "invalid-request", f"a file must be a path string or {{'href': path}}, not {item!r}"
            )
        text = text.removeprefix("file://")
        if CONTROL_CHARS.search(text):
            raise Problem("invalid-request", f"path {text!r} holds a control character")
        try:
            out.extend(_server_files(root_real, text))
        except (OSError, RuntimeError) as exc:  # a name too long, a symlink loop
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise Problem(
                "invalid-request", f"path {text[:200]!r} cannot be used: {reason}"
            ) from None
    if len(out) > settings.max_files:
        raise Problem("invalid-request", f"{len(out)} files; the limit is {settings.max_files}")
    return out


def _server_files(root_real: Path, text: str) -> list[Path]:
    """The LAS/LAZ files ``text`` names under ``root_real``: the file, or a directory's."""
    real = (root_real / text).resolve()  # an absolute `text` replaces the root, then is checked
    if not real.is_relative_to(root_real):
        raise Problem("forbidden-path", f"{text!r} is outside the input root")
    if real.is_dir():
        found = sorted(
            p for p in real.iterdir() if p.is_file() and p.suffix.lower() in LAS_SUFFIXES
        )
        if not found:
            raise Problem("invalid-request", f"directory {text!r} holds no .las/.laz files")
        return found
    if real.is_file():
        return [real]
    raise Problem("invalid-request", f"no file {text!r} under the input root")


def inside_root(settings: Settings, paths: list[Path]) -> None:
    """Re-check, when files are about to be opened, that each still lies in the input root.

    A registered file may since have been replaced by a symlink to somewhere else.
    """
    root = settings.input_root
    for p in paths:
        try:
            real = Path(p).resolve()
        except (OSError, RuntimeError) as exc:  # a symlink loop swapped in
            raise Problem("forbidden-path", f"{Path(p).name!r} cannot be resolved: {exc}") from None
        if root is None or not real.is_relative_to(root.resolve()):
            raise Problem("forbidden-path", f"{Path(p).name!r} now lies outside the input root")


def check_inputs(
    settings: Settings,
    inputs: list[Path],
    raw_params: Mapping[str, Any],
    pipeline: Any,
    *,
    whole: bool = True,
) -> dict[str, Any]:
    """Validated parameters after a header-only look at every input; raises on the first problem.

    ``whole=False`` (a survey) leaves the total to each run: only a tile over the limit fails.
    """
    if not inputs:
        raise Problem("invalid-request", "no input files: send one or more `file` fields")
    params = pipeline.validate_params(raw_params)
    if "max_points" in inspect.signature(pipeline.inspect_inputs).parameters:
        summary = pipeline.inspect_inputs(inputs, params, max_points=settings.max_points)
    else:
        summary = pipeline.inspect_inputs(inputs, params)
    points = int(summary.get("points", 0)) if isinstance(summary, Mapping) else 0
    if whole and points > settings.max_points:
        raise Problem(
            "too-many-points",
            f"the inputs hold {points} points; this service takes at most {settings.max_points}",
        )
    return params


def create_job(
    settings: Settings,
    store: JobStore,
    scheduler: Scheduler,
    tenant: str,
    job_id: str,
    inputs: list[Path],
    raw_params: Mapping[str, Any],
    survey_id: str | None = None,
    outputs: list[str] | None = None,
) -> Job:
    """Check, prepare and record a job whose inputs are in place; the job directory goes on error.

    ``outputs`` selects the outputs to compute (None: all)."""
    job_dir = scheduler.job_dir(job_id)
    try:
        params = check_inputs(settings, inputs, raw_params, scheduler.pipeline)
        job_dir.mkdir(parents=True, exist_ok=True)
        if outputs is None:
            scheduler.pipeline.prepare_job(job_dir, inputs, params)
        else:
            scheduler.pipeline.prepare_job(job_dir, inputs, params, outputs=outputs)
        confine = getattr(scheduler.pipeline, "set_input_roots", None)
        if callable(confine) and scheduler.input_roots is not None:
            confine(job_dir, scheduler.input_roots)  # re-checked by every task that opens one
        job = store.create_job(
            job_id,
            tenant,
            to_jsonable_python(params, fallback=str),
            [str(p) for p in inputs],
            survey_id=survey_id,
        )
    except BaseException:
        shutil.rmtree(job_dir, ignore_errors=True)
        raise
    scheduler.wake()
    return job
