"""What statusInfo carries beyond the job row: stage, warnings, queue position.

The scheduler writes the stage and warnings of a running job to
``progress.json`` in its directory when they change (the job row keeps the
percentage and message); status documents read them back, so a finished job
still shows the warnings it met.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from terrasift.service.store import ACCEPTED, Job, JobStore

FILE = "progress.json"


def write_detail(job_dir: Path, info: Mapping[str, Any]) -> None:
    """Keep the stage and warnings of a progress report (atomic replace)."""
    detail = {"stage": info.get("stage"), "warnings": list(info.get("warnings") or [])}
    path = job_dir / FILE
    tmp = path.with_name(FILE + ".tmp")
    try:
        tmp.write_text(json.dumps(detail))
        os.replace(tmp, path)
    except OSError:  # a dismissed job's directory may be gone already
        pass


def read_detail(job_dir: Path) -> dict[str, Any]:
    try:
        return json.loads((job_dir / FILE).read_text())
    except (OSError, ValueError):
        return {}


def queue_position(store: JobStore, job: Job) -> int | None:
    """Accepted jobs created before this accepted one (0: next to start); None when not queued."""
    if job.status != ACCEPTED:
        return None
    queue = [j.id for j in store.jobs_with_status(ACCEPTED)]
    return queue.index(job.id) if job.id in queue else None


def extras(store: JobStore, job_dir: Path, job: Job) -> dict[str, Any]:
    """The terrasift members of a job's statusInfo: ``stage``, ``warnings``, ``queuePosition``."""
    out: dict[str, Any] = {}
    detail = read_detail(job_dir)
    if detail.get("stage") and job.status == "running":
        out["stage"] = detail["stage"]
    if detail.get("warnings"):
        out["warnings"] = detail["warnings"]
    position = queue_position(store, job)
    if position is not None:
        out["queuePosition"] = position
    return out
