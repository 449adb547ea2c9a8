"""What statusInfo carries beyond OGC's members: stage, warnings, queue position.

The scheduler stores the stage and warnings of a running job in its row when
they change (with the percentage and message), so a status read is one row of
the store and a finished job still shows the warnings it met.
"""

from __future__ import annotations

from typing import Any

from terrasift.service.store import RUNNING, Job, JobStore


def extras(store: JobStore, job: Job) -> dict[str, Any]:
    """The terrasift members of a job's statusInfo: ``stage``, ``warnings``, ``queuePosition``."""
    out: dict[str, Any] = {}
    if job.stage and job.status == RUNNING:
        out["stage"] = job.stage
    if job.warnings:
        out["warnings"] = job.warnings
    position = store.queue_position(job)
    if position is not None:
        out["queuePosition"] = position
    return out
