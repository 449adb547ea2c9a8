"""How a survey run scales with its number of tiles, on a local Dask cluster.

Builds synthetic surveys of ``--tiles`` adjacent tiles (default 16 and 64) of
``--points`` pulses each (about 10 % more returns; one continuous terrain, each
tile with its own buildings and trees), and runs one full survey run of each
(``plan_survey_run`` + ``run_job`` on a ``DaskExecutor``) on one cluster of
separate processes started as a deployment would: ``dask scheduler`` and
``--workers`` ``terrasift worker`` processes of one thread. Prints per survey:
wall time; CPU of the driver (this process, less the thread that polls memory),
of the scheduler and of the workers (with the task processes they start); the
peak RSS of the largest single process of each (driver, scheduler, each worker
tree); the peak RSS of each kind of task (the largest over its tasks, each
task's own high-water mark: ``TERRASIFT_TASK_PEAKS`` in the workers'
environment) with the task that reached it and its growth over the RSS its
process held when it started; the disk used at the end by the survey
(product) and its run folder against the input LAZ. Then the wall-time and
workers' CPU ratios of the largest survey to the smallest against the ratio of
their tiles (linear: equal), and the ratio of each process's and each task
kind's peak RSS.

    .venv/bin/python benchmarks/survey_scale.py [--tiles 16 64] [--points 500000] [--density 10]
        [--workers 2] [--no-waves] [--json F]

``--density`` lower with ``--points`` keeps the survey's width (tile side
``sqrt(points / density)``) at a fraction of the points, to see what grows with
the width; the DTM's cell follows the density.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import psutil  # noqa: E402


class PeakRss:
    """Polls, in a thread, the RSS of every process of a few process trees; keeps the
    peak of the largest single process of each tree and the thread's own CPU time
    (it runs in the driver's process, so it is taken off the driver's CPU)."""

    def __init__(
        self, pids: dict[str, int], every: float = 0.2, alone: tuple[str, ...] = ()
    ) -> None:
        self.alone = alone
        self.pids = pids
        self.peak: dict[str, int] = {k: 0 for k in pids}
        self.own_cpu = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self.every = every

    def __enter__(self) -> PeakRss:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.is_set():
            for name, pid in self.pids.items():
                try:
                    p = psutil.Process(pid)
                    procs = [p] if name in self.alone else [p, *p.children(recursive=True)]
                except psutil.Error:
                    continue
                for q in procs:
                    with suppress(psutil.Error):
                        self.peak[name] = max(self.peak[name], q.memory_info().rss)
            self.own_cpu = time.thread_time()
            self._stop.wait(self.every)


def _cpu(pid: int) -> float:
    """User + system CPU of a process tree: every living process and the children each reaped."""
    total = 0.0
    p = psutil.Process(pid)
    for q in [p, *p.children(recursive=True)]:
        with suppress(psutil.Error):
            t = q.cpu_times()
            total += t.user + t.system + t.children_user + t.children_system
    return total


def _du(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


class _Shifted:
    """A survey-wide surface seen from one tile: ``make_scene`` evaluates its surface
    on the tile's local coordinates, so the tile's offset is added back."""

    def __init__(self, surface: Any, dx: float, dy: float) -> None:
        self.surface, self.dx, self.dy = surface, dx, dy

    def __call__(self, x: Any, y: Any) -> Any:
        return self.surface(np.asarray(x) + self.dx, np.asarray(y) + self.dy)


def make_survey(
    folder: Path, tiles: int, points: int, density: float, waves: bool = True
) -> list[Path]:
    """``tiles`` adjacent square tiles of ``points`` pulses on one continuous terrain
    whose content is the same per tile whatever the survey's size: the default slope
    and waves (``waves``: their ridges and valleys run across the whole survey), a 6 m
    hill on the shared corner of every 2 x 2 tiles, 4 buildings and trees per tile."""
    from terrasift.synthetic.terrain import Surface, make_scene, write_las

    folder.mkdir(parents=True, exist_ok=True)
    side = int(round(math.sqrt(tiles)))
    size = math.sqrt(points / density)
    hills = tuple(
        ((2 * a + 1) * size, (2 * b + 1) * size, 6.0, 0.4 * size)
        for a in range(max(1, side // 2))
        for b in range(max(1, side // 2))
    )
    surface = Surface(hills=hills) if waves else Surface(waves=(), hills=hills)
    out = []
    for j in range(side):
        for i in range(side):
            scene = make_scene(
                size,
                density,
                origin=(500_000.0 + i * size, 5_400_000.0 + j * size),
                surface=_Shifted(surface, i * size, j * size),  # type: ignore[arg-type]
                n_buildings=4,
                seed=1000 * j + i,
            )
            out.append(write_las(scene, folder / f"t_{i:02d}_{j:02d}.laz"))
    return out


def task_peaks(folder: Path) -> dict[str, dict[str, Any]]:
    """Per task kind (function), from the workers' records in ``folder`` (removed after
    reading): tasks, the largest peak RSS with its task and its growth over the RSS
    its process started it with, the largest growth, and the median peak."""
    rows = []
    for f in folder.glob("*.jsonl"):
        rows += [json.loads(line) for line in f.read_text().splitlines() if line.strip()]
        f.unlink()
    kinds: dict[str, dict[str, Any]] = {}
    for fn in sorted({r["fn"] for r in rows}):
        mine = [r for r in rows if r["fn"] == fn]
        top = max(mine, key=lambda r: r["peak_rss"])
        kinds[fn] = {
            "tasks": len(mine),
            "peak_rss_mib": top["peak_rss"] / 2**20,
            "peak_task": top["task"],
            "peak_growth_mib": (top["peak_rss"] - top["rss_start"]) / 2**20,
            "max_growth_mib": max(r["peak_rss"] - r["rss_start"] for r in mine) / 2**20,
            "median_peak_mib": float(np.median([r["peak_rss"] for r in mine])) / 2**20,
            "cpu_s": sum(r["cpu_s"] for r in mine),
        }
    return kinds


def run_one(
    root: Path, tiles: list[Path], scheduler: str, pids: dict[str, int], peaks: Path
) -> dict:
    """One full survey run of ``tiles`` on the cluster; its figures."""
    from terrasift.jobs import run_job, validate_params
    from terrasift.jobs.survey import plan_survey_run
    from terrasift.workers.executors import DaskExecutor

    params = validate_params({"crs": "EPSG:32632"})
    sdir, job = root / "survey", root / "run"
    others = {k: v for k, v in pids.items() if k != "scheduler"}
    before = {k: _cpu(pid) for k, pid in pids.items()}
    executor = DaskExecutor(scheduler)
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    with PeakRss({"driver": os.getpid(), **pids}, alone=("driver",)) as rss:
        plan_survey_run(job, sdir, tiles, params, mode="full")
        plan_cpu = time.process_time() - t_cpu
        run_job(job, executor)
        wall = time.perf_counter() - t_wall
        driver_cpu = time.process_time() - t_cpu
    driver_cpu -= rss.own_cpu  # the RSS poller runs in this process: not the driver's work
    executor.shutdown()
    cpu = {k: _cpu(pid) - before[k] for k, pid in pids.items()}
    worker_cpu = sum(v for k, v in cpu.items() if k in others)
    laz = sum(p.stat().st_size for p in tiles)
    total_cpu = driver_cpu + worker_cpu + cpu["scheduler"]
    return {
        "tiles": len(tiles),
        "points": sum(_points(p) for p in tiles),
        "wall_s": wall,
        "driver_cpu_s": driver_cpu,
        "driver_plan_cpu_s": plan_cpu,
        "scheduler_cpu_s": cpu["scheduler"],
        "worker_cpu_s": worker_cpu,
        "driver_share": driver_cpu / max(total_cpu, 1e-9),
        "driver_scheduler_share": (driver_cpu + cpu["scheduler"]) / max(total_cpu, 1e-9),
        "peak_rss_mib": {k: v / 2**20 for k, v in rss.peak.items()},
        "peak_rss_worker_mib": max(v for k, v in rss.peak.items() if k in others) / 2**20,
        "input_laz_bytes": laz,
        "disk_bytes": _du(sdir) + _du(job),
        "product_bytes": _du(sdir),
        "disk_over_input": (_du(sdir) + _du(job)) / laz,
        "tasks": task_peaks(peaks),
        "squares": _squares(sdir),
    }


def _squares(survey: Path) -> dict[str, Any]:
    """The feature squares of the survey's current version: how many, their side, and
    the largest window a square's search read (cells, and as a share of the mosaic)."""
    from terrasift.jobs.survey import current_state

    state = current_state(survey) or {}
    sq = state.get("squares") or {}
    windows = list((sq.get("windows") or {}).values())
    if not windows:
        return {}
    e = sq["extent"]
    area = (e[2] - e[0]) * (e[3] - e[1])
    import pickle

    from terrasift.jobs.survey import SQUARES, current_version

    version = current_version(survey)
    cut = 0
    for f in (version / SQUARES).glob("*.pkl") if version is not None else []:
        cut += sum(
            getattr(p, "cut", None) is not None for p in pickle.loads(f.read_bytes())["pieces"]
        )
    largest = max(windows, key=lambda w: (w[2] - w[0]) * (w[3] - w[1]))
    return {
        "squares": len(windows),
        "side_cells": sq["side"],
        "mosaic_cells": [e[2] - e[0], e[3] - e[1]],
        "largest_window_cells": [largest[2] - largest[0], largest[3] - largest[1]],
        "largest_window_share": (largest[2] - largest[0]) * (largest[3] - largest[1]) / area,
        "cut_pieces": cut,
    }


