"""One executor interface, ``submit(fn, *args) -> future``, over a process pool or Dask.

Tasks are plain module-level functions of paths and names, so they pickle the
same way for both. Cancelling is two-fold: queued futures are cancelled here,
and running tasks see the job's cancel marker (``terrasift.pipeline``) between
stages, which works on any worker that shares the data directory.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor
from concurrent.futures import wait as cf_wait
from typing import Any, Protocol


class Future(Protocol):
    def result(self, timeout: float | None = None) -> Any: ...
    def cancel(self) -> bool: ...
    def done(self) -> bool: ...


class Executor(Protocol):
    workers: int

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future: ...
    def wait_any(self, futures: Iterable[Future], timeout: float) -> set[Future]: ...
    def shutdown(self) -> None: ...


class LocalExecutor:
    """A process pool with one worker per core (or ``workers``)."""

    def __init__(self, workers: int | None = None):
        self.workers = workers or os.cpu_count() or 1
        # spawn: the service has threads, and forking a threaded process is unsafe.
        ctx = multiprocessing.get_context("spawn")
        self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx)

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        return self._pool.submit(fn, *args)

    def wait_any(self, futures: Iterable[Future], timeout: float) -> set[Future]:
        done, _ = cf_wait(list(futures), timeout=timeout, return_when=FIRST_COMPLETED)  # type: ignore[arg-type]
        return set(done)

    def shutdown(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


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
        from distributed import wait as dask_wait
        from distributed.client import FIRST_COMPLETED as DASK_FIRST

        futs = list(futures)
        try:
            done, _ = dask_wait(futs, timeout=timeout, return_when=DASK_FIRST)
        except TimeoutError:
            return set()
        return set(done)

    def shutdown(self) -> None:
        self._client.close()


def make_executor(workers: int | None = None, dask_scheduler: str | None = None) -> Executor:
    """Dask when a scheduler address is given (or in ``TERRASIFT_DASK_SCHEDULER``), else a local pool."""
    address = dask_scheduler or os.environ.get("TERRASIFT_DASK_SCHEDULER")
    if address:
        return DaskExecutor(address)
    return LocalExecutor(workers)


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
