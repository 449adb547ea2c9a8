"""Speed, memory and ground accuracy of the whole pipeline (``make bench``).

Writes a generated ~5 M point LAZ tile, then prints medians over ``--runs``
runs of points/s for reading, sharding, ground and DTM (one process), and the
whole job through ``terrasift process`` on 1 and 2 workers; peak RSS of a job
and of a job on a 4× larger tile; and ground accuracy on the ISPRS samples.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from terrasift.workers.executors import single_threaded_blas  # noqa: E402

single_threaded_blas()  # in-process stages run as in a worker: one BLAS thread

import numpy as np  # noqa: E402

from terrasift.synthetic.terrain import make_scene, write_las  # noqa: E402


def make_tile(path: Path, size: float, density: float, seed: int = 7) -> int:
    if not path.exists():
        scene = make_scene(
            size=size, density=density, seed=seed, n_buildings=int(size * size / 12_000)
        )
        write_las(scene, path)
        return len(scene)
    import laspy

    with laspy.open(str(path)) as r:
        return int(r.header.point_count)


def median_time(fn, runs: int) -> float:
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def stage_rates(tile: Path, n: int, runs: int, params: dict) -> dict[str, float]:
    """Points/s of read, shard, and ground + DTM over all blocks, in this process."""
    from terrasift import jobs
    from terrasift.jobs.block import run_block
    from terrasift.jobs.plan import plan_job
    from terrasift.tiling.blocks import BlockGrid, shard_parts, shard_tile
    from terrasift.tiling.lasfile import iter_chunks

    def read() -> None:
        for _ in iter_chunks(tile):
            pass

    out: dict[str, float] = {"read": n / median_time(read, runs)}
    work = Path(tempfile.mkdtemp(prefix="bench-stages-"))
    job = work / "job"
    validated = jobs.validate_params(params)
    jobs.prepare_job(job, [tile], validated)
    plan = plan_job(job, jobs.load_json(job / "job.json"))
    grid = BlockGrid(**plan["grid"])
    parts = shard_parts([n])

    def shard() -> None:
        for p in parts:
            shard_tile(str(tile), 0, grid, job / "shards" / p.name, start=p.start, stop=p.stop)

    out["shard"] = n / median_time(shard, runs)
    names = sorted({p.stem for p in (job / "shards").glob("*/*.bin")})
    ground, dtm = [], []
    for _ in range(runs):
        for p in (job / "blocks").glob("*"):
            p.unlink()
        stats = [run_block(str(job), name) for name in names]
        ground.append(sum(s["timings"]["ground"] for s in stats))
        dtm.append(sum(s["timings"]["dtm"] for s in stats))
    out["ground"] = n / statistics.median(ground)
    out["dtm"] = n / statistics.median(dtm)
    return out


def job_run(tile: Path, workers: int, params: dict) -> tuple[float, float]:
    """Seconds and peak RSS (MiB, largest process) of one ``terrasift process`` run."""
    out = Path(tempfile.mkdtemp(prefix="bench-job-"))
    args = [
        sys.executable,
        "-m",
        "terrasift",
        "process",
        str(tile),
        "--out",
        str(out),
        "--quiet",
        "--param",
        f"workers={workers}",
    ]
    args += [f"--param={k}={v}" for k, v in params.items()]
    code = (
        "import resource, subprocess, sys, time; t = time.perf_counter(); "
        "r = subprocess.run(sys.argv[1:]); dt = time.perf_counter() - t; "
        "print(dt, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(r.returncode)"
    )
    res = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=REPO
    )
    if res.returncode != 0:
        raise RuntimeError(res.stderr[-2000:])
    seconds, rss_kib = res.stdout.split()[-2:]
    return float(seconds), float(rss_kib) / 1024


def isprs_accuracy(params: dict) -> None:
    """Ground accuracy of whole jobs (blocks, halos and all) on the ISPRS samples."""
    import laspy

    from terrasift import jobs
    from terrasift.metrics import ground_score
    from terrasift.workers.executors import InlineExecutor

    folder = REPO.parent / "shared" / "data" / "isprs"
    files = sorted(folder.glob("*.laz"))
    if not files:
        print("ground accuracy: skipped, no ISPRS samples at ../shared/data/isprs")
        return
    print(f"{'ISPRS sample':<14}{'Type I %':>10}{'Type II %':>11}{'total %':>9}{'kappa %':>9}")
    rows = []
    for f in files:
        job = Path(tempfile.mkdtemp(prefix="bench-isprs-")) / "job"
        validated = jobs.validate_params({"crs": "EPSG:32632", **params})
        jobs.prepare_job(job, [f], validated)
        jobs.run_job(job, InlineExecutor(), products="classified")
        out = laspy.read(jobs.output_path(job, "classified.laz"))
        ref = laspy.read(f)
        s = ground_score(np.asarray(ref.classification) == 2, np.asarray(out.classification) == 2)
        rows.append(s)
        print(
            f"{f.stem:<14}{100 * s.type1:>10.2f}{100 * s.type2:>11.2f}{100 * s.total:>9.2f}{100 * s.kappa:>9.2f}"
        )
    mean = lambda k: 100 * float(np.mean([getattr(r, k) for r in rows]))  # noqa: E731
    print(
        f"{'mean':<14}{mean('type1'):>10.2f}{mean('type2'):>11.2f}{mean('total'):>9.2f}{mean('kappa'):>9.2f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--size", type=float, default=760.0, help="tile edge in metres")
    ap.add_argument("--density", type=float, default=8.0, help="pulses per m²")
    ap.add_argument("--out", type=Path, default=REPO / "bench-out")
    ap.add_argument("--skip-memory", action="store_true", help="skip the 4× tile memory run")
    ap.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    params = dict(p.split("=", 1) for p in args.param)
    args.out.mkdir(exist_ok=True)
    tile = args.out / f"bench-{int(args.size)}m.laz"
    t = time.perf_counter()
    n = make_tile(tile, args.size, args.density)
    print(
        f"tile: {tile.name}, {n:,} points, {tile.stat().st_size / 2**20:.0f} MiB ({time.perf_counter() - t:.0f} s to make)"
    )
    print(f"parameters: {params or 'defaults'}; medians over {args.runs} runs\n")

    rates = stage_rates(tile, n, args.runs, params)
    print(f"{'stage (one process)':<28}{'points/s':>14}")
    for k, v in rates.items():
        print(f"{k:<28}{v:>14,.0f}")

    print(f"\n{'whole job':<28}{'points/s':>14}{'seconds':>10}{'peak RSS MiB':>14}")
    job_rates = {}
    rss = {}
    for workers in (1, 2):
        runs = [job_run(tile, workers, params) for _ in range(args.runs)]
        secs = statistics.median(r[0] for r in runs)
        rss[workers] = max(r[1] for r in runs)
        job_rates[workers] = n / secs
        print(f"{f'{workers} worker(s)':<28}{n / secs:>14,.0f}{secs:>10.1f}{rss[workers]:>14.0f}")
    print(f"speed-up 2 vs 1 workers: {job_rates[2] / job_rates[1]:.2f}×")

    if not args.skip_memory:
        big = args.out / f"bench-{int(args.size * 2)}m.laz"
        nb = make_tile(big, args.size * 2, args.density, seed=8)
        secs, rss_big = job_run(big, 2, params)
        print(
            f"\n4× tile: {nb:,} points, {nb / secs:,.0f} points/s, peak RSS {rss_big:.0f} MiB "
            f"({100 * (rss_big / rss[2] - 1):+.0f} % against the 1× tile)"
        )

    print()
    isprs_accuracy(params)


if __name__ == "__main__":
    main()
