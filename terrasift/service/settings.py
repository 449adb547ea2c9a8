"""Service settings: environment variables with the ``TERRASIFT_`` prefix, or a ``.env`` file.

``TERRASIFT_DATA_DIR=/srv/terrasift`` moves the job store and job directories;
``TERRASIFT_DASK_SCHEDULER=tcp://host:8786`` sends tasks to a Dask cluster
instead of the embedded process pool.
"""

from __future__ import annotations

import ipaddress
import os
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Everything the service reads from its environment."""

    model_config = SettingsConfigDict(env_prefix="TERRASIFT_", env_file=".env", extra="ignore")

    data_dir: Path = Field(Path("./data"), description="job store (SQLite), uploads, job outputs")
    host: str = Field("127.0.0.1", description="bind address of `terrasift serve`")
    port: int = Field(8000, ge=1, le=65535, description="bind port of `terrasift serve`")
    access_log: bool = Field(
        False,
        description="log every request of `terrasift serve` (off by default: a line per status "
        "poll costs the event loop time and says little)",
    )
    dask_scheduler: str | None = Field(
        None, description="tcp://host:port of a Dask scheduler; unset = local process pool"
    )
    dask_no_workers_timeout: float = Field(
        60.0,
        gt=0,
        description="seconds a job waits with no Dask worker in the cluster before it fails",
    )
    workers: int | None = Field(
        None, ge=1, description="worker processes of the local pool; unset = one per core"
    )
    max_concurrent_jobs: int = Field(
        2, ge=1, description="jobs processed at once; later ones wait as `accepted`"
    )
    max_upload_bytes: int = Field(
        8 * 1024**3, ge=1, description="total bytes of one upload request (413 above)"
    )
    max_points: int = Field(
        2_000_000_000, ge=1, description="total points of one job, from the headers"
    )
    max_files: int = Field(1000, ge=1, description="tiles in one job or survey")
    keep_intermediates: bool = Field(
        False,
        description="keep a survey run's shards, block results and per-tile outputs after it "
        "published (default: removed then; they are several times the input)",
    )
    input_root: Path | None = Field(
        None,
        description="server directory whose files jobs may name by path; unset = paths refused",
    )
    token_file: Path | None = Field(
        None, description="lines `token tenant`; unset on a loopback bind = auth off"
    )
    auth: Literal["auto", "on", "off"] = Field(
        "auto", description="auto: off only on a loopback bind without a token file"
    )
    worker_memory: int | None = Field(
        None,
        ge=64 * 1024**2,
        description="resident bytes one worker may use before its task is stopped; "
        "unset = 80 % of the machine's memory shared by the workers",
    )
    worker_nice: int = Field(
        10,
        ge=0,
        le=19,
        description="CPU priority of workers below the API (os.nice increment; where the kernel"
        " groups CPU time by session, also the nice of each worker's own session group)",
    )
    header_readers: int = Field(
        2,
        ge=0,
        description="processes that read tile headers at submission, each with the budgets below "
        "(a file that crashes or exhausts one fails alone); 0 = read in the API process, "
        "not isolated",
    )
    header_seconds: float = Field(
        5.0,
        gt=0,
        description="CPU seconds one tile header may take to read (twice that in all) before "
        "the file is refused",
    )
    header_memory: int = Field(
        512 * 1024**2,
        ge=64 * 1024**2,
        description="bytes of memory a header reader may map beyond its own start (RLIMIT_AS); "
        "a file that needs more is refused",
    )
    task_seconds: float = Field(
        300.0, gt=0, description="time limit of every task, plus task_seconds_per_mpoint"
    )
    task_seconds_per_mpoint: float = Field(
        60.0, ge=0, description="time limit added per million points of the job"
    )
    shutdown_grace: float = Field(
        10.0,
        ge=0,
        description="seconds running tasks may finish on SIGTERM before they are stopped",
    )
    upload_lifetime: float = Field(
        24 * 3600, gt=0, description="seconds an href from POST /uploads stays valid"
    )
    sync_max_points: int = Field(
        5_000_000,
        ge=0,
        description="execute runs synchronously (Prefer absent or respond-sync) up to this many points",
    )
    sync_timeout: float = Field(
        600, gt=0, description="seconds a synchronous execute waits before answering 201 instead"
    )
    callback_attempts: int = Field(
        4, ge=1, description="tries per subscriber callback (waits 0.5, 1, 2 ... s between)"
    )
    public_url: str | None = Field(
        None, description="base URL used in links (e.g. behind a proxy); unset = from the request"
    )

    @field_validator("data_dir", "input_root", "token_file")
    @classmethod
    def _absolute(cls, path: Path | None) -> Path | None:
        """Absolute at start-up: job paths go to Dask workers in other directories."""
        return path.absolute() if path is not None else None

    @property
    def db_path(self) -> Path:
        return self.data_dir / "jobs.sqlite"

    @property
    def workers_dir(self) -> Path:
        """Pid files of the worker processes, so a restart can reap leftovers."""
        return self.data_dir / "workers"

    def worker_memory_limit(self) -> int | None:
        """``worker_memory``, else 80 % of physical memory split among the workers."""
        if self.worker_memory is not None:
            return self.worker_memory
        try:
            total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):
            return None
        return int(0.8 * total / (self.workers or os.cpu_count() or 1))

    @property
    def jobs_dir(self) -> Path:
        return self.data_dir / "jobs"

    @property
    def uploads_dir(self) -> Path:
        return self.data_dir / "uploads"

    @property
    def surveys_dir(self) -> Path:
        return self.data_dir / "surveys"

    @property
    def auth_enabled(self) -> bool:
        """Auth is off when asked, or on a loopback bind that has no token file."""
        if self.auth != "auto":
            return self.auth == "on"
        return self.token_file is not None or not is_loopback(self.host)


def is_loopback(host: str) -> bool:
    """True for localhost, 127.0.0.0/8 and ::1."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
