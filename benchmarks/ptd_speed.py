"""Per-block speed of ``ground.ptd`` on the benchmark tile, against a git ref.

Cuts ``--blocks`` blocks of ``--block`` m plus a ``--buffer`` m halo (as the
pipeline does) from a LAZ tile, and times ``classify_ground`` of this tree and
of ``ground/ptd.py`` as it is at ``--against`` (default ``main``), alternating,
medians over ``--runs``. Prints per-block seconds, the ratio old/new and how
far the labels differ.

    python benchmarks/ptd_speed.py [--tile bench-out/bench-760m.laz] [--blocks 4]
                                   [--runs 3] [--against main] [--preset default]
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from terrasift.workers.executors import single_threaded_blas  # noqa: E402

single_threaded_blas()  # in-process stages run as in a worker: one BLAS thread

import numpy as np  # noqa: E402

from terrasift.workers.ground import ptd  # noqa: E402


def load_ref(ref: str):
    """``terrasift.workers.ground.ptd`` as it is at git ``ref``, as a separate module."""
    src = subprocess.run(
        ["git", "show", f"{ref}:terrasift/workers/ground/ptd.py"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    # The registry refuses a second "ground.ptd": register the old one under another id.
    src = src.replace('@register("ground.ptd"', '@register("ground.ptd_ref"')
    path = Path(tempfile.mkdtemp(prefix="ptd-ref-")) / "ptd_ref.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("ptd_ref", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def cut_blocks(tile: Path, block: float, buffer: float, count: int) -> list[np.ndarray]:
    """``count`` blocks (core + halo) spread over the tile, in the pipeline's point order."""
    import laspy

    las = laspy.read(str(tile))
    xyz = np.column_stack([las.x, las.y, las.z]).astype(np.float64)
    lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    nx = max(int((hi[0] - lo[0]) // block), 1)
    ny = max(int((hi[1] - lo[1]) // block), 1)
    cells = [(i, j) for j in range(ny) for i in range(nx)]
    pick = np.linspace(0, len(cells) - 1, min(count, len(cells))).round().astype(int)
    out = []
    for k in pick:
        i, j = cells[k]
        x0, y0 = lo[0] + i * block - buffer, lo[1] + j * block - buffer
        sel = (xyz[:, 0] >= x0) & (xyz[:, 0] < x0 + block + 2 * buffer)
        sel &= (xyz[:, 1] >= y0) & (xyz[:, 1] < y0 + block + 2 * buffer)
        b = xyz[sel]
        out.append(b[np.lexsort((b[:, 2], b[:, 1], b[:, 0]))])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tile", type=Path, default=ROOT / "bench-out" / "bench-760m.laz")
    ap.add_argument("--block", type=float, default=200.0)
    ap.add_argument("--buffer", type=float, default=20.0)
    ap.add_argument("--blocks", type=int, default=4)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--against", default="main", help="git ref of the baseline ('' : no baseline)")
    ap.add_argument("--preset", default="default")
    args = ap.parse_args()
    if not args.tile.exists():
        sys.exit(f"no tile at {args.tile}: make it with benchmarks/pipeline_speed.py")
    blocks = cut_blocks(args.tile, args.block, args.buffer, args.blocks)
    impls = {"new": ptd}
    if args.against:
        impls = {"old": load_ref(args.against), "new": ptd}
    times = {k: [[] for _ in blocks] for k in impls}
    labels = {}
    for _ in range(args.runs):
        for b, xyz in enumerate(blocks):
            for name, mod in impls.items():
                params = mod.PtdParams.preset(args.preset)
                t = time.perf_counter()
                labels[name, b] = mod.classify_ground(xyz, params)
                times[name][b].append(time.perf_counter() - t)
    print(f"preset {args.preset}; medians over {args.runs} runs")
    head = f"{'block':>5} {'points':>9}" + "".join(
        f" {k + ' s':>8} {k + ' kpt/s':>10}" for k in impls
    )
    if "old" in impls:
        head += f" {'old/new':>8} {'ground old':>10} {'ground new':>10} {'differ%':>8}"
    print(head)
    tot = {k: 0.0 for k in impls}
    npts = 0
    for b, xyz in enumerate(blocks):
        n = xyz.shape[0]
        npts += n
        med = {k: statistics.median(times[k][b]) for k in impls}
        row = f"{b:>5} {n:>9}"
        for k in impls:
            tot[k] += med[k]
            row += f" {med[k]:>8.2f} {n / med[k] / 1e3:>10.0f}"
        if "old" in impls:
            lo, ln = labels["old", b], labels["new", b]
            row += f" {med['old'] / med['new']:>8.2f} {lo.sum():>10} {ln.sum():>10} {100 * np.mean(lo != ln):>8.2f}"
        print(row)
    row = f"{'all':>5} {npts:>9}" + "".join(
        f" {tot[k]:>8.2f} {npts / tot[k] / 1e3:>10.0f}" for k in impls
    )
    if "old" in impls:
        row += f" {tot['old'] / tot['new']:>8.2f}"
    print(row)


if __name__ == "__main__":
    main()
