"""Command line: ``terrasift serve | process | classify | survey | path | worker``.

``process`` and ``classify`` run the same pipeline as the service, without a
server. Their working files live in ``OUT/.terrasift-work`` until the job
succeeds, so an interrupted run resumes where it stopped when called again.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from terrasift.errors import ParameterError, TerrasiftError
from terrasift.files import atomic_path
from terrasift.jobs.params import parse_cli_params

WORK_DIR = ".terrasift-work"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="terrasift", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("serve", help="run the HTTP API with embedded workers")
    p.add_argument("--host", default=None)
    p.add_argument("--port", type=int, default=None)

    p = sub.add_parser("process", help="process tiles into a folder of outputs")
    p.add_argument("inputs", nargs="+", type=Path)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    p = sub.add_parser("classify", help="write only the classified LAZ")
    p.add_argument("input", type=Path)
    p.add_argument("output", type=Path)
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--quiet", action="store_true")

    p = sub.add_parser(
        "survey",
        help="keep a server survey in step with a folder of tiles, run it, download the product",
    )
    p.add_argument("folder", type=Path)
    p.add_argument("--server", required=True)
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--token", default=None)
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="where the product goes (default: FOLDER/terrasift-out, if FOLDER is writable)",
    )
    p.add_argument(
        "--server-path",
        default=None,
        metavar="PATH",
        help="the folder as the server sees it under its input root: name tiles, do not upload",
    )

    p = sub.add_parser("path", help="pitch and roll along GeoJSON lines over a DTM")
    p.add_argument("dtm", type=Path, help="a DTM GeoTIFF, e.g. OUT/dtm.tif from `process`")
    p.add_argument(
        "line",
        type=Path,
        help="GeoJSON file: a LineString, a Feature or a FeatureCollection of them",
    )
    p.add_argument(
        "--crs",
        default=None,
        help="CRS of the line: the file's crs member or else WGS 84 if omitted, `native` for the DTM's",
    )
    p.add_argument("--spacing", type=float, default=1.0, help="metres between samples")
    p.add_argument("--format", choices=["csv", "json"], default="csv")

    p = sub.add_parser("worker", help="join a Dask cluster as a terrasift worker")
    p.add_argument(
        "scheduler",
        nargs="?",
        default=None,
        help="tcp://host:8786 (default: TERRASIFT_DASK_SCHEDULER)",
    )
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address the worker listens on and announces to the scheduler "
        "(default 127.0.0.1: loopback only; give the machine's address to join a remote scheduler)",
    )
    p.add_argument("--nthreads", type=_positive_int, default=1, help="task threads per worker")
    p.add_argument(
        "--nworkers", type=_positive_int, default=1, help="worker processes (each --nthreads)"
    )
    p.add_argument(
        "--dashboard",
        nargs="?",
        const=":0",
        default=None,
        metavar="[HOST]:PORT",
        help="serve the Dask worker dashboard (off unless given; default port: any free one)",
    )

    args = parser.parse_args(argv)
    try:
        if args.command == "serve":
            from terrasift.service.app import serve

            serve(host=args.host, port=args.port)
            return 0
        if args.command == "process":
            names = process(
                args.inputs, args.out, parse_cli_params(args.param), progress=not args.quiet
            )
            print("\n".join(str(args.out / n) for n in names))
            print_summary(args.out / "report.json")
            return 0
        if args.command == "classify":
            classify(args.input, args.output, parse_cli_params(args.param), progress=not args.quiet)
            return 0
        if args.command == "survey":
            from terrasift.survey import run_survey

            return run_survey(
                args.folder,
                args.server,
                parse_cli_params(args.param),
                token=args.token,
                out=args.out,
                server_path=args.server_path,
            )
        if args.command == "path":
            import json

            from terrasift.jobs import dtm_path_profile

            try:
                geometry = json.loads(args.line.read_text())
            except (OSError, ValueError) as exc:
                raise ParameterError(f"{args.line}: not a readable GeoJSON file ({exc})") from None
            profile = dtm_path_profile(args.dtm, geometry, crs=args.crs, spacing=args.spacing)
            if args.format == "csv":
                sys.stdout.write(profile.to_csv())
            else:
                # x, y are in the DTM's CRS, which the answer names
                print(json.dumps({"crs": profile.crs, "samples": profile.to_records()}))
            return 0
        if args.command == "worker":
            return run_worker(
                args.scheduler,
                args.nthreads,
                host=args.host,
                nworkers=args.nworkers,
                dashboard=args.dashboard,
            )
    except TerrasiftError as exc:
        print(f"terrasift: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return 1


def process(
    inputs: list[Path], out: Path, raw_params: dict, *, progress: bool = True, products: str = "all"
) -> list[str]:
    """Run the pipeline on ``inputs`` into folder ``out``; return the output names."""
    from terrasift.workers.executors import make_executor, single_threaded_blas

    single_threaded_blas()  # before numpy loads: forked workers inherit its BLAS set-up
    from terrasift import jobs

    params = jobs.validate_params(raw_params)
    jobs.inspect_inputs(list(inputs), params)
    out.mkdir(parents=True, exist_ok=True)
    work = out / WORK_DIR
    job_file = work / "job.json"
    if job_file.exists():
        previous = jobs.load_json(job_file)
        if previous["inputs"] != [str(p.resolve()) for p in inputs] or previous["params"] != params:
            shutil.rmtree(work)  # different job: start over
    if not job_file.exists():
        jobs.prepare_job(work, list(inputs), params)
    executor = make_executor(params.get("workers"))
    bar = _progress_bar() if progress else None
    try:
        names = jobs.run_job(work, executor, bar.update if bar else None, products=products)
    finally:
        executor.shutdown()
        if bar:
            bar.close()
    for name in names:
        shutil.move(str(jobs.output_path(work, name)), out / name)
    shutil.rmtree(work)
    return names


def classify(src: Path, dst: Path, raw_params: dict, *, progress: bool = True) -> None:
    """Write ``src`` with the job's classes to ``dst``: LAS for ``.las``, LAZ otherwise."""
    out = dst.parent / f".{dst.name}.terrasift"
    names = process([src], out, raw_params, progress=progress, products="classified")
    print_summary(out / "report.json")
    if dst.suffix.lower() == ".las":
        _decompress(out / "classified.laz", dst)
    else:
        shutil.move(str(out / "classified.laz"), dst)
    for n in names:
        (out / n).unlink(missing_ok=True)
    shutil.rmtree(out, ignore_errors=True)


