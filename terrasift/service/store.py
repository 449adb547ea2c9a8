"""The job store: one SQLite file under the data directory.

A job is written (and committed) before the API answers 201, so a restarted
service knows every job it ever accepted. Status changes are guarded SQL
updates: a dismissed job never turns back into running or successful, whatever
a worker thread reports late.
"""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from terrasift.files import write_json

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
    stage       TEXT,
    warnings    TEXT NOT NULL DEFAULT '[]',
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


ROW_CACHE = 10_000  # job rows kept in memory; beyond, the cache starts again


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
    stage: str | None = None
    warnings: list[str] = field(default_factory=list)
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


RECORD = "record.json"  # a job's (or survey's) row, kept in its directory for rebuilding


class JobStore:
    """Thread-safe access to the SQLite job store (one connection, one lock).

    With ``jobs_dir``/``surveys_dir`` every job and survey also keeps its row as
    ``record.json`` in its directory (written on creation, on every change of
    status and of stage or warnings, not on progress), so a store whose file was deleted or corrupted is
    rebuilt from them; ``check`` notices either while the service runs.

    The rows of jobs read recently are kept in memory and replaced by every write
    to them, so a status poll does not query SQLite (nor wait for its lock).
    """

    def __init__(self, path: Path, jobs_dir: Path | None = None, surveys_dir: Path | None = None):
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self.jobs_dir = jobs_dir
        self.surveys_dir = surveys_dir
        self._lock = threading.Lock()  # the writing connection
        self._rlock = threading.Lock()  # the reading one: reads never wait for a commit
        self.recovered: str | None = None  # what the last open or check had to do
        self._rows: dict[str, sqlite3.Row] = {}  # job rows by id, replaced on every write
        self._db = self._open()
        self._rdb = self._reader()
        with self._lock:
            empty = self._db.execute("SELECT COUNT(*) FROM jobs").fetchone()[0] == 0
        if empty and self._rebuild_from_records():
            self.recovered = self.recovered or "rebuilt from the job directories"

    def _open(self) -> sqlite3.Connection:
        """Connect in WAL mode; a file that is not a sound database is moved aside."""
        for attempt in range(2):
            db = sqlite3.connect(
                self.path, check_same_thread=False, isolation_level=None, timeout=30
            )
            db.row_factory = sqlite3.Row
            try:
                db.execute("PRAGMA journal_mode=WAL")
                # in WAL mode a commit survives a crash of the service without an fsync each
                db.execute("PRAGMA synchronous=NORMAL")
                db.executescript(_SCHEMA)
                _add_missing_columns(db)
                if db.execute("PRAGMA quick_check").fetchone()[0] != "ok":
                    raise sqlite3.DatabaseError("quick_check failed")
            except sqlite3.DatabaseError:
                db.close()
                if attempt:
                    raise
                self._move_aside()
                self.recovered = "the store file was corrupt; rebuilt from the job directories"
                continue
            self._ident = _ident(self.path)
            return db
        raise AssertionError("unreachable")

    def _reader(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=30)
        db.row_factory = sqlite3.Row
        return db

    @contextmanager
    def _read(self) -> Iterator[sqlite3.Connection]:
        with self._rlock:
            yield self._rdb

    def _move_aside(self) -> None:
        stamp = now().replace(":", "")
        for suffix in ("", "-wal", "-shm"):
            src = self.path.with_name(self.path.name + suffix)
            if src.exists():
                os.replace(src, src.with_name(f"{self.path.name}.corrupt-{stamp}{suffix}"))

    def check(self, thorough: bool = True) -> str:
        """Health check: the file is still ours and sound (``thorough``: SQLite's
        quick_check too, which reads every page); repairs it when not.

        ``ok``; ``restored`` (the file was deleted or replaced: the open
        connection's copy is written back, nothing is lost); ``rebuilt`` (it was
        corrupt: rebuilt from the job directories).
        """
        if not thorough and _ident(self.path) == self._ident:
            return "ok"
        # the writer first: readers (status requests on the event loop) must not wait
        # behind a commit or checkpoint this check would otherwise queue for
        with self._lock, self._rlock:
            if _ident(self.path) == self._ident:
                if not thorough:
                    return "ok"
                try:
                    sound = self._db.execute("PRAGMA quick_check").fetchone()[0] == "ok"
                except sqlite3.DatabaseError:
                    sound = False
                if sound:
                    return "ok"
                self._db.close()
                self._move_aside()
                self._db = self._open()
                rebuilt = True
            else:
                copy = sqlite3.connect(":memory:")
                self._db.backup(copy)
                self._db.close()  # removes the -wal/-shm files of the vanished file
                if self.path.exists():
                    self._move_aside()
                self._db = self._open()
                copy.backup(self._db)
                copy.close()
                self._db.execute("PRAGMA journal_mode=WAL")
                self._ident = _ident(self.path)
                rebuilt = False
            self._rdb.close()
            self._rdb = self._reader()
            self._rows.clear()
        if rebuilt:
            self._rebuild_from_records()
            self.recovered = "the store file was corrupt; rebuilt from the job directories"
            return "rebuilt"
        self.recovered = "the store file had gone; restored from the open connection"
        return "restored"

    def _rebuild_from_records(self) -> int:
        """Insert every job and survey whose directory holds a record; how many jobs."""
        self._rows.clear()
        jobs = 0
        for kind, root in (("jobs", self.jobs_dir), ("surveys", self.surveys_dir)):
            if root is None or not root.is_dir():
                continue
            for rec_path in sorted(root.glob(f"*/{RECORD}")):
                try:
                    rec = json.loads(rec_path.read_text())
                except (OSError, ValueError):
                    continue
                if not isinstance(rec, dict) or rec.get("id") != rec_path.parent.name:
                    continue
                if kind == "jobs" and rec.get("status") == RUNNING:
                    rec["status"] = ACCEPTED  # resumed by the scheduler
                cols = _JOB_COLUMNS if kind == "jobs" else _SURVEY_COLUMNS
                row = {c: rec.get(c) for c in cols}
                for c in ("params", "inputs", "outputs", "files", "warnings"):
                    if c in row and not isinstance(row[c], str):
                        row[c] = json.dumps(row[c] if row[c] is not None else [])
                try:
                    with self._tx() as db:
                        db.execute(
                            f"INSERT OR IGNORE INTO {kind} ({', '.join(cols)})"
                            f" VALUES ({', '.join('?' * len(cols))})",
                            [row[c] for c in cols],
                        )
                except sqlite3.Error:
                    continue
                jobs += kind == "jobs"
        return jobs

    def _write_record(self, job_id: str) -> None:
        """Keep the job's row in its directory (when it has one)."""
        if self.jobs_dir is None:
            return
        job_dir = self.jobs_dir / job_id
        if not job_dir.is_dir():
            return
        with self._lock:
            row = self._db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is not None:
            _write_json(job_dir / RECORD, dict(row))

    def close(self) -> None:
        with self._lock, self._rlock:
            self._rdb.close()
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
        self._fresh(job_id)
        self._write_record(job_id)
        job = self.get_job(job_id)
        assert job is not None
        return job

    def get_job(self, job_id: str, tenant: str | None = None) -> Job | None:
        """The job, or None when it does not exist or belongs to another tenant."""
        row = self._rows.get(job_id)
        if row is None:
            with self._read() as db:
                row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is not None:
                if len(self._rows) >= ROW_CACHE:
                    self._rows.clear()
                # a write since this read has put its newer row in: that one stays
                row = self._rows.setdefault(job_id, row)
        if row is None or (tenant is not None and row["tenant"] != tenant):
            return None
        return _job(row)

    def _fresh(self, job_id: str) -> None:
        """Put the committed row of ``job_id`` in the cache (after every write to it)."""
        with self._lock:
            row = self._db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                self._rows.pop(job_id, None)
            else:
                self._rows[job_id] = row

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
        with self._read() as db:
            rows = db.execute(sql, (*args, limit, offset)).fetchall()
        return [_job(r) for r in rows]

    def jobs_with_status(self, *statuses: str) -> list[Job]:
        """Jobs in any of ``statuses``, oldest first (the scheduler's queue order)."""
        marks = ",".join("?" * len(statuses))
        with self._read() as db:
            rows = db.execute(
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
            self._rows.clear()
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
        if cur.rowcount == 1:
            self._fresh(job_id)
            self._write_record(job_id)
        return cur.rowcount == 1

    def set_progress(
        self,
        job_id: str,
        progress: int,
        message: str | None = None,
        *,
        stage: str | None = None,
        warnings: list[str] | None = None,
    ) -> None:
        """Record progress (0–100) of a running job, and its stage and warnings when
        given (the record in its directory follows them); ignored once it left ``running``.

        Status reads come from this row only: nothing a poller asks for touches job files.
        """
        progress = max(0, min(100, int(progress)))
        detail = stage is not None or warnings is not None
        with self._tx() as db:
            cur = db.execute(
                "UPDATE jobs SET progress = ?, message = COALESCE(?, message),"
                " stage = COALESCE(?, stage), warnings = COALESCE(?, warnings), updated = ?"
                " WHERE id = ? AND status = ?",
                (
                    progress,
                    message,
                    stage,
                    None if warnings is None else json.dumps([str(w) for w in warnings]),
                    now(),
                    job_id,
                    RUNNING,
                ),
            )
        if cur.rowcount == 1:
            self._fresh(job_id)
            if detail:
                self._write_record(job_id)

    def queue_position(self, job: Job) -> int | None:
        """Accepted jobs ahead of this accepted one (0: next to start); None when not queued."""
        if job.status != ACCEPTED:
            return None
        with self._read() as db:
            row = db.execute(
                "SELECT COUNT(*) FROM jobs WHERE status = ? AND (created < ?"
                " OR (created = ? AND rowid < (SELECT rowid FROM jobs WHERE id = ?)))",
                (ACCEPTED, job.created, job.created, job.id),
            ).fetchone()
        return int(row[0])

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
        if cur.rowcount == 1:
            self._fresh(job_id)
            self._write_record(job_id)
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
        self._fresh(job_id)
        self._write_record(job_id)
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
        if self.surveys_dir is not None:
            record = {"id": survey_id, "tenant": tenant, "files": files, "params": params}
            _write_json(self.surveys_dir / survey_id / RECORD, {**record, "created": ts})
        return Survey(survey_id, tenant, files, params, ts)

    def set_survey_files(self, survey_id: str, files: list[str]) -> Survey | None:
        """Replace a survey's tile list (a tile added, replaced or removed)."""
        with self._tx() as db:
            db.execute("UPDATE surveys SET files = ? WHERE id = ?", (json.dumps(files), survey_id))
        survey = self.get_survey(survey_id)
        if survey is not None and self.surveys_dir is not None:
            record = {
                "id": survey.id,
                "tenant": survey.tenant,
                "files": survey.files,
                "params": survey.params,
                "created": survey.created,
            }
            _write_json(self.surveys_dir / survey_id / RECORD, record)
        return survey

    def get_survey(self, survey_id: str, tenant: str | None = None) -> Survey | None:
        with self._read() as db:
            row = db.execute("SELECT * FROM surveys WHERE id = ?", (survey_id,)).fetchone()
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
        with self._read() as db:
            rows = db.execute(
                "SELECT * FROM jobs WHERE survey_id = ? ORDER BY created, rowid", (survey_id,)
            ).fetchall()
        return [_job(r) for r in rows]


_JOB_COLUMNS = (
    "id",
    "tenant",
    "process_id",
    "status",
    "message",
    "progress",
    "stage",
    "warnings",
    "params",
    "inputs",
    "outputs",
    "survey_id",
    "created",
    "started",
    "finished",
    "updated",
)
_SURVEY_COLUMNS = ("id", "tenant", "files", "params", "created")


def _add_missing_columns(db: sqlite3.Connection) -> None:
    """Bring a store written by an older version up to the current ``jobs`` columns."""
    have = {r[1] for r in db.execute("PRAGMA table_info(jobs)")}
    if "stage" not in have:
        db.execute("ALTER TABLE jobs ADD COLUMN stage TEXT")
    if "warnings" not in have:
        db.execute("ALTER TABLE jobs ADD COLUMN warnings TEXT NOT NULL DEFAULT '[]'")


def _ident(path: Path) -> tuple[int, int] | None:
    """Device and inode of ``path``: tells a deleted or replaced file from ours."""
    try:
        st = path.stat()
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


def _write_json(path: Path, data: dict[str, Any]) -> None:
    with contextlib.suppress(OSError):  # the record is a spare copy; the store is committed
        write_json(path, data)


def _job(row: sqlite3.Row) -> Job:
    return Job(
        id=row["id"],
        tenant=row["tenant"],
        process_id=row["process_id"],
        status=row["status"],
        message=row["message"],
        progress=row["progress"],
        stage=row["stage"],
        warnings=json.loads(row["warnings"] or "[]"),
        params=json.loads(row["params"]),
        inputs=json.loads(row["inputs"]),
        outputs=json.loads(row["outputs"]),
        survey_id=row["survey_id"],
        created=row["created"],
        started=row["started"],
        finished=row["finished"],
        updated=row["updated"],
    )
