"""Dismiss means stop: DELETE ends a job's running task even inside one long call, and a
shutdown gives running tasks a grace period, then stops them; the job resumes later."""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from terrasift.service.scheduler import Scheduler
from terrasift.service.store import JobStore
from terrasift.workers.executors import LocalExecutor


def long_call(seconds: float) -> float:
    time.sleep(seconds)
    return seconds


def _run_job(job_dir: Path, executor, progress) -> list[str]:
    """A job of one long task, waited on as the pipeline waits on its tasks."""
    future = executor.submit(long_call, 120.0)
    while not future.done():
        executor.wait_any([future], 0.5)
    future.result()
    return []


def _run_two_tasks(job_dir: Path, executor, progress) -> list[str]:
    """One long task running and one queued behind it: a shutdown cancels the queued one
    and the job thread ends (as the pipeline's does) while the long call still runs."""
    futures = [executor.submit(long_call, 120.0), executor.submit(long_call, 0.0)]
    while True:
        for f in executor.wait_any(futures, 0.5):
            f.result()
            futures.remove(f)
        if not futures:
            return []


def _request_cancel(job_dir: Path) -> None:
    (Path(job_dir) / "CANCELLED").touch()


PIPELINE = SimpleNamespace(
    run_job=_run_job, request_cancel=_request_cancel, clear_outputs=lambda job_dir: None
)


@pytest.fixture()
def scheduler(tmp_path: Path):
    store = JobStore(tmp_path / "jobs.sqlite")
    executor = LocalExecutor(1, start_method="spawn")
    s = Scheduler(
        store, tmp_path / "jobs", lambda: executor, 2, pipeline=PIPELINE, poll_seconds=0.1
    )
    s.start()
    yield s, store, executor
    s.stop(timeout=0)
    store.close()


def _start(store: JobStore, scheduler: Scheduler, executor: LocalExecutor, job_id: str) -> None:
    (scheduler.job_dir(job_id)).mkdir(parents=True)
    store.create_job(job_id, "t", {}, [])
    scheduler.wake()
    end = time.monotonic() + 60
    while not executor.pool.busy_pids() and time.monotonic() < end:
        time.sleep(0.02)
    assert executor.pool.busy_pids(), "the task never started"


def test_dismiss_stops_a_long_single_call(scheduler) -> None:
    s, store, executor = scheduler
    _start(store, s, executor, "j1")
    busy = executor.pool.busy_pids()
    t = time.monotonic()
    store.dismiss("j1")
    s.cancel("j1")
    end = time.monotonic() + 10
    while s.is_active("j1") and time.monotonic() < end:
        time.sleep(0.02)
    took = time.monotonic() - t
    print(f"dismiss to stopped: {took:.2f} s")
    assert not s.is_active("j1") and took < 5
    assert store.get_job("j1").status == "dismissed"
    assert not set(busy) & set(executor.pool.worker_pids())
    # the pool goes on with a fresh worker
    assert executor.submit(long_call, 0.0).result(timeout=60) == 0.0


def test_shutdown_stops_running_tasks_after_the_grace_period(scheduler) -> None:
    s, store, executor = scheduler
    _start(store, s, executor, "j2")
    busy = executor.pool.busy_pids()
    t = time.monotonic()
    s.stop(timeout=1.0)
    took = time.monotonic() - t
    print(f"stop with a 1 s grace: {took:.2f} s")
    assert 1.0 <= took < 8
    assert all(not Path(f"/proc/{p}").exists() for p in busy)
    assert store.get_job("j2").status == "running"  # resumes on the next start
    assert store.requeue_interrupted() == ["j2"]


def test_the_grace_period_bounds_tasks_whose_job_thread_has_ended(tmp_path: Path) -> None:
    store = JobStore(tmp_path / "jobs.sqlite")
    executor = LocalExecutor(1, start_method="spawn")
    pipeline = SimpleNamespace(**{**vars(PIPELINE), "run_job": _run_two_tasks})
    s = Scheduler(
        store, tmp_path / "jobs", lambda: executor, 2, pipeline=pipeline, poll_seconds=0.1
    )
    s.start()
    try:
        _start(store, s, executor, "j3")
        busy = executor.pool.busy_pids()
        t = time.monotonic()
        s.stop(timeout=1.0)
        took = time.monotonic() - t
        print(f"stop with a 1 s grace, job thread gone first: {took:.2f} s")
        # before: the pool waited for the 120 s call once no job thread was left
        assert took < 8
        assert all(not Path(f"/proc/{p}").exists() for p in busy)
    finally:
        s.stop(timeout=0)
        store.close()
