"""Dask as a deployable engine: `terrasift worker`, the data-directory pre-flight,
and the no-workers timeout, on a real scheduler with workers as separate processes."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from terrasift import cli, jobs
from terrasift.workers.executors import DaskExecutor, DataDirError, NoWorkersError

distributed = pytest.importorskip("distributed")
psutil = pytest.importorskip("psutil")  # a dependency of distributed

TERRASIFT = [sys.executable, "-m", "terrasift"]


@pytest.fixture
def scheduler():
    """A Dask scheduler on loopback with no workers of its own."""
    with distributed.LocalCluster(
        n_workers=0,
        processes=False,
        protocol="tcp://",
        host="127.0.0.1",
        dashboard_address=None,
    ) as cluster:
        yield cluster.scheduler_address


def _start_worker(address: str, *prefix: str, nworkers: int = 1) -> subprocess.Popen:
    return subprocess.Popen(
        [*prefix, *TERRASIFT, "worker", address, "--nthreads", "1", "--nworkers", str(nworkers)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_workers(client, n: int, timeout: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        workers = client.scheduler_info(n_workers=-1)["workers"]
        if len(workers) >= n:
            return workers
        time.sleep(0.1)
    raise AssertionError(f"{n} worker(s) did not join in {timeout} s")


def _stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def test_worker_arguments(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple] = []
    monkeypatch.setattr(cli, "run_worker", lambda *a, **k: calls.append((a, k)) or 0)
    assert cli.main(["worker", "tcp://10.0.0.1:8786"]) == 0
    assert calls[-1] == (
        ("tcp://10.0.0.1:8786", 1),
        {"host": "127.0.0.1", "nworkers": 1, "dashboard": None},
    )
    args = ["worker", "tcp://s:8786", "--host", "10.0.0.7", "--nthreads", "4", "--nworkers", "3"]
    assert cli.main([*args, "--dashboard"]) == 0
    assert calls[-1] == (
        ("tcp://s:8786", 4),
        {"host": "10.0.0.7", "nworkers": 3, "dashboard": ":0"},
    )
    for bad in (["--nthreads", "0"], ["--nworkers", "-1"]):
        with pytest.raises(SystemExit):
            cli.main(["worker", "tcp://s:8786", *bad])
    # no dashboard unless asked; when asked as :PORT it binds the worker's host
    assert cli.worker_options("127.0.0.1", 2, None) == {
        "host": "127.0.0.1",
        "nthreads": 2,
        "dashboard": False,
    }
    assert cli.worker_options("10.0.0.7", 1, ":8790")["dashboard_address"] == "10.0.0.7:8790"
    assert cli.worker_options("10.0.0.7", 1, "0.0.0.0:8790")["dashboard_address"] == (
        "0.0.0.0:8790"
    )


def test_no_workers_fails_the_job_with_a_message(tmp_path: Path, small_tile, scheduler) -> None:
    executor = DaskExecutor(scheduler, no_workers_timeout=0.5)
    try:
        job = tmp_path / "job"
        jobs.prepare_job(job, [small_tile], jobs.validate_params({}))
        started = time.monotonic()
        with pytest.raises(NoWorkersError, match="no Dask worker joined .* for 0.5 s"):
            jobs.run_job(job, executor)
        assert time.monotonic() - started < 10
        # the same bound holds while a job runs: a submitted task with no worker
        future = executor.submit(sum, [1, 2])
        with pytest.raises(NoWorkersError):
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                assert not executor.wait_any([future], timeout=0.2)
    finally:
        executor.shutdown()


@pytest.mark.skipif(
    shutil.which("unshare") is None
    or subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode != 0,
    reason="needs user and mount namespaces to give a worker its own view of the disk",
)
def test_preflight_names_the_worker_without_the_data_directory(tmp_path: Path, scheduler) -> None:
    """A `terrasift worker` process sees the job directory; a second one, in a mount
    namespace with an empty tmpfs over it (a machine without the shared volume),
    does not, and the pre-flight names that worker."""
    data = tmp_path / "data"
    job_dir = data / "jobs" / "j1"
    job_dir.mkdir(parents=True)
    # both start at once (a worker process takes seconds to start on a busy machine)
    good = _start_worker(scheduler, nworkers=2)  # two worker processes under nannies
    mount = f'mount -t tmpfs tmpfs "{data}" && exec "$0" "$@"'
    bad = _start_worker(scheduler, "unshare", "-rm", "sh", "-c", mount)
    executor = DaskExecutor(scheduler, no_workers_timeout=30)
    try:
        everyone = set(_wait_workers(executor._client, 3))
        # every address, and every socket the good workers listen on (tasks,
        # nannies, Dask's health/metrics HTTP), is loopback by default
        assert all(a.startswith("tcp://127.0.0.1:") for a in everyone)
        procs = [psutil.Process(good.pid), *psutil.Process(good.pid).children(recursive=True)]
        listening = [
            c.laddr.ip
            for p in procs
            for c in p.net_connections(kind="inet")
            if c.status == psutil.CONN_LISTEN
        ]
        assert listening and set(listening) == {"127.0.0.1"}

        with pytest.raises(DataDirError) as err:
            executor.preflight(job_dir)
        message = str(err.value)
        named = [a for a in everyone if f"worker {a}: cannot read" in message]
        assert len(named) == 1 and str(data) in message
        assert sum(f"worker {a}" in message for a in everyone) == 1

        _stop(bad)  # the worker without the shared directory leaves
        deadline = time.monotonic() + 30
        while len(executor._client.scheduler_info(n_workers=-1)["workers"]) > 2:
            assert time.monotonic() < deadline
            time.sleep(0.1)
        executor.preflight(job_dir)  # the shared view passes
        assert executor.workers == 2
        assert not (job_dir / "worker-probes").exists()  # the probe cleans up
    finally:
        executor.shutdown()
        for proc in (good, bad):
            _stop(proc)


def test_service_job_fails_with_the_no_workers_message(
    tmp_path: Path, small_tile, scheduler, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Through the API: the job ends `failed` with the reason, not as an internal error;
    a relative data directory reaches the job as an absolute path."""
    from fastapi.testclient import TestClient

    from terrasift.service.app import create_app
    from terrasift.service.settings import Settings

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("TERRASIFT_DASK_NO_WORKERS_TIMEOUT", "0.5")
    settings = Settings(_env_file=None, data_dir=Path("data"), dask_scheduler=scheduler)
    assert settings.dask_no_workers_timeout == 0.5
    assert settings.data_dir == tmp_path / "data"
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        posted = client.post("/jobs", files=[("file", ("t.laz", small_tile.read_bytes()))])
        assert posted.status_code == 201, posted.text
        job_id = posted.json()["jobID"]
        deadline = time.monotonic() + 60
        while (info := client.get(f"/jobs/{job_id}").json())["status"] in ("accepted", "running"):
            assert time.monotonic() < deadline
            time.sleep(0.2)
    assert info["status"] == "failed"
    assert "no Dask worker joined" in info["message"] and "0.5 s" in info["message"]


