"""The job store: one SQLite file under the data directory.

A job is written (and committed) before the API answers 201, so a restarted
service knows every job it ever accepted. Status changes are guarded SQL
updates: a dismissed job never turns back into running or successful, whatever
a worker thread reports late.
"""

from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

ACCEPTED, RUNNING, SUCCESSFUL, FAILED, DISMISSED = (
    "accepted",
    "running",
    "successful",
    "failed",
    "dismissed",
)
STATUSES = (ACCEPTED, RUNNING, SUCCESSFUL, FAILED, DISMISSED)
ACTIVE = (ACCEPTED, RUNNING)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id          TEXT PRIMARY KEY,
    tenant      TEXT NOT NULL,
    process_id  TEXT NOT NULL,
    status      TEXT NOT NULL,
    message     TEXT,
    progress    INTEGER NOT NULL DEFAULT 0,
    params      TEXT NOT NULL,
    inputs      TEXT NOT NULL,
    outputs     TEXT NOT NULL DEFAULT '[]',
    survey_id   TEXT,
    created     TEXT NOT NULL,
    started     TEXT,
    finished    TEXT,
    updated     TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS jobs_by_tenant ON jobs (tenant, created);
CREATE INDEX IF NOT EXISTS jobs_by_status ON jobs (status);
CREATE TABLE IF NOT EXISTS surveys (
    id       TEXT PRIMARY KEY,
    tenant   TEXT NOT NULL,
    files    TEXT NOT NULL,
    params   TEXT NOT NULL,
    created  TEXT NOT NULL
);
"""


def now() -> str:
    """UTC timestamp, ISO 8601 with microseconds, so text order is time order."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


@dataclass
class Job:
    """One row of ``jobs``; ``params``/``inputs``/``outputs`` decoded from JSON."""

    id: str
    tenant: str
    process_id: str
    status: str
    params: dict[str, Any]
    inputs: list[str]
    created: str
    updated: str
    message: str | None = None
    progress: int = 0
    outputs: list[str] = field(default_factory=list)
    survey_id: str | None = None
    started: str | None = None
    finished: str | None = None


@dataclass
class Survey:
    """A registered set of tiles that runs as one job, as often as asked."""

    id: str
    tenant: str
    files: list[str]
    params: dict[str, Any]
    created: str


