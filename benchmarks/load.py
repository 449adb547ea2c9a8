"""Status latency under load (``make bench-load``): GET /jobs/{id} with 50 pollers.

Starts ``terrasift serve`` on a loopback port with a fresh data directory,
measures p50/p99 of the status read with the pollers while the service is idle,
then again while two jobs run, and prints both. Two jobs run through the whole
busy window on any machine: a third job waits queued behind them, and whenever
one of the two ends (a fast machine finishes a tile before the window does)
the queued one starts in its place, the pollers switch to it and a new one is
queued; a keeper checks the two every 0.25 s and the output says in what share
of those checks both were running (and warns when it was not all of them).
Every loop is bounded: pollers
stop at ``--seconds`` or after ``--max-requests`` each, and the server is stopped
with SIGTERM while the jobs run (its exit time and leftover workers are printed).
Beside what the pollers see it prints the server's own time per request (its
``Server-Timing`` header) and the CPU share of the API process and of the
pollers: the difference between the two latencies is time spent waiting for a
CPU or the event loop, not in the request path. The pollers run with their own
garbage collector off, so its pauses are not counted. ``--profile FILE`` records the
API process with py-spy while the jobs run (collapsed stacks).
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from terrasift.synthetic.terrain import make_scene, write_las  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(data: Path, port: int, pythonpath: str | None = None) -> subprocess.Popen:
    env = {**os.environ, "TERRASIFT_DATA_DIR": str(data), "TERRASIFT_AUTH": "off"}
    if pythonpath:  # another checkout of terrasift, for a baseline in the same run
        env["PYTHONPATH"] = pythonpath
    data.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen(
        [sys.executable, "-m", "terrasift", "serve", "--host", "127.0.0.1", "--port", str(port)],
        env=env,
        cwd=data.parent,  # not the repository: `-m terrasift` would import this tree first
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    end = time.monotonic() + 60
    while time.monotonic() < end:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/conformance", timeout=2).status_code == 200:
                return proc
        except httpx.HTTPError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError("the server did not start within 60 s")


async def poll(
    base: str, job_ids: list[str], pollers: int, seconds: float, interval: float, cap: int
) -> tuple[list[float], list[float]]:
    """Latencies (s) of GET /jobs/{id} from ``pollers`` clients, each every ``interval`` s,
    and the server's own time for each (its ``Server-Timing`` header)."""
    latencies: list[float] = []
    app_times: list[float] = []  # the server's own time (Server-Timing), when it sends it

    async def one(i: int) -> None:
        async with httpx.AsyncClient(base_url=base, timeout=60) as client:
            # the first read opens the poller's connection: not counted
            (await client.get(f"/jobs/{job_ids[i % len(job_ids)]}")).raise_for_status()
            await asyncio.sleep(interval * i / pollers)  # spread the pollers over the interval
            deadline = time.monotonic() + seconds
            for _ in range(cap):
                if time.monotonic() >= deadline:
                    return
                t = time.perf_counter()
                r = await client.get(f"/jobs/{job_ids[i % len(job_ids)]}")
                latencies.append(time.perf_counter() - t)
                r.raise_for_status()
                timing = r.headers.get("server-timing", "")
                if "dur=" in timing:
                    app_times.append(float(timing.split("dur=")[1].split(",")[0]) / 1000)
                await asyncio.sleep(interval)

    # the pollers' own full garbage collections (0.16-0.24 s at load ~15) would stall
    # every request in flight and be counted as the server's latency
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        await asyncio.gather(*(one(i) for i in range(pollers)))
    finally:
        gc.enable()
        gc.unfreeze()
    return latencies, app_times


async def submit(client: httpx.AsyncClient, tile: Path, params: str) -> str:
    """Upload ``tile`` as a new job; its id."""
    r = await client.post(
        "/jobs", files=[("file", ("tile.laz", tile.read_bytes()))], data={"params": params}
    )
    r.raise_for_status()
    return r.json()["jobID"]


async def keep_two_running(
    base: str, job_ids: list[str], tile: Path, params: str, seconds: float
) -> dict[str, int]:
    """For ``seconds``, keep the two jobs of ``job_ids`` running: a standby job waits queued,
    and when one of the two is no longer running it takes its place in ``job_ids`` (which the
    pollers read on every request) and a new standby is queued. Counts of the checks (every
    0.25 s) with both running, of all checks, of the jobs replaced and of those that failed."""
    counts = {"both": 0, "checks": 0, "replaced": 0, "failed": 0}
    async with httpx.AsyncClient(base_url=base, timeout=60) as client:
        standby = await submit(client, tile, params)
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            states = [(await client.get(f"/jobs/{j}")).json()["status"] for j in job_ids]
            counts["checks"] += 1
            counts["both"] += all(s == "running" for s in states)
            for k, state in enumerate(states):
                if state not in ("accepted", "running"):
                    counts["replaced"] += 1
                    counts["failed"] += state != "successful"
                    job_ids[k] = standby
                    standby = await submit(client, tile, params)
            await asyncio.sleep(0.25)
    return counts