def test_compose_topology_as_processes_runs_a_survey(tmp_path: Path, small_scene) -> None:
    """docker-compose.yml's topology as separate processes on loopback: a Dask
    scheduler, two `terrasift worker`s and `terrasift serve` with a relative data
    directory (the workers run elsewhere, so it must reach them absolute); the
    survey CLI's product gives the same labels as the same survey run in-process."""
    import laspy
    import numpy as np

    from terrasift.synthetic.terrain import Scene, write_las
    from terrasift.workers.executors import InlineExecutor

    tiles = tmp_path / "tiles"
    tiles.mkdir()
    mid = (small_scene.bounds[0] + small_scene.bounds[2]) / 2
    for i, sel in enumerate([small_scene.xyz[:, 0] < mid, small_scene.xyz[:, 0] >= mid]):
        part = Scene(
            small_scene.xyz[sel],
            small_scene.truth[sel],
            small_scene.return_number[sel],
            small_scene.number_of_returns[sel],
            small_scene.surface,
            small_scene.bounds,
        )
        write_las(part, tiles / f"part{i}.laz", extra_bytes=True)
    params = {"block_size": 80, "buffer": 15}

    sched_port, api_port = _free_port(), _free_port()
    address = f"tcp://127.0.0.1:{sched_port}"
    (tmp_path / "api").mkdir()
    (tmp_path / "w").mkdir()
    env = {
        **os.environ,
        "TERRASIFT_DATA_DIR": "data",  # relative to the API's folder
        "TERRASIFT_DASK_SCHEDULER": address,
        "TERRASIFT_DASK_NO_WORKERS_TIMEOUT": "60",
    }
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1"]
            + ["--port", str(sched_port), "--no-dashboard"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    ]
    try:
        for _ in range(2):
            procs.append(
                subprocess.Popen(
                    [*TERRASIFT, "worker", "--nthreads", "1"],  # scheduler from the environment
                    cwd=tmp_path / "w",
                    env=env,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        procs.append(
            subprocess.Popen(
                [*TERRASIFT, "serve", "--port", str(api_port)],
                cwd=tmp_path / "api",
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        )
        with distributed.Client(address, set_as_default=False, timeout=60) as client:
            _wait_workers(client, 2)
        server = f"http://127.0.0.1:{api_port}"
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{server}/", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "the API did not start"
            time.sleep(0.2)
        from terrasift.survey import run_survey

        assert run_survey(tiles, server, params, poll=0.2) == 0
    finally:
        for proc in reversed(procs):
            _stop(proc)
    out = tiles / "terrasift-out"
    assert (out / "dtm.vrt").exists() and (out / "collection.json").exists()

    # the same survey run in-process: the same labels per tile
    from terrasift.jobs.survey import current_version, plan_survey_run

    job = tmp_path / "inline"
    plan_survey_run(
        job, tmp_path / "inline-survey", sorted(tiles.glob("*.laz")), jobs.validate_params(params)
    )
    jobs.run_job(job, InlineExecutor())
    version = current_version(tmp_path / "inline-survey")
    assert version is not None
    for i in range(2):
        name = f"tiles/part{i}/classified.laz"
        got = np.asarray(laspy.read(out / name).classification)
        want = np.asarray(laspy.read(version / name).classification)
        assert np.array_equal(got, want)
