"""Tasks run on a Dask worker with the local pool's guarantees: limits and dismissal.

A Dask worker runs tasks in threads of its own process, where nothing can stop
a running task or bound its memory. ``run_guarded`` is the function Dask runs
instead: it hands the task to a ``WorkerPool`` of disposable processes owned by
that Dask worker (one per worker thread, started once, dying with it) and waits,
looking for the job's cancel marker every ``POLL`` seconds. A dismissed job's
task is killed there and then; one that grows past the memory limit or uses
more than its CPU seconds is killed by the pool and fails with the same message
as on the local pool. The task's result or error comes back through Dask as
before.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from collections.abc import Callable
from concurrent.futures import CancelledError
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import Any

from terrasift.errors import JobCancelled
from terrasift.workers.pool import WorkerPool

POLL = 0.25  # seconds between looks at the cancel marker


@dataclass(frozen=True)
class Guard:
    """What a guarded task may use: CPU seconds (None: no limit), resident bytes per
    process (None: this worker's own limit, see ``own_memory_limit``), and the path
    whose existence means its job was dismissed."""

    cpu_seconds: float | None = None
    memory_limit: int | None = None
    cancel_marker: str | None = None
    nice: int = 0


_pools: dict[tuple[int | None, int], WorkerPool] = {}
_pools_lock = threading.Lock()


def _threads() -> int:
    """Threads of the Dask worker this runs in (1 outside one)."""
    try:
        from distributed import get_worker

        return max(1, int(get_worker().state.nthreads))
    except (ImportError, ValueError, AttributeError):
        return 1


def own_memory_limit(threads: int | None = None) -> int | None:
    """Resident bytes one guarded process may use on this Dask worker, from the worker's
    own settings, not the API's (the machines may differ): ``TERRASIFT_WORKER_MEMORY``
    in its environment, else 80 % of its Dask memory limit (``--memory-limit``; by
    default the machine's memory shared by its worker processes), else 80 % of this
    machine's memory, shared by its threads (one guarded process each)."""
    env = os.environ.get("TERRASIFT_WORKER_MEMORY", "").strip()
    if env:
        try:
            return max(64 * 1024**2, int(float(env)))
        except ValueError:
            pass
    threads = threads or _threads()
    total = None
    try:
        from distributed import get_worker

        total = get_worker().memory_manager.memory_limit
    except (ImportError, ValueError, AttributeError):
        pass
    if not total:
        try:
            total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):
            return None
    return int(0.8 * total / threads)


def _pool(guard: Guard) -> WorkerPool:
    """This process's pool for the guard's memory limit and priority, started on first use."""
    key = (guard.memory_limit, guard.nice)
    with _pools_lock:
        pool = _pools.get(key)
        if pool is None:
            _allow_children()
            threads = _threads()
            limit = guard.memory_limit or own_memory_limit(threads)
            pool = WorkerPool(threads, start_method="spawn", nice=guard.nice, memory_limit=limit)
            _pools[key] = pool
        return pool


def _allow_children() -> None:
    """A Dask nanny starts its worker as a daemon process, which multiprocessing
    forbids to start children. The pool's processes die with this one anyway
    (``PR_SET_PDEATHSIG``), so the flag is lifted for this process."""
    me = multiprocessing.current_process()
    if me.daemon:
        try:
            me.daemon = False
        except AssertionError:  # the flag of a started process: set where multiprocessing keeps it
            me._config["daemon"] = False  # type: ignore[attr-defined]


def run_guarded(fn: Callable[..., Any], args: tuple, guard: Guard) -> Any:
    """Run ``fn(*args)`` in a disposable process under ``guard``; its result, or its error."""
    if guard.cancel_marker and os.path.exists(guard.cancel_marker):
        raise JobCancelled("the job was dismissed")
    pool = _pool(guard)
    future = pool.submit(fn, *args, timeout=guard.cpu_seconds)
    while True:
        try:
            return future.result(timeout=POLL)
        except FutureTimeout:
            pass
        if guard.cancel_marker and os.path.exists(guard.cancel_marker):
            pool.cancel([future])
            try:
                return future.result(timeout=30)  # JobCancelled once the worker is killed
            except (FutureTimeout, CancelledError):
                raise JobCancelled("the job was dismissed") from None


def shutdown_pools() -> None:
    """Stop every guarded pool of this process (tests; a Dask worker's pools die with it)."""
    with _pools_lock:
        pools = list(_pools.values())
        _pools.clear()
    for pool in pools:
        pool.shutdown(wait=True, kill=True)
