"""Submission latency with tile headers read in subprocesses (``make bench-submit``).

The service reads every tile header at submission in a pool of pre-started
reader processes (``service.inspector``) rather than in a thread of the API
process. This measures what that costs a client: the same requests against the
app with ``header_readers=2`` (the default) and ``header_readers=0`` (headers read
in the API process, the behaviour before), in alternating blocks of the same run,
through the in-process ASGI client. Requests that only check and record (no job
runs, so nothing else loads the machine):

- ``POST /surveys`` naming 1 and 8 LAZ tiles under the input root (server paths),
- ``PUT /surveys/{id}/tiles/{name}`` with a LAZ tile as the body (an upload).

Prints the median latency of each request per variant, their ratio (readers /
in-process) and the load average. One app at a time: the header reader is
process-wide.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fastapi.testclient import TestClient  # noqa: E402

from terrasift.service.app import create_app  # noqa: E402
from terrasift.service.settings import Settings  # noqa: E402
from terrasift.synthetic.terrain import make_scene, write_las  # noqa: E402


def make_tiles(root: Path, n: int) -> list[str]:
    """``n`` small LAZ tiles (3,200 points each, with a CRS) side by side; their names."""
    names = []
    for i in range(n):
        scene = make_scene(size=40.0, density=2.0, seed=20 + i)
        scene_path = root / f"t{i}.laz"
        write_las(scene, scene_path, crs="EPSG:32632", point_format=1, version="1.2")
        names.append(scene_path.name)
    return names


def block(readers: int, data: Path, root: Path, names: list[str], repeat: int) -> dict[str, list]:
    """Latencies (s) of each request kind, ``repeat`` times, with ``readers`` header readers."""
    settings = Settings(
        _env_file=None, data_dir=data, input_root=root, header_readers=readers, auth="off"
    )
    out: dict[str, list] = {"surveys 1 tile": [], "surveys 8 tiles": [], "PUT tile": []}
    body = (root / names[0]).read_bytes()
    with TestClient(create_app(settings)) as c:
        r = c.post("/surveys", json={"files": names[:1]})  # readers started and warm
        assert r.status_code == 201, r.text
        survey = r.json()["id"]
        for _ in range(repeat):
            for key, files in (("surveys 1 tile", names[:1]), ("surveys 8 tiles", names)):
                t = time.perf_counter()
                r = c.post("/surveys", json={"files": files})
                out[key].append(time.perf_counter() - t)
                assert r.status_code == 201, r.text
            t = time.perf_counter()
            r = c.put(
                f"/surveys/{survey}/tiles/up.laz",
                content=body,
                headers={"Content-Type": "application/octet-stream"},
            )
            out["PUT tile"].append(time.perf_counter() - t)
            assert r.status_code in (200, 201), r.text
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--blocks", type=int, default=6, help="blocks per variant (alternating)")
    ap.add_argument("--repeat", type=int, default=20, help="requests of each kind per block")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "root"
        root.mkdir()
        names = make_tiles(root, 8)
        results: dict[int, dict[str, list]] = {0: {}, 2: {}}
        loads = [os.getloadavg()[0]]
        for b in range(args.blocks):
            order = (2, 0) if b % 2 == 0 else (0, 2)
            for readers in order:
                got = block(readers, Path(tmp) / f"data{b}-{readers}", root, names, args.repeat)
                for key, values in got.items():
                    results[readers].setdefault(key, []).extend(values)
            loads.append(os.getloadavg()[0])
    print(
        f"{args.blocks} blocks x {args.repeat} requests per variant; "
        f"load average (1 min) {min(loads):.1f} to {max(loads):.1f}"
    )
    print(f"{'request':<18} {'readers (ms)':>13} {'in-process (ms)':>16} {'ratio':>7}")
    for key in results[2]:
        sub = statistics.median(results[2][key]) * 1e3
        inproc = statistics.median(results[0][key]) * 1e3
        print(f"{key:<18} {sub:>13.1f} {inproc:>16.1f} {sub / inproc:>7.2f}")


if __name__ == "__main__":
    main()
