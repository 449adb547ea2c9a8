"""Disposable workers: a worker that dies, overruns or grows is replaced and only its task fails."""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import time
from concurrent.futures import CancelledError
from pathlib import Path

import pytest

from terrasift.errors import InputError, JobCancelled, ProcessingError
from terrasift.workers.pool import (
    TaskOutOfMemory,
    TaskTimeout,
    WorkerLost,
    WorkerPool,
    reap_leftovers,
)


def square(x: int) -> int:
    return x * x


def die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def abort() -> None:
    os.abort()


def sleep(seconds: float) -> float:
    time.sleep(seconds)
    return seconds


def spin() -> None:
    while True:
        pass


def grow() -> None:
    held = []
    while True:
        held.append(bytearray(20_000_000))
        time.sleep(0.02)


def hold(megabytes: int) -> int:
    """Touch ``megabytes`` MB, let them go; this process's pid."""
    block = bytearray(megabytes * 1_000_000)
    block[::4096] = b"x" * len(block[::4096])
    del block
    return os.getpid()


def priority() -> tuple[int, int, int, str | None]:
    """The worker's pid, session, nice value and scheduling group (autogroup) line."""
    group = Path("/proc/self/autogroup")
    return os.getpid(), os.getsid(0), os.nice(0), group.read_text() if group.exists() else None


def raises() -> None:
    raise ValueError("bad block")


class Panic(BaseException):
    """Like pyo3's PanicException: a BaseException whose class cannot be pickled."""

    def __reduce__(self):
        raise pickle.PicklingError("Can't pickle Panic: import of module 'pyo3_runtime' failed")


class Strict(Exception):
    """Pickles, but does not unpickle: its constructor wants two arguments."""

    def __init__(self, a: str, b: str):
        super().__init__(f"{a} {b}")


class StrictInput(InputError):
    def __init__(self, a: str, b: str):
        super().__init__(f"{a} {b}")


def panics(path: str) -> None:
    raise Panic("attempt to calculate the remainder with a divisor of zero")


def raises_strict(path: str, input_error: bool) -> None:
    raise (StrictInput if input_error else Strict)("bad", "bytes")


def unpicklable_result(path: str) -> object:
    return lambda: path


@pytest.fixture(scope="module")
def pool():
    p = WorkerPool(2, memory_limit=300_000_000)
    yield p
    p.shutdown()


def test_a_dying_worker_fails_only_its_task(pool: WorkerPool) -> None:
    before = pool.replaced
    for fn in (die, abort):
        with pytest.raises(WorkerLost, match=rf"{fn.__name__}\(\) died \(signal SIG"):
            pool.submit(fn).result(timeout=60)
    assert pool.replaced - before == 4  # each task was tried twice
    assert [f.result(timeout=60) for f in [pool.submit(square, i) for i in range(6)]] == [
        0,
        1,
        4,
        9,
        16,
        25,
    ]
    assert len(pool.worker_pids()) == 2


def test_an_exception_is_the_task_s_own(pool: WorkerPool) -> None:
    with pytest.raises(ValueError, match="bad block"):
        pool.submit(raises).result(timeout=60)


def test_an_exception_that_cannot_travel_fails_its_task_naming_it(pool: WorkerPool) -> None:
    pids = set(pool.worker_pids())
    with pytest.raises(ProcessingError, match=r"panics\(t\.laz\) failed: Panic: attempt to"):
        pool.submit(panics, "/data/t.laz").result(timeout=60)
    with pytest.raises(ProcessingError, match=r"raises_strict\(t\.laz\) failed: Strict: bad bytes"):
        pool.submit(raises_strict, "/data/t.laz", False).result(timeout=60)
    # an input error stays one, so the service answers it as the client's
    with pytest.raises(InputError, match=r"raises_strict\(t\.laz\) failed: StrictInput: bad"):
        pool.submit(raises_strict, "/data/t.laz", True).result(timeout=60)
    with pytest.raises(ProcessingError, match=r"unpicklable_result\(t\.laz\) finished, but"):
        pool.submit(unpicklable_result, "/data/t.laz").result(timeout=60)
    assert set(pool.worker_pids()) == pids  # no worker was lost or replaced
    assert pool.submit(square, 5).result(timeout=60) == 25


