"""The issue's nine failures re-probed against a live service (``make bench-audit``).

Starts the service as the README says (``make serve``) with its own port, data directory,
input root and a 1 GiB worker memory limit, and sends real requests:

1. a LAZ whose chunk table claims 2^31-1 chunks; ``kill -9`` of a busy worker mid-job,
   then that job and a later one;
2. LAZ files with random bytes in their compressed points (the workers' peak RSS);
3. three concurrent LAS uploads whose header says 0xFFFFFFFF VLRs (the API's RSS);
4. ``features`` with 80 000 names (and 80 000 times one name); DELETE of a running job;
5. x/y offsets of +-1e300 and 4e9, a NaN z offset, zeroed compressed points, a point count
   short of the data;
6. the five 5xx: nested JSON in ``params``, a 5000-digit number, a NUL byte in a server
   path, ``GET /jobs?offset=254357068941219463168``, a data directory that cannot be written;
7. a survey tile replaced by a symbolic link to a file outside the input root after the
   survey was registered;
8. ``jobs.sqlite`` deleted under the running server, then a restart; ``kill -9`` of the API
   with a job running (orphans), then a restart;
9. ``GET /jobs/{id}`` p50/p99 with 50 pollers while two jobs run;

and SIGTERM with a job running. Prints one line per check with ``ok`` or ``FAIL`` and what
was seen; the exit status is the number of failed checks.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from load import free_port, keep_two_running, poll  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from terrasift.synthetic.malformed import write_pair  # noqa: E402
from terrasift.synthetic.terrain import make_scene, write_las  # noqa: E402

PARAMS = json.dumps({"block_size": 40, "resolution": 1.0, "features": "none"})
FINAL = ("successful", "failed", "dismissed")
results: list[tuple[str, bool, str]] = []


def check(name: str, ok: bool, seen: str) -> None:
    results.append((name, ok, seen))
    print(f"{'ok  ' if ok else 'FAIL'} {name}: {seen}", flush=True)


def put(data: bytes, at: int, fmt: str, value: object) -> bytes:
    out = bytearray(data)
    struct.pack_into("<" + fmt, out, at, value)
    return bytes(out)


class Service:
    """``make serve`` with its own settings; the API process is make's child."""

    def __init__(self, env: dict[str, str], port: int) -> None:
        self.env, self.port = env, port
        self.base = f"http://127.0.0.1:{port}"
        self.make: subprocess.Popen | None = None

    def start(self) -> None:
        self.make = subprocess.Popen(
            ["make", "--no-print-directory", "serve"],
            cwd=REPO,
            env=self.env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        end = time.monotonic() + 120
        while time.monotonic() < end:
            try:
                if httpx.get(f"{self.base}/conformance", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                time.sleep(0.2)
        raise RuntimeError("the service did not start within 120 s")

    @property
    def api_pid(self) -> int:
        assert self.make is not None
        kids = Path(f"/proc/{self.make.pid}/task/{self.make.pid}/children").read_text().split()
        return int(kids[0])

    def stop(self) -> tuple[float, int]:
        """SIGTERM to the API; seconds to exit."""
        assert self.make is not None
        pid, t = self.api_pid, time.monotonic()
        os.kill(pid, signal.SIGTERM)
        self.make.wait(timeout=90)
        return time.monotonic() - t, pid


def rss(pid: int, field: str = "VmRSS") -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def children(data: Path) -> set[int]:
    """Live processes with a pid file under the data directory (workers, header readers)."""
    out = set()
    for p in (data / "workers").glob("[0-9]*"):
        try:
            if Path(f"/proc/{p.name}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
                out.add(int(p.name))
        except OSError:
            pass
    return out


def busy_worker(data: Path, within: float = 0.5) -> int | None:
    """A worker (niced) of the service that used CPU within ``within`` s."""

    def cpu(pid: int) -> float:
        try:
            f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            return int(f[11]) + int(f[12])
        except OSError:
            return 0

    def niced(pid: int) -> bool:
        try:
            return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[16]) > 0
        except (OSError, ValueError):
            return False

    pids = [p for p in children(data) if niced(p)]
    before = {p: cpu(p) for p in pids}
    time.sleep(within)
    moved = [p for p in pids if cpu(p) > before[p]]
    return moved[0] if moved else None


def upload(c: httpx.Client, name: str, data: bytes, params: str = PARAMS) -> httpx.Response:
    return c.post("/jobs", files=[("file", (name, data))], data={"params": params})


def wait(c: httpx.Client, job: str, timeout: float = 300) -> dict:
    end = time.monotonic() + timeout
    info: dict = {}
    while time.monotonic() < end:
        info = c.get(f"/jobs/{job}").json()
        if info["status"] in FINAL:
            return info
        time.sleep(0.2)
    info["status"] = f"stuck ({info.get('status')} after {timeout:.0f} s)"
    return info


def sample_peak(pids: Callable[[], set[int]], stop: threading.Event, peak: dict) -> None:
    while not stop.is_set():
        for p in pids():
            peak["rss"] = max(peak.get("rss", 0), rss(p, "VmHWM"))
        time.sleep(0.1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--payloads", type=int, default=32, help="LAZ files with corrupt points")
    ap.add_argument("--seconds", type=float, default=20.0, help="polling window of check 9")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="terrasift-audit-") as tmp:
        run(Path(tmp), args)
    failed = sum(not ok for _, ok, _ in results)
    print(f"{len(results)} checks, {failed} failed")
    sys.exit(failed)


def run(tmp: Path, args: argparse.Namespace) -> None:
    data, root = tmp / "data", tmp / "root"
    root.mkdir()
    port = free_port()
    env = {
        **os.environ,
        "TERRASIFT_PORT": str(port),
        "TERRASIFT_DATA_DIR": str(data),
        "TERRASIFT_INPUT_ROOT": str(root),
        "TERRASIFT_AUTH": "off",
        "TERRASIFT_WORKER_MEMORY": str(1024**3),
    }
    las, laz = write_pair(tmp)
    job_tile = write_las(make_scene(size=120, density=6, seed=3), tmp / "job.laz").read_bytes()
    (root / "tile.laz").write_bytes(laz)
    svc = Service(env, port)
    svc.start()
    c = httpx.Client(base_url=svc.base, timeout=120)
    try:
        probes(svc, c, data, root, tmp, las, laz, job_tile, args)
    finally:
        if svc.make is not None and svc.make.poll() is None:
            svc.stop()
        c.close()


def probes(
    svc: Service,
    c: httpx.Client,
    data: Path,
    root: Path,
    tmp: Path,
    las: bytes,
    laz: bytes,
    job_tile: bytes,
    args: argparse.Namespace,
) -> None:
    offset = struct.unpack_from("<I", laz, 96)[0]
    table = struct.unpack_from("<q", laz, offset)[0]

    # 1. lying chunk table; kill -9 of a busy worker
    r = upload(c, "chunks.laz", put(laz, table + 4, "I", 0x7FFFFFFF))
    check("1 chunk table of 2^31-1 chunks", r.status_code == 422, f"{r.status_code} {r.text[:160]}")
    job = upload(c, "job.laz", job_tile).json()["jobID"]
    victim = None
    end = time.monotonic() + 120
    while victim is None and time.monotonic() < end:
        victim = busy_worker(data)
    if victim:
        os.kill(victim, signal.SIGKILL)
    first = wait(c, job)
    second = wait(c, upload(c, "job.laz", job_tile).json()["jobID"])
    check(
        "1 kill -9 of a busy worker",
        victim is not None and first["status"] == second["status"] == "successful",
        f"killed {victim}; that job {first['status']}, the next {second['status']}",
    )

    # 2. corrupt compressed points, the workers' peak RSS
    rng = np.random.default_rng(7)
    stop, peak = threading.Event(), {}
    sampler = threading.Thread(target=sample_peak, args=(lambda: children(data), stop, peak))
    sampler.start()
    outcomes: dict[str, int] = {}
    jobs = []
    for i in range(args.payloads):
        body = bytearray(laz)
        start = int(rng.integers(offset + 8, table - 64))
        n = int(rng.integers(4, 64))
        body[start : start + n] = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        r = upload(c, f"payload{i}.laz", bytes(body))
        if r.status_code == 201:
            jobs.append(r.json()["jobID"])
        else:
            key = f"refused {r.status_code}"
            outcomes[key] = outcomes.get(key, 0) + 1
    for j in jobs:
        s = wait(c, j)["status"]
        outcomes[s] = outcomes.get(s, 0) + 1
    stop.set()
    sampler.join()
    check(
        "2 corrupt compressed points",
        not any(k.startswith(("stuck", "refused 5")) for k in outcomes)
        and peak.get("rss", 0) < 1024**3,
        f"{args.payloads} files: {outcomes}; peak RSS of any worker or reader "
        f"{peak.get('rss', 0) / 2**20:.0f} MiB (limit 1024)",
    )

    # 3. 0xFFFFFFFF VLRs, three at once
    api = svc.api_pid
    before = rss(api)
    bomb = put(las, 100, "I", 0xFFFFFFFF)
    answers: list[tuple[int, float]] = []

    def one() -> None:
        t = time.monotonic()
        with httpx.Client(base_url=svc.base, timeout=120) as cc:
            answers.append((upload(cc, "vlrs.las", bomb).status_code, time.monotonic() - t))

    threads = [threading.Thread(target=one) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    grew = (rss(api) - before) / 2**20
    check(
        "3 three LAS with 0xFFFFFFFF VLRs at once",
        all(s == 422 for s, _ in answers) and grew < 100,
        f"answers {[(s, round(d, 2)) for s, d in answers]} s; API RSS "
        f"{before / 2**20:.0f} -> {rss(api) / 2**20:.0f} MiB",
    )

    # 4. 80 000 feature names; DELETE of a running job
    names = ",".join(f"f{i}" for i in range(80_000))
    r = upload(c, "t.laz", laz, json.dumps({"features": names}))
    check("4 features with 80 000 names", r.status_code == 400, f"{r.status_code} {r.text[:140]}")
    r = upload(c, "t.laz", laz, json.dumps({"features": ",".join(["ditch"] * 80_000)}))
    ok = r.status_code == 201
    if ok:
        info = wait(c, r.json()["jobID"])
        seen = f"201, job {info['status']}"
        ok = info["status"] == "successful"
    else:
        seen = f"{r.status_code} {r.text[:140]}"
    check("4 features with 80 000 times one name (de-duplicated)", ok, seen)
    job = upload(c, "job.laz", job_tile).json()["jobID"]
    worker = None
    end = time.monotonic() + 120
    while worker is None and time.monotonic() < end:
        worker = busy_worker(data)
    t = time.monotonic()
    code = c.delete(f"/jobs/{job}").status_code
    answered = time.monotonic() - t
    while worker and Path(f"/proc/{worker}").exists() and time.monotonic() - t < 30:
        time.sleep(0.01)
    gone = time.monotonic() - t
    check(
        "4 DELETE of a running job",
        code == 200 and worker is not None and gone < 5,
        f"{code} in {answered:.2f} s; its busy worker {worker} gone after {gone:.2f} s; "
        f"status {c.get(f'/jobs/{job}').json()['status']}",
    )

    # 5. garbage in, no silent garbage out
    x_off = 155
    count = struct.unpack_from("<I", las, 107)[0]
    garbage = {
        "x offset +1e300": ("laz", put(laz, x_off, "d", 1e300)),
        "x offset -1e300": ("laz", put(laz, x_off, "d", -1e300)),
        "y offset 4e9": ("laz", put(laz, x_off + 8, "d", 4e9)),
        "z offset NaN": ("laz", put(laz, x_off + 16, "d", float("nan"))),
        "zeroed compressed points": (
            "laz",
            laz[: offset + 8] + bytes(table - offset - 8) + laz[table:],
        ),
        "LAS point count half the data": ("las", put(las, 107, "I", count // 2)),
        "LAZ point count one short": ("laz", put(laz, 107, "I", count - 1)),
    }
    for name, (suffix, body) in garbage.items():
        r = upload(c, f"t.{suffix}", body)
        if r.status_code == 201:
            info = wait(c, r.json()["jobID"])
            seen = f"job {info['status']}: {info.get('message', '')[:120]}"
            ok = info["status"] == "failed" or bool(info.get("warnings"))
        else:
            detail = r.json().get("detail", "")[:120]
            seen, ok = f"{r.status_code} {detail}", 400 <= r.status_code < 500
        check(f"5 {name}", ok, seen)

    # 6. the five 5xx
    nested = upload(c, "t.laz", laz, '{"a":' * 5000 + "1" + "}" * 5000)
    digits = upload(c, "t.laz", laz, '{"resolution": ' + "9" * 5000 + "}")
    nul = c.post("/processes/terrain/execution", json={"inputs": {"files": ["tile\u0000.laz"]}})
    offset_q = c.get("/jobs", params={"offset": "254357068941219463168"})
    for name, r in (
        ("nested JSON in params", nested),
        ("a 5000-digit number", digits),
        ("a NUL byte in a server path", nul),
        ("offset=254357068941219463168", offset_q),
    ):
        check(f"6 {name}", 400 <= r.status_code < 500, f"{r.status_code} {r.text[:120]}")
    long_upload = upload(c, "a" * 300 + ".laz", laz)
    long_path = c.post(
        "/processes/terrain/execution", json={"inputs": {"files": ["a" * 300 + ".laz"]}}
    )
    check(
        "6 names longer than the file system takes",
        long_upload.status_code == 201 and long_path.status_code == 400,
        f"upload named with 300 characters {long_upload.status_code}, server path "
        f"{long_path.status_code} {long_path.text[:100]}",
    )
    jobs_dir = data / "jobs"
    aside = data / "jobs.aside"
    jobs_dir.rename(aside)
    jobs_dir.write_text("not a directory")  # root writes through permissions: a file instead
    try:
        r = upload(c, "t.laz", laz)
    finally:
        jobs_dir.unlink()
        aside.rename(jobs_dir)
    check(
        "6 a data directory that cannot be written",
        r.status_code == 503,
        f"{r.status_code} {r.text[:120]}",
    )

    # 7. symlink swapped in after the survey was registered
    r = c.post("/surveys", json={"files": ["tile.laz"]})
    survey = r.json().get("id")
    outside = tmp / "outside.laz"
    outside.write_bytes(laz)
    (root / "tile.laz").unlink()
    (root / "tile.laz").symlink_to(outside)
    r = c.post(f"/surveys/{survey}/runs")
    if r.status_code == 201:
        info = wait(c, r.json()["jobID"])
        ok, seen = (
            info["status"] == "failed",
            f"run {info['status']}: {info.get('message', '')[:120]}",
        )
    else:
        ok, seen = 400 <= r.status_code < 500, f"{r.status_code} {r.json().get('detail', '')[:120]}"
    check("7 symlink to outside the root after registration", ok, seen)

    # 8. jobs.sqlite deleted under the running server, then a restart
    before_ids = {j["jobID"] for j in c.get("/jobs", params={"limit": 1000}).json()["jobs"]}
    (data / "jobs.sqlite").unlink()
    time.sleep(3)
    back = (data / "jobs.sqlite").exists()
    health = c.get("/health")
    took, _ = svc.stop()
    svc.start()
    after_ids = {j["jobID"] for j in c.get("/jobs", params={"limit": 1000}).json()["jobs"]}
    check(
        "8 jobs.sqlite deleted under the server, then a restart",
        back and before_ids <= after_ids and health.status_code == 200,
        f"file back after 3 s: {back}; /health {health.status_code}; jobs listed before "
        f"{len(before_ids)}, after the restart {len(after_ids & before_ids)}",
    )
    job = upload(c, "job.laz", job_tile).json()["jobID"]
    end = time.monotonic() + 120
    while c.get(f"/jobs/{job}").json()["status"] != "running" and time.monotonic() < end:
        time.sleep(0.2)
    end = time.monotonic() + 20  # readers and workers of the restarted service all up
    while len(children(data)) < 4 and time.monotonic() < end:
        time.sleep(0.2)
    kids = children(data)
    os.kill(svc.api_pid, signal.SIGKILL)
    assert svc.make is not None
    svc.make.wait(timeout=30)
    time.sleep(10)
    left = children(data) & kids
    svc.start()
    info = wait(c, job)
    check(
        "8 kill -9 of the API with a job running",
        not left and info["status"] == "successful",
        f"{len(left)} of its {len(kids)} workers and readers alive after 10 s; after a restart "
        f"the job is {info['status']}",
    )

    # 9. status latency with 50 pollers while two jobs run
    ids = [upload(c, "job.laz", job_tile).json()["jobID"] for _ in range(2)]
    end = time.monotonic() + 120
    while time.monotonic() < end and not all(
        c.get(f"/jobs/{j}").json()["status"] == "running" for j in ids
    ):
        time.sleep(0.2)
    tile_path = tmp / "job.laz"

    async def window() -> tuple[tuple[list[float], list[float]], dict[str, int]]:
        return await asyncio.gather(
            poll(svc.base, ids, 50, args.seconds, 0.5, 1000),
            keep_two_running(svc.base, ids, tile_path, PARAMS, args.seconds),
        )

    (lat, _), kept = asyncio.run(window())
    p50 = 1000 * statistics.median(lat)
    p99 = 1000 * statistics.quantiles(lat, n=100)[98]
    check(
        "9 GET /jobs/{id} with 50 pollers, two jobs running",
        p99 < 50,
        f"n={len(lat)} p50 {p50:.1f} ms p99 {p99:.1f} ms; both running in {kept['both']} of "
        f"{kept['checks']} checks; load average {os.getloadavg()[0]:.1f}",
    )

    # SIGTERM with jobs running
    kids = children(data)
    took, _ = svc.stop()
    time.sleep(1)
    left = children(data) & kids
    check(
        "SIGTERM with jobs running",
        took < 15 and not left,
        f"exit after {took:.1f} s, {len(left)} of {len(kids)} workers and readers left",
    )


if __name__ == "__main__":
    main()
