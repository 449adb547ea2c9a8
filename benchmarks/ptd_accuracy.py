"""Accuracy and speed of ``ground.ptd``.

Accuracy: Type I/II, total error and kappa on the five ISPRS reference samples
(``../shared/data/isprs``, class 2 = ground), one parameter set for all.
Speed: points/s on one core on a synthetic airborne scene, whole and per block.

    python benchmarks/ptd_accuracy.py [--preset default] [--set key=value ...]
                                      [--speed SIZE] [--block METRES] [--no-isprs]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from terrasift.metrics import ground_score  # noqa: E402
from terrasift.synthetic.terrain import make_scene  # noqa: E402
from terrasift.workers.ground.ptd import PtdParams, classify_ground  # noqa: E402

ISPRS = ROOT / ".." / "shared" / "data" / "isprs"


def load_isprs() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    import laspy

    out = {}
    for f in sorted(ISPRS.glob("*.laz")):
        las = laspy.read(f)
        out[f.stem] = (np.column_stack([las.x, las.y, las.z]), np.asarray(las.classification) == 2)
    return out


def isprs_table(params: PtdParams, samples=None, quiet: bool = False) -> float:
    samples = samples if samples is not None else load_isprs()
    kappas = []
    if not quiet:
        print(
            f"{'sample':8} {'n':>7} {'TypeI%':>7} {'TypeII%':>8} {'total%':>7} {'kappa%':>7} {'s':>6}"
        )
    for name, (xyz, truth) in samples.items():
        t = time.perf_counter()
        pred = classify_ground(xyz, params)
        dt = time.perf_counter() - t
        sc = ground_score(truth, pred).as_percent()
        kappas.append(sc["kappa"])
        if not quiet:
            print(
                f"{name:8} {sc['n']:7d} {sc['type1']:7.2f} {sc['type2']:8.2f} {sc['total']:7.2f} {sc['kappa']:7.2f} {dt:6.2f}"
            )
    mean = float(np.mean(kappas))
    if not quiet:
        print(f"{'mean':8} {'':7} {'':7} {'':8} {'':7} {mean:7.2f}")
    return mean


def speed(params: PtdParams, size: float, block: float, repeats: int) -> None:
    scene = make_scene(size=size, density=8.0, seed=1)
    n = len(scene)
    print(f"scene {size:.0f} m, {n} points")
    x0, y0 = scene.bounds[:2]
    if block > 0:
        ix = np.floor((scene.xyz[:, 0] - x0) / block).astype(int)
        iy = np.floor((scene.xyz[:, 1] - y0) / block).astype(int)
        sel = (ix == 0) & (iy == 0)
        xyz, truth = scene.xyz[sel], scene.is_ground[sel]
        label = f"block {block:.0f} m"
    else:
        xyz, truth = scene.xyz, scene.is_ground
        label = "whole scene"
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        pred = classify_ground(xyz, params)
        times.append(time.perf_counter() - t)
    med = float(np.median(times))
    sc = ground_score(truth, pred).as_percent()
    print(
        f"{label}: {xyz.shape[0]} points, median {med:.2f} s over {repeats} -> {xyz.shape[0] / med / 1e3:.0f} k points/s; "
        f"TypeI {sc['type1']}% TypeII {sc['type2']}% kappa {sc['kappa']}%"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", action="append", default=[], help="key=value override")
    ap.add_argument("--speed", type=float, default=0.0, help="synthetic scene size in m (0: skip)")
    ap.add_argument(
        "--block", type=float, default=0.0, help="time one block of this size (0: whole scene)"
    )
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--no-isprs", action="store_true")
    args = ap.parse_args()
    overrides = {k: float(v) for k, v in (s.split("=", 1) for s in args.set)}
    params = PtdParams.preset(args.preset, **overrides)
    print(params.model_dump())
    if not args.no_isprs:
        if ISPRS.is_dir():
            isprs_table(params)
        else:
            print(f"ISPRS samples not found at {ISPRS}: accuracy skipped")
    if args.speed > 0:
        speed(params, args.speed, args.block, args.repeats)


if __name__ == "__main__":
    main()
