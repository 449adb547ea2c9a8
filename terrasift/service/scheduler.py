"""The scheduler: a background thread that starts accepted jobs, up to a limit at once.

Each running job gets a thread that calls ``pipeline.run_job`` and waits on the
executor's futures, so no processing ever happens in the API's event loop.
The executor handed to ``run_job`` is wrapped per job: dismissing the job cancels
the futures it has queued and refuses new submissions, while
``pipeline.request_cancel`` writes the marker that running tasks check.
On start, jobs a stopped service left ``running`` are queued again; ``run_job``
is resumable and repeats only the tasks that are missing.
"""

from __future__ import annotations

import inspect
import json
import logging
import shutil
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

from terrasift.errors import JobCancelled, TerrasiftError
from terrasift.service.store import ACCEPTED, DISMISSED, FAILED, SUCCESSFUL, JobStore
from terrasift.workers.executors import Executor

log = logging.getLogger(__name__)

STORE_CHECK_SECONDS = 60.0  # between full integrity checks of the job store
GENERIC_FAILURE = "processing failed on an internal error; the service log has the details"


class JobExecutor:
    """One job's view of the shared executor: remembers its futures so they can be cancelled."""

    def __init__(
        self,
        inner: Any,
        task_timeout: Callable[[], float | None] | None = None,
        cancel_marker: Path | None = None,
    ):
        """``task_timeout`` gives each task's CPU-second limit; ``cancel_marker`` is the file
        whose appearance stops running tasks on executors that watch it (Dask)."""
        self._inner = inner
        self._cancel_marker = str(cancel_marker) if cancel_marker is not None else None
        self._futures: list[Any] = []
        self._lock = threading.Lock()
        self._task_timeout = task_timeout
        self.cancelled = False

    def submit(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            if self.cancelled:
                raise JobCancelled("the job was dismissed")
            limited = getattr(self._inner, "submit_limited", None)
            guarded = self._task_timeout is not None or self._cancel_marker is not None
            if limited is not None and guarded and not kwargs:
                timeout = self._task_timeout() if self._task_timeout is not None else None
                if self._cancel_marker is not None:
                    future = limited(timeout, fn, *args, cancel_marker=self._cancel_marker)
                else:
                    future = limited(timeout, fn, *args)
            else:
                future = self._inner.submit(fn, *args, **kwargs)
            self._futures = [f for f in self._futures if not f.done()]
            self._futures.append(future)
            return future

    def cancel(self) -> int:
        """Cancel every future; running ones too where the executor can stop its workers."""
        with self._lock:
            self.cancelled = True
            futures, self._futures = self._futures, []
        stop = getattr(self._inner, "cancel_running", None)
        if stop is not None:
            return stop(futures)
        return sum(1 for f in futures if f.cancel())

    def wait_any(self, futures: Iterable[Any], timeout: float) -> set[Any]:
        """Futures already done (cancelled ones included) without waiting, else the executor's wait.

        A pool notifies waiters of a cancelled future only when it would have run
        it, so after a cancel the job would otherwise sit out the running tasks.
        """
        futures = list(futures)
        done = {f for f in futures if f.done()}
        return done or self._inner.wait_any(futures, timeout)

    def stop_queued(self) -> None:
        """Cancel the futures not yet running; running ones may finish (a shutdown's grace)."""
        with self._lock:
            self.cancelled = True
            futures = list(self._futures)
        for f in futures:
            f.cancel()

    def shutdown(self, *args: Any, **kwargs: Any) -> None:
        """The scheduler owns the shared executor; a job cannot shut it down."""

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


class Scheduler:
    """Runs accepted jobs from the store in worker threads, at most ``max_concurrent`` at once."""

    def __init__(
        self,
        store: JobStore,
        jobs_dir: Path,
        executor_factory: Callable[[], Executor],
        max_concurrent: int = 2,
        pipeline: ModuleType | Any | None = None,
        poll_seconds: float = 2.0,
        task_seconds: tuple[float, float] | None = None,
        input_roots: list[Path] | None = None,
    ):
        self.store = store
        self.jobs_dir = jobs_dir
        self._executor_factory = executor_factory
        self._executor: Executor | None = None
        self._executor_lock = threading.Lock()
        self.max_concurrent = max_concurrent
        self._pipeline = pipeline
        self._poll = poll_seconds
        # (seconds, seconds per million points): every task's time limit
        self._task_seconds = task_seconds
        # where a job's inputs may lie when it starts (None: anywhere, for tests)
        self._input_roots = input_roots
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._active: dict[str, JobExecutor | None] = {}
        self._threads: dict[str, threading.Thread] = {}
        self._lock = threading.Lock()
        self._loop: threading.Thread | None = None
        #: called with a job's id when it succeeded, before it is marked so (a survey's next batch)
        self.on_success: Callable[[str], Any] | None = None

    @property
    def pipeline(self) -> Any:
        if self._pipeline is None:
            import terrasift.jobs

            self._pipeline = terrasift.jobs
        return self._pipeline

    @property
    def executor(self) -> Executor | None:
        """The shared executor, once a job has needed it."""
        return self._executor

    def job_dir(self, job_id: str) -> Path:
        return self.jobs_dir / job_id

    # -- lifecycle --------------------------------------------------------

    def start(self) -> None:
        """Queue jobs interrupted by a previous stop and start the dispatch loop."""
        resumed = self.store.requeue_interrupted()
        if resumed:
            log.info("resuming %d interrupted job(s): %s", len(resumed), ", ".join(resumed))
        self._stopping.clear()
        self._loop = threading.Thread(
            target=self._dispatch_loop, name="terrasift-scheduler", daemon=True
        )
        self._loop.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Stop dispatching, let running tasks finish for up to ``timeout`` s, then stop them.

        Jobs still running stay ``running`` in the store and resume on the next start
        (their finished tasks are kept).
        """
        deadline = time.monotonic() + timeout
        self._stopping.set()
        self._wake.set()
        with self._lock:
            threads = list(self._threads.values())
            executors = [e for e in self._active.values() if e is not None]
        for ex in executors:
            ex.stop_queued()
        if self._loop is not None:
            self._loop.join(max(0.0, deadline - time.monotonic()))
        for t in threads:
            t.join(max(0.0, deadline - time.monotonic()))
        with self._executor_lock:
            executor, self._executor = self._executor, None
        if executor is not None:
            try:
                # a job thread may have ended (its queued tasks cancelled) while a task it
                # submitted still runs: the rest of the grace period is for those tasks
                grace = 0.0 if any(t.is_alive() for t in threads) else deadline - time.monotonic()
                options = inspect.signature(executor.shutdown).parameters
                if "grace" in options:
                    executor.shutdown(grace=max(0.0, grace))  # type: ignore[call-arg]
                elif "kill" in options and grace <= 0:
                    executor.shutdown(kill=True)  # type: ignore[call-arg]
                else:
                    executor.shutdown()
            except Exception:  # noqa: BLE001 - shutting down anyway
                log.exception("executor shutdown failed")
        end = time.monotonic() + 5.0
        for t in threads:
            t.join(max(0.0, end - time.monotonic()))

    @property
    def stopping(self) -> bool:
        return self._stopping.is_set()

    def wake(self) -> None:
        """Look for accepted jobs now rather than at the next poll."""
        self._wake.set()

    def is_active(self, job_id: str) -> bool:
        with self._lock:
            return job_id in self._threads

    def wait_idle(self, timeout: float) -> bool:
        """Wait until no job thread runs (for tests and orderly shutdown)."""
        with self._lock:
            threads = list(self._threads.values())
        for t in threads:
            t.join(timeout)
        return not any(t.is_alive() for t in threads)

    # -- cancelling -------------------------------------------------------

    def cancel(self, job_id: str) -> None:
        """Make a dismissed job stop: the cancel marker for running tasks, future.cancel for queued ones."""
        job_dir = self.job_dir(job_id)
        if job_dir.exists():
            try:
                self.pipeline.request_cancel(job_dir)
            except Exception:  # noqa: BLE001 - the futures are still cancelled below
                log.exception("request_cancel failed for job %s", job_id)
        with self._lock:
            ex = self._active.get(job_id)
            running = job_id in self._threads
        if ex is not None:
            ex.cancel()
        if not running:
            self.purge(job_dir)

    # -- internals --------------------------------------------------------

    def _executor_or_create(self) -> Executor:
        with self._executor_lock:
            if self._executor is None:
                self._executor = self._executor_factory()
            return self._executor

    def _dispatch_loop(self) -> None:
        checked = time.monotonic()
        while not self._stopping.is_set():
            try:
                # the store file may be deleted or damaged under a running service
                thorough = time.monotonic() - checked > STORE_CHECK_SECONDS
                if thorough:
                    checked = time.monotonic()
                state = self.store.check(thorough=thorough)
                if state != "ok":
                    log.error("job store: %s", self.store.recovered)
                self._dispatch()
            except Exception:  # noqa: BLE001 - the loop must survive a bad row or a locked db
                log.exception("scheduler dispatch failed")
            self._wake.wait(self._poll)
            self._wake.clear()

    def _dispatch(self) -> None:
        for job in self.store.jobs_with_status(ACCEPTED):
            with self._lock:
                if self._stopping.is_set() or len(self._threads) >= self.max_concurrent:
                    return
                if job.id in self._threads:
                    continue
                thread = threading.Thread(
                    target=self._run, args=(job.id,), name=f"job-{job.id[:8]}", daemon=True
                )
                self._threads[job.id] = thread
                self._active[job.id] = None
            thread.start()

    def _run(self, job_id: str) -> None:
        try:
            self._run_job(job_id)
        finally:
            with self._lock:
                self._threads.pop(job_id, None)
                self._active.pop(job_id, None)
            self._wake.set()

    def _run_job(self, job_id: str) -> None:
        job_dir = self.job_dir(job_id)
        if not self.store.mark_running(job_id):
            job = self.store.get_job(job_id)
            if job is not None and job.status == DISMISSED:  # dismissed while queued
                self.purge(job_dir)
            return
        escaped = self._escaped_input(job_id)
        if escaped:
            self.store.finish(job_id, FAILED, f"input {escaped} now lies outside the input root")
            return
        try:
            marker = getattr(self.pipeline, "cancel_marker", None)
            ex = JobExecutor(
                self._executor_or_create(),
                self._time_limit(job_dir),
                marker(job_dir) if callable(marker) else None,
            )
        except Exception as exc:  # noqa: BLE001 - e.g. Dask scheduler unreachable
            log.exception("cannot create the executor for job %s", job_id)
            self.store.finish(job_id, FAILED, f"no workers available: {exc}")
            return
        with self._lock:
            self._active[job_id] = ex
        job = self.store.get_job(job_id)
        if job is not None and job.status == DISMISSED:  # dismissed between mark_running and here
            ex.cancel()

        last: list[Any] = [-1, None, 0.0, None]

        def progress(done: int, total: int, info: Mapping[str, Any] | None = None) -> None:
            # 100 only when successful: after the last block the mosaics still run
            pct = min(99, (100 * done) // total) if total > 0 else 0
            message = info.get("message") if info else f"{done} of {total} tasks done"
            now = time.monotonic()
            detail = (info.get("stage"), list(info.get("warnings") or [])) if info else None
            changed = info is not None and detail != last[3]
            # counts change often: a new message alone is stored at most once a second,
            # except when the stage or warnings change, so message and stage agree
            if pct != last[0] or changed or (message != last[1] and now - last[2] >= 1.0):
                last[:3] = [pct, message, now]
                if changed:
                    assert detail is not None
                    last[3] = detail
                    self.store.set_progress(
                        job_id, pct, message, stage=detail[0] or "", warnings=detail[1]
                    )
                else:
                    self.store.set_progress(job_id, pct, message)

        try:
            names = self.pipeline.run_job(job_dir, ex, progress)
        except JobCancelled:
            # DELETE already stored `dismissed`; a shutdown cancels too, and then the job resumes later
            if not self._stopping.is_set():
                self.store.finish(job_id, DISMISSED, "dismissed by request")
        except TerrasiftError as exc:
            if not self._stopping.is_set():
                self.store.finish(job_id, FAILED, str(exc))
        except BaseException:  # noqa: BLE001 - a job must never stay running
            if self._stopping.is_set():
                log.info("job %s interrupted by shutdown; it resumes on the next start", job_id)
            else:
                log.exception("job %s failed", job_id)
                self.store.finish(job_id, FAILED, GENERIC_FAILURE)
        else:
            if (
                self.on_success is not None
            ):  # before the status: a client seeing it sees what follows
                try:
                    self.on_success(job_id)
                except Exception:  # noqa: BLE001 - the job itself succeeded
                    log.exception("after job %s", job_id)
            self.store.finish(job_id, SUCCESSFUL, _finished_message(job_dir), list(names))
        job = self.store.get_job(job_id)
        if job is not None and job.status == DISMISSED:
            self.purge(job_dir)

    @property
    def input_roots(self) -> list[Path] | None:
        """Where inputs may lie (data directories and the input root); None: anywhere."""
        return None if self._input_roots is None else list(self._input_roots)

    def _escaped_input(self, job_id: str) -> str | None:
        """The name of an input that resolves outside the allowed roots (a symlink swapped in)."""
        job = self.store.get_job(job_id)
        if self._input_roots is None or job is None:
            return None
        roots = [r.resolve() for r in self._input_roots]
        for p in job.inputs:
            real = Path(p).resolve()
            if not any(real.is_relative_to(r) for r in roots):
                return Path(p).name
        return None

    def _time_limit(self, job_dir: Path) -> Callable[[], float | None] | None:
        """Each task's time limit, from the job's points once the plan has counted them."""
        if self._task_seconds is None:
            return None
        base, per_million = self._task_seconds
        known: list[float] = []

        def limit() -> float:
            if not known:
                try:
                    plan = json.loads((job_dir / "plan.json").read_text())
                    points = sum(int(t["point_count"]) for t in plan["tiles"])
                except (OSError, ValueError, KeyError, TypeError):
                    return base  # not planned yet: no task runs before the plan
                known.append(base + per_million * points / 1e6)
            return known[0]

        return limit

    def purge(self, job_dir: Path) -> None:
        """Remove what a dismissed job produced and its uploads; job.json stays for the record."""
        clear = getattr(self.pipeline, "clear_outputs", None)
        if callable(clear):
            clear(job_dir)
        for sub in ("outputs", "inputs"):
            shutil.rmtree(job_dir / sub, ignore_errors=True)


def _finished_message(job_dir: Path) -> str:
    """``finished``, with the plan's warnings (e.g. header counts that disagree) when there are any."""
    try:
        warnings = json.loads((job_dir / "plan.json").read_text()).get("warnings", [])
    except (OSError, ValueError, AttributeError):
        warnings = []
    if not warnings:
        return "finished"
    return f"finished with {len(warnings)} warning(s): " + "; ".join(str(w) for w in warnings)
