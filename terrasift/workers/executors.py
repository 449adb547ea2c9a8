"""One executor interface, ``submit(fn, *args) -> future``, over a process pool or Dask.

Tasks are plain module-level functions of paths and names, so they pickle the
same way for both. Cancelling is two-fold: queued futures are cancelled here,
and running tasks see the job's cancel marker (``terrasift.jobs``) between
stages, which works on any worker that shares the data directory.
"""

from __future__ import annotations

import importlib
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED
from concurrent.futures import wait as cf_wait
from pathlib import Path
from typing import Any, Protocol

from terrasift.errors import TerrasiftError
from terrasift.workers.pool import WorkerPool


class Future(Protocol):
    def result(self, timeout: float | None = None) -> Any: ...
    def cancel(self) -> bool: ...
    def done(self) -> bool: ...


class Executor(Protocol):
    workers: int

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future: ...
    def wait_any(self, futures: Iterable[Future], timeout: float) -> set[Future]: ...
    def shutdown(self) -> None: ...


BLAS_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def single_threaded_blas() -> None:
    """One BLAS thread per worker process: the pool already uses every core, and
    threaded BLAS on top of it makes small per-block solves crawl. Must run
    before numpy is imported in the worker, so it is set in the environment the
    workers inherit."""
    for var in BLAS_THREAD_VARS:
        os.environ.setdefault(var, "1")


# The heavy modules every task needs (the stages, raster and LAS writing): a
# forked worker inherits them already imported.
TASK_MODULES = (
    "terrasift.workers.stages",
    "terrasift.tiling.rasters",
    "terrasift.tiling.classified",
)


def _os_thread_count() -> int:
    """Threads of this process, native ones included (Linux; 0 elsewhere).

    ``threading.active_count`` misses native pools (a LAZ decoder's, BLAS's),
    and a forked child finds such a pool's threads gone and its locks held.
    """
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return 0


class LocalExecutor:
    """A pool of disposable worker processes, one per core (or ``workers``).

    Workers are forked (Linux) when this process has a single thread, native
    threads included, so they start with the task modules imported instead of
    importing them each (~0.7 s of CPU per worker, on the critical path of a
    short CLI job), and spawned otherwise: forking a threaded process (the
    service, or one that has run a parallel LAZ decoder) can deadlock a child
    on a lock another thread held. A worker that dies is replaced by a spawned
    one (``terrasift.workers.pool``).
    """

    def __init__(
        self,
        workers: int | None = None,
        start_method: str | None = None,
        *,
        nice: int = 0,
        memory_limit: int | None = None,
        pid_dir: Path | None = None,
    ):
        self.workers = workers or os.cpu_count() or 1
        single_threaded_blas()
        if start_method is None:
            fork_safe = sys.platform == "linux" and _os_thread_count() == 1
            start_method = "fork" if fork_safe else "spawn"
        self.start_method = start_method
        if start_method == "fork":
            for name in TASK_MODULES:
                importlib.import_module(name)
        self.pool = WorkerPool(
            self.workers,
            start_method=start_method,
            nice=nice,
            memory_limit=memory_limit,
            pid_dir=pid_dir,
        )

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        return self.pool.submit(fn, *args)

    def submit_limited(
        self,
        timeout: float | None,
        fn: Callable[..., Any],
        *args: Any,
        cancel_marker: str | None = None,
    ) -> Future:
        """``submit`` with a time limit in seconds: past it the worker is killed and the task
        fails. ``cancel_marker`` is not needed here: ``cancel_running`` kills the workers."""
        return self.pool.submit(fn, *args, timeout=timeout)

    def cancel_running(self, futures: Iterable[Future]) -> int:
        """Cancel queued futures and stop running ones by replacing their workers."""
        return self.pool.cancel(futures)  # type: ignore[arg-type]

    def wait_any(self, futures: Iterable[Future], timeout: float) -> set[Future]:
        done, _ = cf_wait(list(futures), timeout=timeout, return_when=FIRST_COMPLETED)  # type: ignore[arg-type]
        return set(done)

    def shutdown(self, *, kill: bool = False, grace: float | None = None) -> None:
        """Wait for running tasks (``kill``: stop them now; ``grace``: stop them after
        that many seconds); queued ones are cancelled."""
        self.pool.shutdown(wait=True, kill=kill, grace=grace)


