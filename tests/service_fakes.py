"""A small pipeline with the real contract, for testing the service's own logic.

Its tasks sleep and write a marker file each, so tests can see exactly which
tasks ran (resume repeats only the missing ones) and hold a job in `running`
(an Event gates every task after the first ``free_tasks``). End-to-end tests use
the real pipeline; this one isolates scheduling, cancelling and HTTP behaviour.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from terrasift.errors import InputError, JobCancelled, ParameterError

MARKER = "CANCELLED"


class FakePipeline:
    def __init__(
        self, tasks: int = 4, free_tasks: int | None = None, fail: BaseException | None = None
    ):
        self.tasks = tasks
        self.free_tasks = tasks if free_tasks is None else free_tasks
        self.gate = threading.Event()
        self.abort: Callable[[], bool] = lambda: False
        self.fail = fail
        self.ran: list[tuple[str, int]] = []
        self._lock = threading.Lock()

    def validate_params(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        out = {"resolution": 0.5}
        for key, value in raw.items():
            if key != "resolution":
                raise ParameterError(f"unknown parameter {key!r}")
            if not isinstance(value, int | float) or not 0.05 <= value <= 100:
                raise ParameterError(
                    f"parameter resolution: must be a number in [0.05, 100], not {value!r}"
                )
            out[key] = value
        return out

    def inspect_inputs(self, paths: list[Path], params: Mapping[str, Any]) -> dict[str, Any]:
        for p in paths:
            with open(p, "rb") as fh:
                if fh.read(4) != b"LASF":
                    raise InputError(f"{p.name}: not a LAS/LAZ file (no LASF signature)")
        return {"points": sum(p.stat().st_size for p in paths), "tiles": len(paths)}

    def prepare_job(
        self,
        job_dir: Path,
        inputs: list[Path],
        params: Mapping[str, Any],
        outputs: list[str] | None = None,
    ) -> None:
        job = {"inputs": [str(p) for p in inputs], "params": dict(params)}
        if outputs is not None:
            job["outputs"] = outputs
        (job_dir / "job.json").write_text(json.dumps(job))

    def run_job(
        self, job_dir: Path, executor: Any, progress: Callable[[int, int], None] | None = None
    ) -> list[str]:
        if (job_dir / MARKER).exists():
            raise JobCancelled("dismissed")
        todo = [i for i in range(self.tasks) if not (job_dir / f"task{i}.done").exists()]
        done = self.tasks - len(todo)
        futures = [executor.submit(self._task, job_dir, i) for i in todo]
        for f in futures:
            f.result()
            done += 1
            if progress:
                progress(done, self.tasks)
        if self.fail is not None:
            raise self.fail
        out = job_dir / "outputs"
        out.mkdir(exist_ok=True)
        wanted = json.loads((job_dir / "job.json").read_text()).get("outputs")
        names = []
        if wanted is None or "dtm.tif" in wanted:
            (out / "dtm.tif").write_bytes(bytes(range(256)) * 40)
            names.append("dtm.tif")
        if wanted is None or "report.json" in wanted:
            (out / "report.json").write_text(json.dumps({"tasks": self.tasks}))
            names.append("report.json")
        return names

    def _task(self, job_dir: Path, i: int) -> None:
        if i >= self.free_tasks:
            while not self.gate.wait(0.02):
                if (job_dir / MARKER).exists():
                    raise JobCancelled("dismissed")
                if self.abort():
                    raise RuntimeError("worker went away")
        if (job_dir / MARKER).exists():
            raise JobCancelled("dismissed")
        time.sleep(0.01)
        with self._lock:
            self.ran.append((job_dir.name, i))
        (job_dir / f"task{i}.done").touch()

    def request_cancel(self, job_dir: Path) -> None:
        (job_dir / MARKER).touch()

    def output_path(self, job_dir: Path, name: str) -> Path:
        return job_dir / "outputs" / name


def thread_executor() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(2)


def las_bytes(n: int = 400) -> bytes:
    """Bytes that pass the fake's signature check."""
    return b"LASF" + bytes(n)


def wait_for(predicate: Callable[[], Any], timeout: float = 10.0) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError("condition not reached in time")


__all__ = ["FakePipeline", "las_bytes", "thread_executor", "wait_for"]
