"""Dask tasks run guarded: a dismissed job's running task stops, memory and CPU-time
limits hold, as on the local pool (``terrasift.workers.guarded``)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from terrasift import jobs
from terrasift.errors import JobCancelled
from terrasift.service.scheduler import JobExecutor
from terrasift.workers.executors import DaskExecutor
from terrasift.workers.guarded import shutdown_pools
from terrasift.workers.pool import TaskOutOfMemory, TaskTimeout

distributed = pytest.importorskip("distributed")


def _spin(pid_file: str) -> None:
    Path(pid_file).write_text(str(os.getpid()))
    while True:
        pass


def _grow(step: int = 50 * 2**20) -> int:
    held = []
    for _ in range(200):  # 10 GB: far past any limit given here
        held.append(bytearray(step))  # zero-filled: every page is touched
        time.sleep(0.01)
    return len(held)


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(
        n_workers=1,
        threads_per_worker=2,
        processes=False,
        protocol="tcp://",
        host="127.0.0.1",
        dashboard_address=None,
    ) as c:
        yield c.scheduler_address
    shutdown_pools()


@pytest.fixture
def executor(cluster):
    ex = DaskExecutor(cluster, 30, memory_limit=400 * 2**20)
    yield ex
    ex.shutdown()


def _gone(pid: int, within: float) -> bool:
    end = time.monotonic() + within
    while time.monotonic() < end:
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            return True
        if stat.rsplit(")", 1)[1].split()[0] == "Z":  # killed, not yet reaped
            return True
        time.sleep(0.05)
    return False


def test_a_dismissed_jobs_running_task_stops(executor: DaskExecutor, tmp_path: Path) -> None:
    """The service's view of a job (JobExecutor) hands the job's cancel marker to Dask
    tasks; DELETE's marker (``jobs.request_cancel``) stops the running one."""
    pid_file = tmp_path / "pid"
    job_ex = JobExecutor(executor, lambda: 600.0, jobs.cancel_marker(tmp_path))
    future = job_ex.submit(_spin, str(pid_file))
    end = time.monotonic() + 60
    while not pid_file.exists() and time.monotonic() < end:
        time.sleep(0.05)
    pid = int(pid_file.read_text())
    assert pid != os.getpid()  # the task runs in a process of its own
    t = time.monotonic()
    jobs.request_cancel(tmp_path)
    with pytest.raises(JobCancelled):
        future.result(timeout=30)
    assert time.monotonic() - t < 10
    assert _gone(pid, 5.0)
    # the pool goes on: the next task runs
    assert executor.submit(os.getpid).result(timeout=60) not in (pid, os.getpid())


def test_cpu_time_and_memory_limits_hold(executor: DaskExecutor, tmp_path: Path) -> None:
    spin = executor.submit_limited(1.0, _spin, str(tmp_path / "pid"))
    grow = executor.submit(_grow)
    with pytest.raises(TaskTimeout, match="limit of 1 s of CPU"):
        spin.result(timeout=60)
    with pytest.raises(TaskOutOfMemory, match="memory limit"):
        grow.result(timeout=60)


def test_guarded_tasks_run_under_a_dask_nanny(tmp_path: Path) -> None:
    """`terrasift worker --nworkers 2` runs daemonic workers, which may not start
    processes by default: the guard lifts that, so tasks run (in a child)."""
    with distributed.LocalCluster(
        n_workers=0, processes=False, protocol="tcp://", host="127.0.0.1", dashboard_address=None
    ) as c:
        cmd = [sys.executable, "-m", "terrasift", "worker", c.scheduler_address]
        proc = subprocess.Popen(
            [*cmd, "--nthreads", "1", "--nworkers", "2"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            ex = DaskExecutor(c.scheduler_address, 60)
            ex.wait_for_workers()
            workers = set(ex._client.run(os.getpid).values())
            pids = [ex.submit(os.getpid) for _ in range(4)]
            got = {f.result(timeout=120) for f in pids}
            assert got and not got & workers and os.getpid() not in got
            ex.shutdown()
        finally:
            proc.terminate()
            proc.wait(timeout=30)


def test_the_memory_limit_is_the_dask_workers_own(cluster, monkeypatch) -> None:
    """Not the API machine's: 80 % of the worker's Dask memory limit per thread, or
    TERRASIFT_WORKER_MEMORY set where the worker runs."""
    from terrasift.workers.guarded import own_memory_limit

    monkeypatch.delenv("TERRASIFT_WORKER_MEMORY", raising=False)
    client = distributed.Client(cluster, set_as_default=False)
    try:
        (info,) = client.scheduler_info(n_workers=-1)["workers"].values()
        assert info["memory_limit"] > 0 and info["nthreads"] == 2
        got = client.submit(own_memory_limit, pure=False).result(timeout=30)
        assert got == int(0.8 * info["memory_limit"] / 2)
        monkeypatch.setenv(
            "TERRASIFT_WORKER_MEMORY", str(300 * 2**20)
        )  # this process is the worker
        got = client.submit(own_memory_limit, pure=False).result(timeout=30)
        assert got == 300 * 2**20
    finally:
        client.close()