NO_WORKERS_TIMEOUT = 60.0
PROBE_DIR = "worker-probes"


class NoWorkersError(TerrasiftError):
    """The Dask cluster had no worker for longer than the configured time."""

    problem = "no-workers"


class DataDirError(TerrasiftError):
    """A Dask worker does not see the job directory the driver wrote."""

    problem = "data-dir-not-shared"


def _probe_data_dir(probe: str, token: str, dask_worker: Any = None) -> str:
    """On a worker: read the driver's probe file and write a reply beside it.

    Returns "" when both work, else why not; never raises, so one bad worker
    does not hide the others' answers.
    """
    path = Path(probe)
    try:
        if path.read_text() != token:
            return f"{path} holds another job's probe"
    except OSError as exc:
        return f"cannot read {path} ({exc.strerror or exc})"
    name = getattr(dask_worker, "address", None) or f"pid-{os.getpid()}"
    reply = path.parent / f"reply-{_safe(name)}"
    try:
        reply.write_text(token)
    except OSError as exc:
        return f"cannot write {reply} ({exc.strerror or exc})"
    return ""


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


class DaskExecutor:
    """Tasks on a Dask distributed cluster; workers must share the data directory.

    ``no_workers_timeout`` (seconds) bounds how long a job waits with no worker
    in the cluster, before it starts and while it runs; past it the job fails
    with :class:`NoWorkersError` instead of sitting at 0 % forever.

    Every task runs guarded (``terrasift.workers.guarded``): in a disposable
    process of the Dask worker, under ``memory_limit`` (bytes per process; None:
    each worker's own limit, ``guarded.own_memory_limit``),
    the CPU seconds of ``submit_limited``, and stopped when the cancel marker
    it was given appears, as on the local pool.
    """

    def __init__(
        self,
        address: str,
        no_workers_timeout: float | None = None,
        *,
        memory_limit: int | None = None,
        nice: int = 0,
    ):
        from distributed import Client  # imported lazily: the default path needs no Dask

        if no_workers_timeout is None:
            env = os.environ.get("TERRASIFT_DASK_NO_WORKERS_TIMEOUT")
            no_workers_timeout = float(env) if env else NO_WORKERS_TIMEOUT
        self.no_workers_timeout = no_workers_timeout
        self.memory_limit = memory_limit
        self.nice = nice
        self.address = address
        self._client = Client(address, set_as_default=False)
        self._workers_seen = time.monotonic()
        self._last_check = 0.0
        self.workers = 1
        self._count_workers()

    def _count_workers(self) -> int:
        """Workers in the cluster now; updates ``workers`` (threads, at least 1)."""
        info = self._client.scheduler_info(n_workers=-1)
        workers = info.get("workers", {})
        if workers:
            self.workers = max(1, sum(w.get("nthreads", 1) for w in workers.values()))
            self._workers_seen = time.monotonic()
        return len(workers)

    def _no_workers_error(self) -> NoWorkersError:
        return NoWorkersError(
            f"no Dask worker joined the scheduler {self.address} for "
            f"{self.no_workers_timeout:g} s (TERRASIFT_DASK_NO_WORKERS_TIMEOUT); "
            "start workers with `terrasift worker SCHEDULER`"
        )

    def wait_for_workers(self) -> None:
        """Return once the cluster has a worker; raise NoWorkersError after the timeout."""
        deadline = time.monotonic() + self.no_workers_timeout
        while self._count_workers() == 0:
            if time.monotonic() >= deadline:
                raise self._no_workers_error()
            time.sleep(min(0.2, self.no_workers_timeout))

    def preflight(self, job_dir: Path) -> None:
        """Check every worker reads and writes the job directory, before any task runs.

        The driver writes a probe file under ``job_dir``; each worker reads it and
        writes a reply next to it, which the driver then reads back. A worker
        with a private data directory would otherwise "succeed" tasks into its
        own folder and the job fail much later on a missing file.
        """
        import secrets

        self.wait_for_workers()
        folder = Path(job_dir).absolute() / PROBE_DIR
        folder.mkdir(parents=True, exist_ok=True)
        token = secrets.token_hex(8)
        probe = folder / "probe"
        probe.write_text(token)
        try:
            answers = self._client.run(_probe_data_dir, str(probe), token, on_error="return")
            problems = []
            for address, answer in sorted(answers.items()):
                if isinstance(answer, BaseException):
                    answer = f"probe failed ({answer!r})"
                elif not answer:
                    reply = folder / f"reply-{_safe(address)}"
                    try:
                        ok = reply.read_text() == token
                    except OSError:
                        ok = False
                    if not ok:
                        answer = f"wrote its reply where the driver cannot see it ({reply})"
                if answer:
                    problems.append(f"worker {address}: {answer}")
            if problems:
                raise DataDirError(
                    "Dask workers do not share the data directory "
                    f"{Path(job_dir).absolute().parent}: "
                    + "; ".join(problems)
                    + ". Every worker must mount the same data directory at the same path."
                )
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        return self.submit_limited(None, fn, *args)

    def submit_limited(
        self,
        timeout: float | None,
        fn: Callable[..., Any],
        *args: Any,
        cancel_marker: str | None = None,
    ) -> Future:
        """``fn(*args)`` guarded on a worker: at most ``timeout`` CPU seconds, the memory
        limit, and stopped within a fraction of a second once ``cancel_marker`` exists."""
        from terrasift.workers.guarded import Guard, run_guarded

        guard = Guard(timeout, self.memory_limit, cancel_marker, self.nice)
        # pure=False gives every submission a fresh key, so a retried task is
        # never confused with the failed one.
        return self._client.submit(run_guarded, fn, args, guard, pure=False)

    def wait_any(self, futures: Iterable[Future], timeout: float) -> set[Future]:
        """Futures done within ``timeout``; raises NoWorkersError once the cluster
        has had no worker for longer than ``no_workers_timeout``."""
        # distributed.wait needs a default client, which this one is not (a
        # service may talk to several); futures know their state, so poll them.
        futs = list(futures)
        deadline = time.monotonic() + timeout
        while True:
            done = {f for f in futs if f.done()}
            if done:
                return done
            now = time.monotonic()
            if now - self._last_check >= 1.0:
                self._last_check = now
                if (
                    self._count_workers() == 0
                    and now - self._workers_seen >= self.no_workers_timeout
                ):
                    raise self._no_workers_error()
            if now >= deadline:
                return done
            time.sleep(0.02)

    def shutdown(self) -> None:
        self._client.close()


def make_executor(
    workers: int | None = None,
    dask_scheduler: str | None = None,
    no_workers_timeout: float | None = None,
    **pool: Any,
) -> Executor:
    """Dask when a scheduler address is given (or in ``TERRASIFT_DASK_SCHEDULER``), else a local
    pool; ``pool`` holds LocalExecutor's options (nice, memory_limit, pid_dir)."""
    address = dask_scheduler or os.environ.get("TERRASIFT_DASK_SCHEDULER")
    if address:
        # the memory limit is each Dask worker's own (its machine, its settings)
        return DaskExecutor(address, no_workers_timeout, nice=pool.get("nice", 0))
    return LocalExecutor(workers, **pool)


class InlineExecutor:
    """Runs each task at submission in the calling process: for tests and debugging."""

    workers = 1

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        from concurrent.futures import Future as CFuture

        fut: CFuture = CFuture()
        try:
            fut.set_result(fn(*args))
        except BaseException as exc:  # the future carries it to the waiter
            fut.set_exception(exc)
        return fut

    def wait_any(self, futures: Iterable[Future], timeout: float) -> set[Future]:
        return {f for f in futures if f.done()}

    def shutdown(self) -> None:
        pass
