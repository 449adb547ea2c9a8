"""Buildings, vegetation and noise through the whole job, against exact truth; CHM pits.

    python benchmarks/buildings_accuracy.py [--quick] [--only town|isprs|chm]

1. The synthetic town family (``terrasift.synthetic.town``): seeds × densities,
   flat and pitched roofs 5–100 m, trees over roofs, walls seen off nadir,
   isolated outliers. Each scene is written as LAZ and run as a job (blocks
   with halos, our own ground filter and DTM); the classified LAZ is scored:
   building precision and recall (class 6 against true roofs and walls), the
   share of true vegetation points called building, noise recall. Seeds 0–1
   were used while choosing the parameters; seeds from 2 on are the held-out
   part the worst case is reported on.
2. ISPRS samples: the share of reference object points (class 1: buildings,
   vegetation, bridges, outliers) labelled 6, and of reference ground labelled 6.
3. lidR MixedConifer: share of canopy cells of the CHM that are pits, for the
   CHM as DSM − DTM (the former output) and the pit-free CHM.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import laspy  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from terrasift import jobs  # noqa: E402
from terrasift.synthetic.terrain import write_las  # noqa: E402
from terrasift.synthetic.town import make_town, town_family  # noqa: E402
from terrasift.workers.executors import InlineExecutor  # noqa: E402

DATA = ROOT / ".." / "shared" / "data"
VEG = (3, 4, 5)


def run_job(tile: Path, work: Path, params: dict) -> Path:
    job = work / tile.stem
    jobs.prepare_job(job, [tile], jobs.validate_params(params))
    jobs.run_job(job, InlineExecutor())
    return job


def classes_of(job: Path) -> np.ndarray:
    return np.asarray(laspy.read(job / "outputs" / "classified.laz").classification)


def stats(values: list[float]) -> str:
    v = np.asarray(values)
    return f"worst {v.min() if v.size else np.nan:.4f}  p10 {np.percentile(v, 10):.4f}  median {np.median(v):.4f}"


def town(work: Path, seeds: list[int], densities: tuple[float, ...]) -> None:
    print("\n## town family (whole job, classified.laz against truth)")
    print("seed density points  precision  recall  veg->6  noise_recall  houses")
    rows = []
    for kw in town_family(seeds, densities):
        # Off the 200 m block grid: the town straddles block corners.
        scene = make_town(**kw, origin=(500_120.0, 5_400_130.0))
        tile = write_las(scene, work / f"town-{kw['seed']}-{kw['density']:g}.laz")
        job = run_job(tile, work, {})
        got = classes_of(job)
        truth = scene.truth
        tb, pb = truth == 6, got == 6
        precision = float((tb & pb).sum() / max(pb.sum(), 1))
        recall = float((tb & pb).sum() / max(tb.sum(), 1))
        veg = np.isin(truth, VEG)
        veg_b = float((veg & pb).sum() / max(veg.sum(), 1))
        nz = truth == 7
        noise_rec = float((nz & (got == 7)).sum() / max(nz.sum(), 1))
        sizes = scene.extra["houses"]
        rows.append((kw["seed"], kw["density"], precision, recall, veg_b, noise_rec))
        print(
            f"{kw['seed']:4d} {kw['density']:7g} {len(scene):6d}  {precision:.4f}  {recall:.4f}"
            f"  {veg_b:.4f}  {noise_rec:.4f}  {len(sizes)} ({sizes.min():.0f}-{sizes.max():.0f} m)",
            flush=True,
        )
    for part, keep in (
        ("tuning (seeds 0-1)", lambda r: r[0] < 2),
        ("held out", lambda r: r[0] >= 2),
    ):
        sel = [r for r in rows if keep(r)]
        if not sel:
            continue
        print(f"\n{part}, {len(sel)} scenes")
        print(f"  building precision   {stats([r[2] for r in sel])}")
        print(f"  building recall      {stats([r[3] for r in sel])}")
        v = np.asarray([r[4] for r in sel])
        print(
            f"  vegetation called 6  worst {v.max():.4f}  p90 {np.percentile(v, 90):.4f}  median {np.median(v):.4f}"
        )
        print(f"  noise recall         {stats([r[5] for r in sel])}")
        fail = [r for r in sel if r[2] < 0.95 or r[3] < 0.95 or r[4] > 0.02]
        print(
            "  fails (precision/recall < 0.95 or veg->6 > 2 %): "
            + (", ".join(f"seed {r[0]} density {r[1]:g}" for r in fail) or "none")
        )


def isprs(work: Path) -> None:
    print("\n## ISPRS samples (whole job; reference 1 = object, 2 = ground)")
    print("sample  objects  object->6  ground->6  object->veg")
    for name in ("samp11", "samp12", "samp31", "samp52", "samp61"):
        path = DATA / "isprs" / f"{name}.laz"
        if not path.exists():
            print(f"{name}: not found, skipped")
            continue
        job = run_job(path, work, {"crs": "EPSG:32632"})
        ref = np.asarray(laspy.read(path).classification)
        got = classes_of(job)
        obj, gnd = ref == 1, ref == 2
        print(
            f"{name}  {obj.sum():7d}  {(got[obj] == 6).mean():.4f}  {(got[gnd] == 6).mean():.4f}"
            f"  {np.isin(got[obj], VEG).mean():.4f}",
            flush=True,
        )


def pit_share(chm: np.ndarray, depth: float = 1.0, canopy: float = 2.0) -> tuple[float, int]:
    """Share of canopy cells (8-neighbour median > ``canopy``) lying more than
    ``depth`` below the median of their 8 neighbours."""
    from scipy import ndimage

    a = np.where(np.isfinite(chm), chm, np.nan)
    fp = np.ones((3, 3), bool)
    fp[1, 1] = False
    med = ndimage.generic_filter(a, np.nanmedian, footprint=fp, mode="constant", cval=np.nan)
    ok = np.isfinite(a) & np.isfinite(med) & (med > canopy)
    pits = ok & (a < med - depth)
    return float(pits.sum() / max(ok.sum(), 1)), int(ok.sum())


def hole_share(chm: np.ndarray, depth: float = 1.0, canopy: float = 2.0) -> tuple[float, int]:
    """Share of canopy cells (4-neighbour median > ``canopy``) lying more than
    ``depth`` below all four of their edge neighbours: a hole, where a gap
    between crowns is lower than two neighbours only."""
    a = np.where(np.isfinite(chm), chm, np.nan)
    p = np.pad(a, 1, constant_values=np.nan)
    nb = np.stack([p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]])
    ok = np.isfinite(a) & np.all(np.isfinite(nb), axis=0)
    ok &= np.median(np.where(ok, nb, 0), axis=0) > canopy
    holes = ok & (a < np.min(np.where(ok, nb, 0), axis=0) - depth)
    return float(holes.sum() / max(ok.sum(), 1)), int(ok.sum())


def chm_pits(work: Path) -> None:
    import rasterio

    print("\n## CHM pits on lidR MixedConifer (canopy cells more than 1 m below their neighbours)")
    path = DATA / "lidr" / "MixedConifer.laz"
    if not path.exists():
        print("MixedConifer.laz not found, skipped")
        return
    job = run_job(path, work, {})
    out = job / "outputs"
    with rasterio.open(out / "dsm.tif") as d, rasterio.open(out / "dtm.tif") as t:
        dsm = d.read(1, masked=True).filled(np.nan)
        dtm = t.read(1, masked=True).filled(np.nan)
    with rasterio.open(out / "chm.tif") as c:
        chm = c.read(1, masked=True).filled(np.nan)
        res = c.res[0]
    old = np.clip(dsm - dtm, 0, None)
    for label, fn in (
        ("8-neighbour median - 1 m", pit_share),
        ("all 4 edge neighbours - 1 m", hole_share),
    ):
        before, n0 = fn(old)
        after, n1 = fn(chm)
        print(
            f"{label}, {res} m cells: DSM - DTM {before:.4f} of {n0} canopy cells;"
            f" pit-free CHM {after:.4f} of {n1}"
        )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="4 seeds x 3 densities (1, 4, 16)")
    ap.add_argument("--only", choices=["town", "isprs", "chm"])
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--densities", type=str, default=None, help="comma list, pulses/m²")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if args.only in (None, "town"):
            seeds = list(
                range(args.first_seed, args.first_seed + (4 if args.quick else args.seeds))
            )
            densities = (1.0, 4.0, 16.0) if args.quick else (1.0, 2.0, 4.0, 8.0, 16.0)
            if args.densities:
                densities = tuple(float(d) for d in args.densities.split(","))
            town(work, seeds, densities)
        if args.only in (None, "isprs"):
            isprs(work)
        if args.only in (None, "chm"):
            chm_pits(work)


if __name__ == "__main__":
    main()