def _decompress(src: Path, dst: Path, chunk_size: int = 1_000_000) -> None:
    """Copy LAZ ``src`` to an uncompressed LAS at ``dst`` (atomically), chunk by chunk."""
    import laspy

    reader = laspy.open(str(src))
    with (
        atomic_path(dst) as tmp,
        reader,
        laspy.open(
            str(tmp),
            mode="w",
            header=reader.header,
            do_compress=False,
            encoding_errors="replace",  # text fields copied as they are, ASCII or not
        ) as writer,
    ):
        for pts in reader.chunk_iterator(chunk_size):
            writer.write_points(pts)


def print_summary(report_path: Path) -> None:
    """Warnings first (to stderr), then one summary line of the job (to stderr as well)."""
    import json

    try:
        report = json.loads(report_path.read_text())
    except (OSError, ValueError):
        return
    for warning in report.get("warnings", []):
        print(f"terrasift: warning: {warning}", file=sys.stderr)
    counts = report.get("counts_per_class", {})
    classes = ", ".join(f"class {c}: {n}" for c, n in counts.items())
    seconds = report.get("timings_seconds", {}).get("job", {}).get("total")
    took = f" in {seconds:.1f} s ({report['points_per_second']:,.0f} points/s)" if seconds else ""
    print(
        f"terrasift: {report.get('points', 0):,} points of {len(report.get('tiles', []))} tile(s), "
        f"{report.get('blocks', 0)} blocks{took}; {classes}; "
        f"{len(report.get('warnings', []))} warning(s)",
        file=sys.stderr,
    )


class _progress_bar:
    """A tqdm bar over the job's work, described by the current stage and counts."""

    def __init__(self) -> None:
        from tqdm import tqdm

        self._bar = tqdm(total=100, unit="%", desc="terrasift", file=sys.stderr)

    def update(self, done: int, total: int, info: Mapping[str, Any] | None = None) -> None:
        pct = int(100 * done / total) if total else 0
        self._bar.n = min(pct, 100)
        if info:
            self._bar.set_postfix_str(info.get("message", ""), refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        self._bar.close()


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


def worker_options(host: str, nthreads: int, dashboard: str | None) -> dict:
    """Keyword arguments of a Dask worker: bound to ``host``, dashboard only when asked.

    A dashboard given as ``:PORT`` listens on ``host`` too.
    """
    options: dict = {"host": host, "nthreads": nthreads, "dashboard": dashboard is not None}
    if dashboard is not None:
        options["dashboard_address"] = (
            f"{host}{dashboard}" if dashboard.startswith(":") else dashboard
        )
    return options


def run_worker(
    scheduler: str | None,
    nthreads: int,
    *,
    host: str = "127.0.0.1",
    nworkers: int = 1,
    dashboard: str | None = None,
) -> int:
    """Run Dask worker(s) that can execute terrasift tasks (they import this package).

    One worker runs in this process; several run each in its own process under a
    Dask nanny, which also restarts a worker that dies.
    """
    import asyncio

    from terrasift.workers.executors import single_threaded_blas

    single_threaded_blas()
    from distributed import Nanny, Worker

    address = scheduler or os.environ.get("TERRASIFT_DASK_SCHEDULER")
    if not address:
        print(
            "terrasift worker: give a scheduler address or set TERRASIFT_DASK_SCHEDULER",
            file=sys.stderr,
        )
        return 2
    options = worker_options(host, nthreads, dashboard)

    async def run() -> None:
        if nworkers == 1:
            async with Worker(address, **options) as worker:
                await worker.finished()
            return
        nannies = [Nanny(address, **options) for _ in range(nworkers)]
        await asyncio.gather(*nannies)  # starts them
        try:
            await asyncio.gather(*(n.finished() for n in nannies))
        finally:
            await asyncio.gather(*(n.close() for n in nannies), return_exceptions=True)

    asyncio.run(run())
    return 0


if __name__ == "__main__":
    sys.exit(main())
