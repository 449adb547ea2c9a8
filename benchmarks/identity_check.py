"""Fingerprints of whole jobs, to show a refactoring leaves behaviour unchanged.

Runs ``terrasift process`` (in this process, through ``terrasift.cli.process``,
which every layout of the package keeps) on a few synthetic scenes and on the
ISPRS samples, and prints one JSON document: per job, a SHA-256 of the
classified LAZ's classes and points, of every raster's array (with its
transform, CRS and nodata), of every GeoJSON and of ``report.json`` and
``item.json`` without their timings and timestamps. Run it before and after a
change and compare:

    python benchmarks/identity_check.py --out before.json
    ... change ...
    python benchmarks/identity_check.py --out after.json --compare before.json

``--only NAME`` runs the jobs whose name contains NAME. The ISPRS samples are
read from ``$TERRASIFT_SHARED_DATA/isprs`` (default ``../shared/data``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

#: the ISPRS samples (DATA_DIR/isprs/samp*.laz); a missing folder skips them
DATA_DIR = Path(os.environ.get("TERRASIFT_SHARED_DATA", REPO.parent / "shared" / "data"))

#: report fields that measure time or name the machine's folders, not behaviour
VOLATILE_REPORT = ("timings_seconds", "points_per_second")


def _sha(*parts: bytes) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p)
    return h.hexdigest()[:16]


def _scenes(folder: Path) -> dict[str, tuple[list[Path], dict]]:
    """Job name -> (input files, parameters)."""
    from terrasift.synthetic.slopes import forest_on_slopes, ground_based, steep_hillside
    from terrasift.synthetic.terrain import Scene, make_scene, write_las

    def write(name: str, scene: Scene) -> Path:
        return write_las(scene, folder / f"{name}.laz")

    jobs: dict[str, tuple[list[Path], dict]] = {}
    town = make_scene(160, 6.0, seed=11)
    jobs["town"] = ([write("town", town)], {"block_size": 80})
    jobs["town-ptd"] = (
        [folder / "town.laz"],
        {"block_size": 80, "ground": "ptd", "ground.preset": "conservative"},
    )
    two = make_scene(200, 4.0, seed=12)
    left = two.xyz[:, 0] < two.bounds[0] + 90
    halves = []
    for k, keep in enumerate((left, ~left)):
        part = Scene(
            two.xyz[keep],
            two.truth[keep],
            two.return_number[keep],
            two.number_of_returns[keep],
            two.surface,
            two.bounds,
            {},
        )
        halves.append(write(f"two-{k}", part))
    jobs["two-tiles"] = (halves, {"block_size": 80, "features": "ditch,ridge,flat"})
    jobs["hillside"] = ([write("hillside", steep_hillside(120, 6.0))], {"block_size": 60})
    jobs["forest-ptd-always"] = (
        [write("forest", forest_on_slopes(120, 6.0))],
        {"block_size": 60, "ground": "ptd", "rotation": "always"},
    )
    jobs["sparse"] = ([write("sparse", make_scene(240, 1.0, seed=13))], {"block_size": 120})
    scan, origin = ground_based(radius=30.0, near_density=60.0)
    jobs["ground-based"] = (
        [write("scan", scan)],
        {"block_size": 40, "sensor_origin": ",".join(f"{v:.3f}" for v in origin)},
    )
    for path in sorted((DATA_DIR / "isprs").glob("samp*.laz")):
        jobs[f"isprs-{path.stem}"] = ([path], {"crs": "EPSG:32632"})
    return jobs


def fingerprint(out: Path) -> dict[str, str]:
    """Hashes of every output in folder ``out``."""
    import laspy
    import numpy as np
    import rasterio

    prints: dict[str, str] = {}
    for path in sorted(out.iterdir()):
        name = path.name
        if name.endswith(".laz"):
            las = laspy.read(path)
            prints[name + ":classes"] = _sha(np.asarray(las.classification).tobytes())
            prints[name + ":points"] = _sha(
                np.asarray(las.X).tobytes(),
                np.asarray(las.Y).tobytes(),
                np.asarray(las.Z).tobytes(),
            )
        elif name.endswith(".tif"):
            with rasterio.open(path) as ds:
                prints[name] = _sha(
                    ds.read().tobytes(),
                    repr(tuple(ds.transform)).encode(),
                    (ds.crs.to_wkt() if ds.crs else "").encode(),
                    repr(ds.nodata).encode(),
                )
        elif name == "report.json":
            report = json.loads(path.read_text())
            for key in VOLATILE_REPORT:
                report.pop(key, None)
            for key, value in sorted(report.items()):
                prints[f"report:{key}"] = _sha(json.dumps(value, sort_keys=True).encode())
        elif name == "item.json":
            item = json.loads(path.read_text())
            for key in ("datetime", "created"):
                item["properties"].pop(key, None)
            prints[name] = _sha(json.dumps(item, sort_keys=True).encode())
        elif name.endswith(".geojson") or name.endswith(".json"):
            prints[name] = _sha(json.dumps(json.loads(path.read_text()), sort_keys=True).encode())
        elif name.endswith(".gpkg"):  # its bytes carry the time it was written
            import pyogrio

            for layer, _ in pyogrio.list_layers(path):
                _, _, geometry, fields = pyogrio.raw.read(path, layer=layer)
                prints[f"{name}:{layer}"] = _sha(
                    *(np.asarray(g).tobytes() for g in geometry),
                    *(np.asarray(f).astype(str).tobytes() for f in fields),
                )
        else:
            prints[name] = _sha(path.read_bytes())
    return prints


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, help="write the fingerprints here (JSON)")
    ap.add_argument("--compare", type=Path, help="fingerprints of an earlier run to compare with")
    ap.add_argument("--only", default="", help="run the jobs whose name contains this")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--keep", type=Path, help="write the jobs' outputs under this folder")
    args = ap.parse_args()

    from terrasift.cli import process

    result: dict[str, dict[str, str]] = {}
    with tempfile.TemporaryDirectory(prefix="identity-") as tmp:
        folder = Path(tmp)
        for name, (inputs, params) in _scenes(folder).items():
            if args.only not in name:
                continue
            t = time.perf_counter()
            out = (args.keep or folder / "out") / name  # the same job name on every run
            process(inputs, out, {**params, "workers": args.workers}, progress=False)
            result[name] = fingerprint(out)
            print(
                f"{name}: {len(result[name])} outputs, {time.perf_counter() - t:.1f} s",
                file=sys.stderr,
            )
    text = json.dumps(result, indent=1, sort_keys=True)
    if args.out:
        args.out.write_text(text + "\n")
    else:
        print(text)
    if args.compare:
        before = json.loads(args.compare.read_text())
        differ = 0
        for name, prints in result.items():
            old = before.get(name)
            if old is None:
                print(f"{name}: not in {args.compare.name}")
                continue
            keys = sorted(set(prints) | set(old))
            bad = [k for k in keys if prints.get(k) != old.get(k)]
            differ += bool(bad)
            print(
                f"{name}: {'identical' if not bad else 'DIFFERS in ' + ', '.join(bad)} ({len(keys)} fingerprints)"
            )
        return 1 if differ else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