@contextmanager
def _cluster(
    workers: int, peaks: Path, cap: str | None = None
) -> Iterator[tuple[str, dict[str, int]]]:
    """A Dask scheduler and ``workers`` one-thread ``terrasift worker`` processes,
    each a process of its own as in a deployment, whose tasks record their peak RSS
    in ``peaks`` (and search feature squares with ``cap``: metres or ``none``, else
    the default); yields the address and the process ids (scheduler, worker0 ...)."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    exe = Path(sys.executable).parent
    env = {**os.environ, "TERRASIFT_TASK_PEAKS": str(peaks)}
    if cap is not None:
        env["TERRASIFT_FEATURE_CAP_M"] = cap
    procs = [
        subprocess.Popen(
            [str(exe / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port),
             "--dashboard-address", ":0"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
    ]  # fmt: skip
    try:
        time.sleep(3)
        for _ in range(workers):
            procs.append(
                subprocess.Popen(
                    [str(exe / "terrasift"), "worker", address, "--nthreads", "1"],
                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
                )
            )  # fmt: skip
        from distributed import Client

        with Client(address, set_as_default=False) as client:
            client.wait_for_workers(workers, timeout=120)
        yield (
            address,
            {
                "scheduler": procs[0].pid,
                **{f"worker{k}": p.pid for k, p in enumerate(procs[1:])},
            },
        )
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _points(path: Path) -> int:
    import laspy

    with laspy.open(str(path)) as f:
        return int(f.header.point_count)


def _run_caps(args: argparse.Namespace, cap: str | None) -> list[dict]:
    """One cluster (feature squares' ``cap``) running a survey of each ``--tiles``."""
    rows = []
    peak_dir = Path(tempfile.mkdtemp(prefix="task-peaks-"))
    with _cluster(args.workers, peak_dir, cap) as (address, pids):
        for n in args.tiles:
            root = Path(tempfile.mkdtemp(prefix=f"survey{n}-", dir=args.keep))
            try:
                tiles = make_survey(root / "tiles", n, args.points, args.density, not args.no_waves)
                task_peaks(peak_dir)  # nothing of the survey's making
                row = run_one(root, tiles, address, pids, peak_dir)
            finally:
                if args.keep is None:
                    shutil.rmtree(root, ignore_errors=True)
            rows.append(row)
            peaks = ", ".join(f"{k} {v:.0f}" for k, v in row["peak_rss_mib"].items())
            print(
                f"{row['tiles']:>3} tiles, {row['points'] / 1e6:.1f} M points: wall {row['wall_s']:.0f} s; "
                f"CPU driver {row['driver_cpu_s']:.1f} s (plan {row['driver_plan_cpu_s']:.1f} s), "
                f"scheduler {row['scheduler_cpu_s']:.1f} s, workers {row['worker_cpu_s']:.0f} s: "
                f"driver {100 * row['driver_share']:.2f} % of all CPU "
                f"(with the scheduler {100 * row['driver_scheduler_share']:.2f} %); "
                f"peak RSS of one process (MiB): {peaks}; "
                f"disk {row['disk_bytes'] / 2**20:.0f} MiB = {row['disk_over_input']:.2f}x the input LAZ "
                f"({row['input_laz_bytes'] / 2**20:.0f} MiB)",
                flush=True,
            )
            for kind, t in row["tasks"].items():
                print(
                    f"    {kind:<22} {t['tasks']:>4} tasks: peak RSS {t['peak_rss_mib']:.0f} MiB "
                    f"({t['peak_task']}, +{t['peak_growth_mib']:.0f} MiB over its start), "
                    f"median {t['median_peak_mib']:.0f}, largest growth {t['max_growth_mib']:.0f} MiB; "
                    f"CPU {t['cpu_s']:.0f} s",
                    flush=True,
                )
            if row["squares"]:
                q = row["squares"]
                print(
                    f"    feature squares: {q['squares']} of {q['side_cells']} cells on a "
                    f"{q['mosaic_cells'][0]} x {q['mosaic_cells'][1]} mosaic; largest window "
                    f"searched {q['largest_window_cells'][0]} x {q['largest_window_cells'][1]} "
                    f"({100 * q['largest_window_share']:.0f} % of the mosaic); "
                    f"{q['cut_pieces']} pieces of objects searched in parts",
                    flush=True,
                )
    shutil.rmtree(peak_dir, ignore_errors=True)
    return rows


def _print_ratios(rows: list[dict]) -> None:
    """The largest survey's figures against the smallest's."""
    if len(rows) < 2:
        return
    a, b = rows[0], rows[-1]
    ratios = ", ".join(
        f"{k} {b['peak_rss_mib'][k] / max(a['peak_rss_mib'][k], 1e-9):.2f}"
        for k in a["peak_rss_mib"]
    )
    print(
        f"{b['tiles']}/{a['tiles']} tiles: wall-time ratio {b['wall_s'] / a['wall_s']:.2f} "
        f"(linear: {b['tiles'] / a['tiles']:.2f}), workers' CPU ratio "
        f"{b['worker_cpu_s'] / max(a['worker_cpu_s'], 1e-9):.2f}; "
        f"peak RSS ratio per process: {ratios}"
    )
    kinds = ", ".join(
        f"{k} {b['tasks'][k]['peak_rss_mib'] / max(a['tasks'][k]['peak_rss_mib'], 1e-9):.2f}"
        for k in a["tasks"]
        if k in b["tasks"]
    )
    growth = ", ".join(
        f"{k} {a['tasks'][k]['max_growth_mib']:.0f} -> {b['tasks'][k]['max_growth_mib']:.0f}"
        for k in a["tasks"]
        if k in b["tasks"]
    )
    print(f"peak RSS ratio per task kind: {kinds}")
    print(
        "largest growth of a task over the RSS its process held when it started (MiB; "
        f"a process keeps what earlier tasks left, so peaks carry it): {growth}"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tiles", type=int, nargs="+", default=[16, 64])
    ap.add_argument(
        "--points", type=int, default=500_000, help="pulses per tile (returns: ~10 %% more)"
    )
    ap.add_argument("--density", type=float, default=10.0, help="pulses per m²")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--no-waves",
        action="store_true",
        help="terrain without the long waves (objects of bounded size: the feature "
        "squares' windows need not grow across the survey)",
    )
    ap.add_argument(
        "--feature-cap",
        nargs="+",
        default=[None],
        help="metres a feature square's window may grow beyond its halo, or none "
        "(TERRASIFT_FEATURE_CAP_M); several: each on a cluster of its own, in turn",
    )
    ap.add_argument("--keep", type=Path, help="keep the surveys under this folder")
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args()

    every: list[dict] = []
    for cap in args.feature_cap:
        if cap is not None:
            print(f"feature squares' cap: {cap}", flush=True)
        rows = _run_caps(args, cap)
        for row in rows:
            row["feature_cap"] = cap
        every += rows
        _print_ratios(rows)
    if len(args.feature_cap) > 1:
        for n in args.tiles:
            mine = [r for r in every if r["tiles"] == n]
            print(
                f"{n} tiles, per cap: "
                + "; ".join(
                    f"{r['feature_cap']}: workers' peak {r['peak_rss_worker_mib']:.0f} MiB, "
                    f"search_feature_square peak "
                    f"{r['tasks'].get('search_feature_square', {}).get('peak_rss_mib', 0):.0f} MiB, "
                    f"largest window {100 * r['squares'].get('largest_window_share', 0):.0f} %"
                    for r in mine
                )
            )
    rows = every
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
