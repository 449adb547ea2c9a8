"""Stage costs for the progress meter, and the progress trace of a whole job (``make bench-progress``).

``costs``: runs a job in this process and times every task, then prints the
seconds per million job points of each kind of task, the numbers
``terrasift.progress.COST`` holds. ``trace``: runs a job on a process pool and
prints the reported percentage against elapsed time, with the largest gap to
a straight line from 0 to 100 over the job's duration.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from terrasift.workers.executors import single_threaded_blas  # noqa: E402

single_threaded_blas()

from terrasift import jobs as pipeline  # noqa: E402
from terrasift.synthetic.terrain import make_scene, write_las  # noqa: E402
from terrasift.workers.executors import InlineExecutor, make_executor  # noqa: E402

KINDS = {
    "shard_tile": "shard",
    "run_block": "block",
    "write_classified": "classified",
    "write_raster": "raster",
    "write_slope": "slope",
    "write_categories": "categories",
    "write_quicklooks": "quicklooks",
}


class TimingExecutor(InlineExecutor):
    """Runs tasks at submission, in this process, and sums their CPU seconds per kind
    (CPU time: the machine may be shared, and a worker's task is CPU-bound)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.count: dict[str, int] = defaultdict(int)

    def submit(self, fn: Any, *args: Any) -> Any:
        t = time.process_time()
        fut = super().submit(fn, *args)
        kind = KINDS.get(fn.__name__, fn.__name__)
        self.seconds[kind] += time.process_time() - t
        self.count[kind] += 1
        return fut


def make_tile(folder: Path, size: float, density: float) -> tuple[Path, int]:
    scene = make_scene(size=size, density=density, seed=11, n_buildings=int(size * size / 12_000))
    return write_las(scene, folder / f"tile-{size:g}-{density:g}.laz"), len(scene)


def new_job(folder: Path, tile: Path, params: dict[str, Any]) -> Path:
    job = folder / f"job-{time.monotonic_ns()}"
    pipeline.prepare_job(job, [tile], pipeline.validate_params(params))
    return job


def costs(folder: Path, tile: Path, points: int, params: dict[str, Any], runs: int) -> None:
    per_kind: dict[str, list[float]] = defaultdict(list)
    report = 0.0
    for _ in range(runs):
        ex = TimingExecutor()
        job = new_job(folder, tile, params)
        t = time.process_time()
        pipeline.run_job(job, ex)
        total = time.process_time() - t
        for kind, s in ex.seconds.items():
            # rasters: one task per raster, cost per task
            per = s / ex.count[kind] if kind == "raster" else s
            per_kind[kind].append(per / points * 1e6)
        report = total - sum(ex.seconds.values())
        per_kind["report"].append(report / points * 1e6)
    print(f"CPU seconds per million points, one process, medians of {runs} ({points:,} points):")
    for kind, values in per_kind.items():
        print(f"    {kind!r}: {statistics.median(values):.3f},")


def trace(folder: Path, tile: Path, points: int, params: dict[str, Any], workers: int) -> None:
    job = new_job(folder, tile, params)
    samples: list[tuple[float, float, str]] = []
    start = time.perf_counter()

    def progress(done: int, total: int, info: Any) -> None:
        samples.append((time.perf_counter() - start, 100 * done / total, info["message"]))

    ex = make_executor(workers)
    try:
        pipeline.run_job(job, ex, progress)
        duration = time.perf_counter() - start
    finally:
        ex.shutdown()
    gaps = [pct - 100 * t / duration for t, pct, _ in samples]
    worst = max(gaps, key=abs)
    print(f"{points:,} points on {workers} workers: {duration:.1f} s, {len(samples)} reports")
    print("elapsed %  reported %  message")
    marks = iter(range(0, 101, 5))
    mark = next(marks)
    for t, pct, msg in samples:
        if 100 * t / duration >= mark:
            print(f"{100 * t / duration:9.0f}  {pct:10.1f}  {msg}")
            while mark <= 100 * t / duration:
                mark = next(marks, 101)
    print(
        f"largest gap to the straight line: {worst:+.1f} points; "
        f"median |gap| {statistics.median(abs(g) for g in gaps):.1f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["costs", "trace", "both"], nargs="?", default="both")
    ap.add_argument("--size", type=float, default=400.0, help="scene edge in metres")
    ap.add_argument("--density", type=float, default=12.0, help="pulses per m²")
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="folder kept for the tile and jobs")
    args = ap.parse_args()
    params = {"block_size": 100, "resolution": 0.5}
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.out or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        tile, points = make_tile(folder, args.size, args.density)
        if args.what in ("costs", "both"):
            costs(folder, tile, points, params, args.runs)
        if args.what in ("trace", "both"):
            trace(folder, tile, points, params, args.workers)


if __name__ == "__main__":
    main()
