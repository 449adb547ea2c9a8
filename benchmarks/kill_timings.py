"""Kill and dismiss timings against ``terrasift serve`` (``make bench-kill``).

Starts the server on a loopback port (as ``benchmarks/load.py`` does) and measures:

1. ``kill -9`` of a worker busy with a job: how long until a replacement is up,
   and whether that job and the next one succeed;
2. ``DELETE /jobs/{id}`` of a running job: how long until the workers that ran
   its tasks are gone, and until the status says ``dismissed``;
3. ``kill -9`` of the API process with a job running: how long until every
   worker and header reader it started is gone (none may be left).

Processes are found by the pid files under ``<data>/workers``; workers (not
header readers) run niced, and a worker is busy when its CPU time grows.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))
from load import cpu_seconds, free_port, start_server  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from terrasift.synthetic.terrain import make_scene, write_las  # noqa: E402

PARAMS = json.dumps({"block_size": 50, "resolution": 0.5})


def children(data: Path) -> set[int]:
    """Live processes with a pid file (workers and header readers)."""
    return {
        int(p.name) for p in (data / "workers").glob("[0-9]*") if Path(f"/proc/{p.name}").exists()
    }


def alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def nice(pid: int) -> int:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[16])
    except (OSError, ValueError, IndexError):
        return 0


def busy(pids: set[int], within: float = 1.0) -> set[int]:
    """Workers (niced, unlike the header readers) of ``pids`` that used CPU in ``within`` s."""
    workers = {p for p in pids if nice(p) > 0}
    before = {p: cpu_seconds(p) for p in workers}
    time.sleep(within)
    return {p for p in workers if cpu_seconds(p) - before[p] > 0}


def submit(c: httpx.Client, tile: Path) -> str:
    with open(tile, "rb") as fh:
        r = c.post("/jobs", files=[("file", ("tile.laz", fh))], data={"params": PARAMS})
    r.raise_for_status()
    return r.json()["jobID"]


def wait_status(c: httpx.Client, job: str, states: tuple[str, ...], timeout: float) -> str:
    end = time.monotonic() + timeout
    status = ""
    while time.monotonic() < end:
        status = c.get(f"/jobs/{job}").json()["status"]
        if status in states:
            return status
        time.sleep(0.2)
    return status


def running_workers(c: httpx.Client, data: Path, job: str) -> set[int]:
    """Wait until the job runs and some worker is busy with it; those workers."""
    wait_status(c, job, ("running",), 120)
    end = time.monotonic() + 120
    while time.monotonic() < end:
        found = busy(children(data), 1.0)
        if found:
            return found
    raise RuntimeError("no worker got busy within 120 s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=float, default=150.0, help="edge of the job's tile in metres")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="terrasift-kill-") as tmp:
        tmp = Path(tmp)
        tile = write_las(make_scene(size=args.size, density=8, seed=4), tmp / "tile.laz")
        data = tmp / "data"
        port = free_port()
        server = start_server(data, port)
        base = f"http://127.0.0.1:{port}"
        try:
            with httpx.Client(base_url=base, timeout=60) as c:
                # 1. kill -9 of a busy worker
                job = submit(c, tile)
                victim = min(running_workers(c, data, job))
                before = children(data)
                t = time.monotonic()
                os.kill(victim, signal.SIGKILL)
                while time.monotonic() - t < 60 and not (children(data) - before):
                    time.sleep(0.02)
                replaced = time.monotonic() - t
                outcome = wait_status(c, job, ("successful", "failed", "dismissed"), 600)
                after = submit(c, tile)
                next_outcome = wait_status(c, after, ("successful", "failed", "dismissed"), 600)
                print(
                    f"kill -9 of a busy worker: replacement up in {replaced:.2f} s; "
                    f"that job {outcome}, the next {next_outcome}"
                )
                # 2. DELETE of a running job
                job = submit(c, tile)
                workers = running_workers(c, data, job)
                t = time.monotonic()
                c.delete(f"/jobs/{job}").raise_for_status()
                answered = time.monotonic() - t
                while time.monotonic() - t < 60 and any(alive(p) for p in workers):
                    time.sleep(0.01)
                gone = time.monotonic() - t
                status = wait_status(c, job, ("dismissed",), 60)
                print(
                    f"DELETE of a running job: answered in {answered:.2f} s, its {len(workers)} "
                    f"busy worker(s) gone in {gone:.2f} s; status {status}"
                )
                # 3. kill -9 of the API with a job running
                job = submit(c, tile)
                running_workers(c, data, job)
            started = children(data)
            t = time.monotonic()
            server.kill()
            server.wait()
            while time.monotonic() - t < 10 and any(alive(p) for p in started):
                time.sleep(0.01)
            gone = time.monotonic() - t
            left = [p for p in started if alive(p)]
            print(
                f"kill -9 of the API: its {len(started)} workers and header readers gone in "
                f"{gone:.2f} s; left after 10 s: {len(left)}"
            )
        finally:
            if server.poll() is None:
                server.kill()
        print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
