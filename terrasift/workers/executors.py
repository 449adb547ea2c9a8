"""One executor interface, ``submit(fn, *args) -> future``, over a process pool or Dask.

Tasks are plain module-level functions of paths and names, so they pickle the
same way for both. Cancelling is two-fold: queued futures are cancelled here,
and running tasks see the job's cancel marker (``terrasift.jobs``) between
stages, which works on any worker that shares the data directory.
"""

from __future__ import annotations

import importlib
import os
import sys
import time
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED
from concurrent.futures import wait as cf_wait
from pathlib import Path
from typing import Any, Protocol

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

    def submit_limited(self, timeout: float | None, fn: Callable[..., Any], *args: Any) -> Future:
        """``submit`` with a time limit in seconds: past it the worker is killed and the task fails."""
        return self.pool.submit(fn, *args, timeout=timeout)

    def cancel_running(self, futures: Iterable[Future]) -> int:
        """Cancel queued futures and stop running ones by replacing their workers."""
        return self.pool.cancel(futures)  # type: ignore[arg-type]

    def wait_any(self, futures: Iterable[Future], timeout: float) -> set[Future]:
        done, _ = cf_wait(list(futures), timeout=timeout, return_when=FIRST_COMPLETED)  # type: ignore[arg-type]
        return set(done)

    def shutdown(self, *, kill: bool = False) -> None:
        """Wait for running tasks (``kill``: stop them now); queued ones are cancelled."""
        self.pool.shutdown(wait=True, kill=kill)


class DaskExecutor:
    """Tasks on a Dask distributed cluster; workers must share the data directory."""

    def __init__(self, address: str):
        from distributed import Client  # imported lazily: the default path needs no Dask

        self._client = Client(address, set_as_default=False)
        info = self._client.scheduler_info()
        self.workers = max(1, sum(w.get("nthreads", 1) for w in info.get("workers", {}).values()))

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        # pure=False gives every submission a fresh key, so a retried task is
        # never confused with the failed one.
        return self._client.submit(fn, *args, pure=False)

    def wait_any(self, futures: Iterable[Future], timeout: float) -> set[Future]:
        # distributed.wait needs a default client, which this one is not (a
        # service may talk to several); futures know their state, so poll them.
        futs = list(futures)
        deadline = time.monotonic() + timeout
        while True:
            done = {f for f in futs if f.done()}
            if done or time.monotonic() >= deadline:
                return done
            time.sleep(0.02)

    def shutdown(self) -> None:
        self._client.close()


def make_executor(
    workers: int | None = None, dask_scheduler: str | None = None, **pool: Any
) -> Executor:
    """Dask when a scheduler address is given (or in ``TERRASIFT_DASK_SCHEDULER``), else a local
    pool; ``pool`` holds LocalExecutor's options (nice, memory_limit, pid_dir)."""
    address = dask_scheduler or os.environ.get("TERRASIFT_DASK_SCHEDULER")
    if address:
        return DaskExecutor(address)
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