def test_time_limit_and_dismiss_stop_a_running_call(pool: WorkerPool) -> None:
    t = time.monotonic()
    with pytest.raises(TaskTimeout, match=r"spin\(\) ran longer than its limit of 1 s of CPU"):
        pool.submit(spin, timeout=1.0).result(timeout=30)
    assert time.monotonic() - t < 10
    # a task that waits instead of computing meets the wall-clock limit (4 x)
    with pytest.raises(TaskTimeout, match=r"sleep\(\) ran longer .* \(4 s in all\)"):
        pool.submit(sleep, 60, timeout=1.0).result(timeout=30)
    running = pool.submit(sleep, 60)
    queued = [pool.submit(sleep, 60) for _ in range(2)]
    while not pool.busy_pids():
        time.sleep(0.05)
    busy = set(pool.busy_pids())
    t = time.monotonic()
    assert pool.cancel([running, *queued]) == 3
    with pytest.raises(JobCancelled):
        running.result(timeout=10)
    assert time.monotonic() - t < 5
    for f in queued:  # one of them was running on the other worker
        with pytest.raises((JobCancelled, CancelledError)):
            f.result(timeout=5)
    assert pool.submit(square, 3).result(timeout=60) == 9
    assert not busy & set(pool.worker_pids())  # the workers that ran them are gone


def test_memory_limit_names_the_task(pool: WorkerPool) -> None:
    with pytest.raises(TaskOutOfMemory, match=r"grow\(\) needed more than the worker memory limit"):
        pool.submit(grow).result(timeout=60)
    assert pool.peak_rss < 300_000_000 + 200_000_000  # stopped within a few polls
    assert pool.submit(square, 4).result(timeout=60) == 16


@pytest.mark.skipif(sys.platform != "linux", reason="PR_SET_PDEATHSIG is Linux")
def test_workers_run_below_their_owner_in_a_group_of_their_own() -> None:
    # a nice value alone counts only inside the session's scheduling group: the workers
    # would use up the owner's group share and the API would wait for a CPU with them
    p = WorkerPool(1, nice=7)
    try:
        pid, session, nice, group = p.submit(priority).result(timeout=60)
    finally:
        p.shutdown()
    assert pid != os.getpid()
    assert session == pid != os.getsid(0)
    assert nice == min(19, os.nice(0) + 7)
    if group is not None:  # kernels with autogroup
        assert group.split()[-1] == "7"
        assert Path("/proc/self/autogroup").read_text() != group


def test_workers_without_nice_stay_in_the_owner_s_session(pool: WorkerPool) -> None:
    pid, session, nice, _ = pool.submit(priority).result(timeout=60)
    assert session == os.getsid(0) and nice == os.nice(0)


def test_workers_die_with_their_owner_and_leftovers_are_reaped(tmp_path: Path) -> None:
    pid_dir = tmp_path / "workers"
    code = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from terrasift.workers.pool import WorkerPool\n"
        f"p = WorkerPool(2, pid_dir=Path({str(pid_dir)!r}))\n"
        "while len(list(Path(p.pid_dir).iterdir())) < 2: time.sleep(0.05)\n"
        "print(' '.join(map(str, p.worker_pids())), flush=True)\n"
        "time.sleep(600)\n"
    )
    owner = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    pids = [int(p) for p in owner.stdout.readline().split()]
    assert len(pids) == 2
    owner.kill()
    owner.wait()
    end = time.monotonic() + 10
    while any(Path(f"/proc/{p}").exists() for p in pids) and time.monotonic() < end:
        time.sleep(0.05)
    assert not any(Path(f"/proc/{p}").exists() for p in pids)
    # their pid files stay behind; a restart reaps what they name (here: only a live stand-in)
    stand_in = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    stat = Path(f"/proc/{stand_in.pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    (pid_dir / str(stand_in.pid)).write_text(stat + "\n")
    (pid_dir / "999999999").write_text("1\n")
    assert reap_leftovers(pid_dir) == [stand_in.pid]
    assert stand_in.wait(timeout=10) == -signal.SIGKILL
    assert not list(pid_dir.iterdir())


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="Linux peak reset")
def test_each_task_records_its_own_peak_memory(tmp_path: Path, monkeypatch) -> None:
    """With TERRASIFT_TASK_PEAKS set, every task writes its own peak RSS: a large task
    followed by a small one in the same process, the small one's peak is its own."""
    import json

    monkeypatch.setenv("TERRASIFT_TASK_PEAKS", str(tmp_path))
    p = WorkerPool(1)
    try:
        big = p.submit(hold, 200).result(60)
        small = p.submit(hold, 5).result(60)
    finally:
        p.shutdown()
    assert big == small  # one process ran both
    rows = [json.loads(x) for x in (tmp_path / f"{big}.jsonl").read_text().splitlines()]
    assert [r["fn"] for r in rows] == ["hold", "hold"] and all(r["ok"] for r in rows)
    grown = [r["peak_rss"] - r["rss_start"] for r in rows]
    assert grown[0] >= 190 * 2**20 * 0.95
    assert grown[1] < 50 * 2**20
