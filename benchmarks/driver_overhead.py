"""CPU the job driver spends per task, to show it stays linear in the number of tasks.

Runs the driver's task loop (``jobs.run._run_mixed_tasks``) over 1 k, 4 k and
16 k tasks of 2 ms each on a pool of two threads, and prints the process CPU
(driver plus the pool's own bookkeeping) for each and the 16 k / 1 k ratio:
16 is linear. The tasks sleep, so the CPU measured is the driver's and the
pool's, not the tasks'.

    python benchmarks/driver_overhead.py
"""

from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


class ThreadPool:
    """The executor interface the driver uses, on threads."""

    workers = 2

    def __init__(self) -> None:
        self.pool = ThreadPoolExecutor(self.workers)

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        return self.pool.submit(fn, *args)

    def wait_any(self, futures: Iterable[Future], timeout: float) -> set[Future]:
        done, _ = wait(list(futures), timeout=timeout, return_when=FIRST_COMPLETED)
        return set(done)

    def shutdown(self) -> None:
        self.pool.shutdown()


def _task(_: int) -> None:
    time.sleep(0.002)


def main() -> int:
    from terrasift.jobs.run import Task, _run_mixed_tasks

    cpu = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in (1000, 4000, 16000):
            pool = ThreadPool()
            t = time.process_time()
            _run_mixed_tasks(
                pool, Path(tmp), [Task(_task, (i,)) for i in range(n)], lambda i, r: None
            )
            cpu[n] = time.process_time() - t
            pool.shutdown()
            print(f"{n:>6} tasks: {cpu[n]:.2f} s CPU, {1e3 * cpu[n] / n:.3f} ms per task")
    print(f"16 k / 1 k CPU ratio: {cpu[16000] / cpu[1000]:.1f} (16 is linear)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
