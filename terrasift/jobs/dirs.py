"""Where things live in a job directory, and its cancel marker.

``job.json`` (inputs, parameters), ``plan.json`` (tiles, CRS, block grid; after
sharding also the ground stage's density), ``shards/<tile part>/<block>.bin``
and ``occupancy.npy``, ``blocks/<block>.npz`` and ``.json``,
``work/`` (mosaics being written) and ``outputs/``. A ``CANCELLED`` file
marks a dismissed job; running tasks look for it between stages, which works
on any worker that shares the data directory.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from terrasift.errors import JobCancelled

CANCEL_MARKER = "CANCELLED"


def output_path(job_dir: Path, name: str) -> Path:
    """Where output ``name`` of a job lives (it may not exist yet)."""
    return Path(job_dir) / "outputs" / name


def block_result_path(job_dir: Path, name: str) -> Path:
    """The result of block ``name``: labels and rasters (``.npz``); its stats sit beside as ``.json``."""
    return Path(job_dir) / "blocks" / f"{name}.npz"


def block_results(job_dir: Path) -> list[Path]:
    """Every finished block result of the job, by name."""
    return sorted((Path(job_dir) / "blocks").glob("*.npz"), key=lambda p: p.name)


def cancel_marker(job_dir: Path) -> Path:
    """The file whose existence means the job was dismissed (watched by guarded tasks)."""
    return Path(job_dir) / CANCEL_MARKER


def request_cancel(job_dir: Path) -> None:
    """Mark the job dismissed; running tasks stop at their next stage boundary."""
    Path(job_dir).mkdir(parents=True, exist_ok=True)
    (Path(job_dir) / CANCEL_MARKER).touch()


def is_cancelled(job_dir: Path) -> bool:
    return (Path(job_dir) / CANCEL_MARKER).exists()


def check_cancel(job_dir: Path) -> None:
    """Raise JobCancelled when the job was dismissed."""
    if is_cancelled(job_dir):
        raise JobCancelled("job was dismissed")


def clear_outputs(job_dir: Path) -> None:
    """Remove a job's intermediate and output files (after dismissal)."""
    for sub in ("shards", "blocks", "outputs"):
        shutil.rmtree(Path(job_dir) / sub, ignore_errors=True)