async def busy_window(
    args: argparse.Namespace, base: str, job_ids: list[str], tile: Path, params: str
) -> tuple[tuple[list[float], list[float]], dict[str, int]]:
    """The pollers and the keeper of the two running jobs, side by side."""
    polled, kept = await asyncio.gather(
        poll(base, job_ids, args.pollers, args.seconds, args.interval, args.max_requests),
        keep_two_running(base, job_ids, tile, params, args.seconds),
    )
    return polled, kept


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (0 when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def summary(lat: list[float]) -> str:
    if len(lat) < 2:
        return "not reported" if not lat else f"n={len(lat)}"
    q = statistics.quantiles(lat, n=100)
    return f"n={len(lat)} p50={1000 * statistics.median(lat):.1f} ms p99={1000 * q[98]:.1f} ms max={1000 * max(lat):.1f} ms"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--pollers", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--interval", type=float, default=0.5, help="seconds between a poller's reads")
    ap.add_argument("--max-requests", type=int, default=1000, help="per poller")
    ap.add_argument("--size", type=float, default=200.0, help="edge of each job's tile in metres")
    ap.add_argument(
        "--profile",
        help="record the API process with py-spy while the jobs run (collapsed stacks to this file)",
    )
    ap.add_argument(
        "--baseline", help="a directory holding another terrasift package to measure first"
    )
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="terrasift-load-") as tmp:
        tile = write_las(make_scene(size=args.size, density=8, seed=4), Path(tmp) / "tile.laz")
        runs = [("baseline", args.baseline)] if args.baseline else []
        for label, path in [*runs, ("this tree", None)]:
            print(f"== {label}")
            measure(args, tile, path)


def measure(args: argparse.Namespace, tile: Path, pythonpath: str | None) -> None:

    with tempfile.TemporaryDirectory(prefix="terrasift-load-") as tmp:
        tmp = Path(tmp)
        port = free_port()
        base = f"http://127.0.0.1:{port}"
        server = start_server(tmp / "data", port, pythonpath)
        try:
            params = json.dumps({"block_size": 50, "resolution": 0.5})
            with httpx.Client(base_url=base, timeout=60) as c:
                # an idle job to poll first: submitted, then dismissed before it runs much
                ids = []
                for _ in range(2):
                    with open(tile, "rb") as fh:
                        r = c.post(
                            "/jobs", files=[("file", ("tile.laz", fh))], data={"params": params}
                        )
                    r.raise_for_status()
                    ids.append(r.json()["jobID"])
                idle_ids = list(ids)
                for j in idle_ids:
                    c.delete(f"/jobs/{j}")
                time.sleep(2)
                idle = asyncio.run(
                    poll(
                        base,
                        idle_ids,
                        args.pollers,
                        args.seconds / 2,
                        args.interval,
                        args.max_requests,
                    )
                )
                busy_ids = []
                for _ in range(2):
                    with open(tile, "rb") as fh:
                        r = c.post(
                            "/jobs", files=[("file", ("tile.laz", fh))], data={"params": params}
                        )
                    busy_ids.append(r.json()["jobID"])
                end = time.monotonic() + 60
                while time.monotonic() < end and not all(
                    c.get(f"/jobs/{j}").json()["status"] == "running" for j in busy_ids
                ):
                    time.sleep(0.2)
                time.sleep(2)  # past the workers' start
                spy = None
                if args.profile:
                    out = f"{args.profile}.{'baseline' if pythonpath else 'tree'}"
                    spy = subprocess.Popen(
                        [
                            *(
                                [
                                    "py-spy",
                                    "record",
                                    "--nonblocking",
                                    "--format",
                                    "raw",
                                    "--rate",
                                    "250",
                                ]
                            ),
                            *("--pid", str(server.pid), "--duration", str(int(args.seconds))),
                            *("--output", out),
                        ],
                        stdout=subprocess.DEVNULL,
                        stderr=subprocess.DEVNULL,
                    )
                cpu0 = (time.process_time(), cpu_seconds(server.pid), time.monotonic())
                busy, kept = asyncio.run(busy_window(args, base, busy_ids, tile, params))
                cpu1 = (time.process_time(), cpu_seconds(server.pid), time.monotonic())
                if spy is not None:
                    spy.wait(timeout=60)
                states = [c.get(f"/jobs/{j}").json() for j in busy_ids]
                still = [s["progress"] for s in states if s["status"] == "running"]
                workers = [int(p.name) for p in (tmp / "data" / "workers").glob("[0-9]*")]
        finally:
            # SIGTERM with the jobs still running: the grace period (10 s), then the workers go
            t = time.monotonic()
            server.send_signal(signal.SIGTERM)
            try:
                server.wait(timeout=60)
            except subprocess.TimeoutExpired:
                server.kill()
            stop_seconds = time.monotonic() - t
            time.sleep(1.0)
            alive = [p for p in workers if Path(f"/proc/{p}").exists()]
        load = os.getloadavg()[0]
        print(
            f"{args.pollers} pollers, one read each every {args.interval} s; load average {load:.1f}"
        )
        print(f"idle (jobs dismissed):        {summary(idle[0])}")
        print(f"  server's own time:          {summary(idle[1])}")
        print(
            f"two jobs running ({len(still)} still running at the end, progress {still}): {summary(busy[0])}"
        )
        print(f"  server's own time:          {summary(busy[1])}")
        share = kept["both"] / max(kept["checks"], 1)
        print(
            f"  both jobs running in {kept['both']} of {kept['checks']} checks ({100 * share:.0f} %); "
            f"jobs that ended in the window and were replaced: {kept['replaced']} "
            f"({kept['failed']} not successful)"
        )
        if share < 1.0:
            print(
                f"  NOTE: fewer than two jobs were running in {100 * (1 - share):.0f} % of the "
                "checks (a job starting or ending): those reads were not all under two jobs"
            )
        wall = cpu1[2] - cpu0[2]
        print(
            f"  CPU while polling: API process {100 * (cpu1[1] - cpu0[1]) / wall:.0f} %, "
            f"pollers {100 * (cpu1[0] - cpu0[0]) / wall:.0f} % of one core"
        )
        print(
            f"SIGTERM with both jobs running to exit: {stop_seconds:.1f} s; "
            f"workers left alive: {len(alive)} of {len(workers)}"
        )


if __name__ == "__main__":
    main()