class JobStore:
    """Thread-safe access to the SQLite job store (one connection, one lock)."""

    def __init__(self, path: Path):
        path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None, timeout=30)
        self._db.row_factory = sqlite3.Row
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.executescript(_SCHEMA)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    # -- jobs -------------------------------------------------------------

    def create_job(
        self,
        job_id: str,
        tenant: str,
        params: dict[str, Any],
        inputs: list[str],
        *,
        process_id: str = "terrain",
        survey_id: str | None = None,
    ) -> Job:
        """Insert an ``accepted`` job; committed when this returns."""
        ts = now()
        with self._tx() as db:
            db.execute(
                "INSERT INTO jobs (id, tenant, process_id, status, params, inputs, survey_id, created, updated)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    job_id,
                    tenant,
                    process_id,
                    ACCEPTED,
                    json.dumps(params),
                    json.dumps(inputs),
                    survey_id,
                    ts,
                    ts,
                ),
            )
        job = self.get_job(job_id)
        assert job is not None
        return job

    def get_job(self, job_id: str, tenant: str | None = None) -> Job | None:
        """The job, or None when it does not exist or belongs to another tenant."""
        with self._lock:
            row = self._db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None or (tenant is not None and row["tenant"] != tenant):
            return None
        return _job(row)

    def list_jobs(
        self,
        tenant: str | None,
        *,
        statuses: list[str] | None = None,
        process_id: str | None = None,
        limit: int = 100,
        offset: int = 0,
    ) -> list[Job]:
        """Jobs newest first, filtered by tenant (None = all), status and process."""
        where, args = [], []
        if tenant is not None:
            where.append("tenant = ?")
            args.append(tenant)
        if statuses:
            where.append(f"status IN ({','.join('?' * len(statuses))})")
            args.extend(statuses)
        if process_id is not None:
            where.append("process_id = ?")
            args.append(process_id)
        sql = "SELECT * FROM jobs" + (" WHERE " + " AND ".join(where) if where else "")
        sql += " ORDER BY created DESC, rowid DESC LIMIT ? OFFSET ?"
        with self._lock:
            rows = self._db.execute(sql, (*args, limit, offset)).fetchall()
        return [_job(r) for r in rows]

    def jobs_with_status(self, *statuses: str) -> list[Job]:
        """Jobs in any of ``statuses``, oldest first (the scheduler's queue order)."""
        marks = ",".join("?" * len(statuses))
        with self._lock:
            rows = self._db.execute(
                f"SELECT * FROM jobs WHERE status IN ({marks}) ORDER BY created, rowid", statuses
            ).fetchall()
        return [_job(r) for r in rows]

    def requeue_interrupted(self) -> list[str]:
        """Turn jobs left ``running`` by a stopped service back to ``accepted``; their ids."""
        ts = now()
        with self._tx() as db:
            ids = [r["id"] for r in db.execute("SELECT id FROM jobs WHERE status = ?", (RUNNING,))]
            db.execute(
                "UPDATE jobs SET status = ?, message = ?, updated = ? WHERE status = ?",
                (ACCEPTED, "resumed after a service restart", ts, RUNNING),
            )
        return ids

    def mark_running(self, job_id: str) -> bool:
        """accepted → running; False when the job is no longer accepted (e.g. dismissed)."""
        ts = now()
        with self._tx() as db:
            cur = db.execute(
                "UPDATE jobs SET status = ?, message = ?, started = COALESCE(started, ?), updated = ?"
                " WHERE id = ? AND status = ?",
                (RUNNING, "processing", ts, ts, job_id, ACCEPTED),
            )
        return cur.rowcount == 1

    def set_progress(self, job_id: str, progress: int, message: str | None = None) -> None:
        """Record progress (0–100) of a running job; ignored once it left ``running``."""
        progress = max(0, min(100, int(progress)))
        with self._tx() as db:
            db.execute(
                "UPDATE jobs SET progress = ?, message = COALESCE(?, message), updated = ? WHERE id = ? AND status = ?",
                (progress, message, now(), job_id, RUNNING),
            )

    def finish(
        self, job_id: str, status: str, message: str, outputs: list[str] | None = None
    ) -> bool:
        """running/accepted → successful|failed|dismissed; False when already finished or dismissed."""
        if status not in (SUCCESSFUL, FAILED, DISMISSED):
            raise ValueError(f"not a final status: {status}")
        ts = now()
        progress_sql = ", progress = 100" if status == SUCCESSFUL else ""
        with self._tx() as db:
            cur = db.execute(
                f"UPDATE jobs SET status = ?, message = ?, outputs = ?, finished = ?, updated = ?{progress_sql}"
                " WHERE id = ? AND status IN (?, ?)",
                (status, message, json.dumps(outputs or []), ts, ts, job_id, *ACTIVE),
            )
        return cur.rowcount == 1

    def dismiss(self, job_id: str, message: str = "dismissed by request") -> Job | None:
        """Any status → dismissed (outputs forgotten); the updated job, or None if unknown."""
        ts = now()
        with self._tx() as db:
            db.execute(
                "UPDATE jobs SET status = ?, message = ?, outputs = '[]', finished = COALESCE(finished, ?),"
                " updated = ? WHERE id = ? AND status != ?",
                (DISMISSED, message, ts, ts, job_id, DISMISSED),
            )
        return self.get_job(job_id)

    # -- surveys ----------------------------------------------------------

    def create_survey(
        self, survey_id: str, tenant: str, files: list[str], params: dict[str, Any]
    ) -> Survey:
        ts = now()
        with self._tx() as db:
            db.execute(
                "INSERT INTO surveys (id, tenant, files, params, created) VALUES (?, ?, ?, ?, ?)",
                (survey_id, tenant, json.dumps(files), json.dumps(params), ts),
            )
        return Survey(survey_id, tenant, files, params, ts)

    def get_survey(self, survey_id: str, tenant: str | None = None) -> Survey | None:
        with self._lock:
            row = self._db.execute("SELECT * FROM surveys WHERE id = ?", (survey_id,)).fetchone()
        if row is None or (tenant is not None and row["tenant"] != tenant):
            return None
        return Survey(
            row["id"],
            row["tenant"],
            json.loads(row["files"]),
            json.loads(row["params"]),
            row["created"],
        )

    def survey_jobs(self, survey_id: str) -> list[Job]:
        with self._lock:
            rows = self._db.execute(
                "SELECT * FROM jobs WHERE survey_id = ? ORDER BY created, rowid", (survey_id,)
            ).fetchall()
        return [_job(r) for r in rows]


def _job(row: sqlite3.Row) -> Job:
    return Job(
        id=row["id"],
        tenant=row["tenant"],
        process_id=row["process_id"],
        status=row["status"],
        message=row["message"],
        progress=row["progress"],
        params=json.loads(row["params"]),
        inputs=json.loads(row["inputs"]),
        outputs=json.loads(row["outputs"]),
        survey_id=row["survey_id"],
        created=row["created"],
        started=row["started"],
        finished=row["finished"],
        updated=row["updated"],
    )
