"""Accuracy and speed of categories + feature filters (ROBUSTNESS.md applied to Sjövall).

Parts (``--part``):

``job``
    The family of ``terrasift.synthetic.feature_family`` through the whole job:
    pulses written as LAS, ``terrasift process`` (ground filter, DTM, categories
    on the mosaicked DTM, all built-in filters), ``features.native.geojson``
    scored against the exact truth. Report seeds by default (``--seeds``): 32-47
    (0-15 and then 16-31 were the report seeds until causes were looked for on
    them; they are kept for comparison, no longer held out).
``dtm``
    The same family handed in as a DTM directly (the exact surface on the 0.5 m
    grid plus the scene's noise): no ground filter, fast; the tuning part
    (``--tune-seeds``), kept apart from the report seeds.
``scene``
    The older single-layout scene (``make_feature_scene``: a 16 % hillside with
    cones, ridges, ditches, ponds, roads and a field) as a DTM, three seeds.
``kept``
    Scores the features kept by earlier ``job --keep DIR`` runs (``--keep DIR``),
    so seeds run in several processes are summarised together.
``rerun``
    This code's filters re-run on the DTMs kept by earlier ``job --keep DIR``
    runs (``--keep DIR``): the objects of a filter change without running the
    ground filter again (the job's DTM is the same; categories and filters are
    run on the whole DTM, as the job does on a scene narrower than a feature
    square).
``rerun-sparse``, ``rerun-rough``
    ``rerun`` on the DTMs kept by ``sparse`` / ``rough`` runs with ``--keep DIR``
    (``--sparse-seeds`` / ``--rough-seeds``); every detection but a flat area on
    naturally flat ground is false.
``sparse``
    The counter-case family (``make_sparse_scene``): plain fields of 0-12 %
    scanned at 0.15-0.6 pulses/m^2 with 3-10 cm of noise, no object, through
    the whole job; every detection but a flat area on naturally flat ground
    is false. Report seeds 0-11 (``--sparse-seeds``), tuning seeds 100-111.
``rough``
    The second counter-case family (``make_rough_scene``, drawn after ISPRS
    samp11): steep slopes of 15-55 % carrying hummocks (0.15-0.6 m RMS,
    wavelengths 6-30 m), 0.3-3 pulses/m^2, 2-8 cm of noise, no object, through
    the whole job. Report seeds 0-11 (``--rough-seeds``), tuning seeds 100-111.
``speed``
    Categories (the 2 m grid and the 1 m-step grid the road filter runs on)
    and all built-in filters on a 1 km^2 DTM (2000 x 2000 cells of 0.5 m), one
    core, in CPU seconds. Target <= 10 s.

Scoring, per kind (ditch, ridge, hill, pond, road, flat-area). A detection
*lies on* a truth object of its kind when at least half its area is inside the
truth polygon grown by one tile (2 m); a truth object is *found* when the
detections lying on it cover at least half of its area (grown by one tile)
or one of them is at least half its length (a ridge's crest band, a hill's
outline);
its length error is that of the largest detection lying on it, so an object
found in pieces scores the piece's length. A flat-area detection that lies on
no field is still correct when the flat-area definition holds on the exact
surface under it: at least 90 % of its tiles lie in 100 m windows with at most
5 % non-flat tiles of the noise-free surface's categories (naturally flat
ground). A field's truth is the flat area the definition gives around it on the
exact surface (the flat-area filter on the noise-free categories, when its object
covers at least half the field): a field levelled on a slope that is itself flat by
the category definition (under 0.2 m relief per 2 m tile, i.e. below about 9-13 %)
is one flat area with that hillside. Recall = found / truth,
precision = correct detections / detections, per scene; the table gives the
worst case, the 10th percentile and the median over scenes holding the kind
(scenes with no detection of a kind have no precision for it).

Run: PYTHONPATH=. python benchmarks/features_accuracy.py [--part job kept rerun rerun-sparse rerun-rough
     sparse rough dtm scene speed]
     [--seeds 32 .. 47] [--tune-seeds 100 .. 111] [--rough-seeds 0 .. 11] [--workers 1]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from rasterio import Affine  # noqa: E402
from rasterio.features import geometry_mask  # noqa: E402
from scipy import ndimage  # noqa: E402
from shapely.affinity import translate  # noqa: E402
from shapely.geometry import shape  # noqa: E402
from shapely.ops import unary_union  # noqa: E402

from terrasift.synthetic.feature_family import (  # noqa: E402
    make_family_scene,
    make_rough_scene,
    make_sparse_scene,
    point_scene,
    surface_raster,
)
from terrasift.synthetic.features import make_feature_scene  # noqa: E402
from terrasift.workers.categories import CategoryParams, compute_categories  # noqa: E402
from terrasift.workers.features import (  # noqa: E402
    builtin_filter_names,
    categories_for,
    detect_features,
    load_filter,
)

KINDS = ("ditch", "ridge", "hill", "pond", "road", "flat-area")
ORIGIN = (500_000.0, 5_400_000.0)
TILE = 2.0


# --------------------------------------------------------------------------- scoring


def _flat_tiles(surface: np.ndarray, cell: float) -> np.ndarray:
    """Where the flat-area definition holds on the exact surface: tiles inside a
    window of the flat-area filter passing on the noise-free categories."""
    return _flat_definition(surface, cell, None)[0]


def _flat_definition(
    surface: np.ndarray, cell: float, transform: Affine | None
) -> tuple[np.ndarray, list]:
    """The flat-area definition on the exact surface: the tiles it covers (``_flat_tiles``)
    and, with the surface's ``transform``, the objects the flat-area filter makes of the
    noise-free categories (the flat areas the definition gives there)."""
    from terrasift.workers.features import connect, resolve_lengths

    cats = compute_categories(surface, cell, CategoryParams(noise=0))
    flat = (cats.inclination == 0) & (cats.orientation == 0) & (cats.state == 0)
    flt = load_filter("flat-area")
    r = resolve_lengths(flt, cats.tile_size).rectangle
    cover = connect.rectangle_cover(flat, r.width, r.height, r.error)
    if transform is None:
        return cover, []
    return cover, detect_features(cats, [flt], transform, cats.tile_size).objects


def field_truth(truth: list, flat_objects: list) -> list:
    """``truth`` with each field (flat-area truth) replaced by the flat area the definition
    gives on the exact surface around it: the flat-area object covering most of the field,
    when it covers at least half of it. A field levelled on a slope that is itself flat by
    the category definition (under 0.2 m relief per tile: below about 9-13 % on 2 m tiles,
    by the slope's direction) is one flat area with that hillside, as long as the
    definition's object, not the field alone."""
    from terrasift.synthetic.features import TruthFeature

    out = []
    for t in truth:
        if t.kind == "flat-area" and flat_objects:
            best = max(flat_objects, key=lambda o: o.geometry.intersection(t.polygon).area)
            if best.geometry.intersection(t.polygon).area >= 0.5 * t.polygon.area:
                t = TruthFeature("flat-area", best.geometry, float(best.length_m))
        out.append(t)
    return out


def score_scene(truth, detections, flat_exact: np.ndarray | None, tile_transform: Affine) -> dict:
    """Per kind: (n_truth, n_found, n_det, n_correct, [length errors of found objects])."""
    out = {}
    for kind in KINDS:
        tr = [t for t in truth if t.kind == kind]
        det = [(g, length) for k, g, length in detections if k == kind]
        grown = [t.polygon.buffer(TILE) for t in tr]
        lies_on = [
            [i for i, gt in enumerate(grown) if g.intersection(gt).area >= 0.5 * g.area]
            for g, _ in det
        ]
        correct = 0
        for (g, _), on in zip(det, lies_on, strict=True):
            if on:
                correct += 1
            elif kind == "flat-area" and flat_exact is not None:
                inside = ~geometry_mask([g], flat_exact.shape, tile_transform, all_touched=False)
                if inside.any() and flat_exact[inside].mean() >= 0.9:
                    correct += 1
        found, errors = 0, []
        for i, t in enumerate(tr):
            mine = [det[j] for j, on in enumerate(lies_on) if i in on]
            if not mine:
                continue
            cover = unary_union([g.buffer(TILE) for g, _ in mine]).intersection(grown[i]).area
            longest = max(length for _, length in mine)
            if cover >= 0.5 * grown[i].area or longest >= 0.5 * t.length_m:
                found += 1
                g, length = max(mine, key=lambda d: d[0].area)
                errors.append(abs(length - t.length_m) / t.length_m)
        out[kind] = (len(tr), found, len(det), correct, errors)
    return out


def summarise(rows: list[tuple[str, dict]], title: str) -> None:
    """Worst case, 10th percentile and median of recall, precision and length error per kind."""
    print(f"\n{title}: {len(rows)} scenes")
    print(
        f"{'kind':<10} {'truth':>5} {'found':>5} {'det':>5}   "
        f"{'recall worst/p10/median':>24}   {'precision worst/p10/median':>27}   "
        f"{'length err worst/p90/median':>28}"
    )
    fails = []
    for kind in KINDS:
        rec, prec, errs = [], [], []
        nt = nf = nd = 0
        for label, sc in rows:
            t, f, d, c, e = sc[kind]
            nt, nf, nd = nt + t, nf + f, nd + d
            if t:
                rec.append(f / t)
                if f < t:
                    fails.append(f"{kind}: {label} found {f}/{t}")
            if d:
                prec.append(c / d)
                if c / d < 0.8:
                    fails.append(f"{kind}: {label} precision {c}/{d}")
            errs += e
            fails += [f"{kind}: {label} length error {x:.0%}" for x in e if x > 0.25]

        def stats(v, worst_low=True):
            if not v:
                return "-"
            a = np.asarray(v)
            if worst_low:
                return f"{a.min():.2f} / {np.percentile(a, 10):.2f} / {np.median(a):.2f}"
            return f"{a.max():.0%} / {np.percentile(a, 90):.0%} / {np.median(a):.0%}"

        print(
            f"{kind:<10} {nt:>5} {nf:>5} {nd:>5}   {stats(rec):>24}   {stats(prec):>27}   "
            f"{stats(errs, False):>28}"
        )
    print("where it breaks (recall < 1, precision < 0.8, length error > 25 %):")
    for f in fails:
        print("  " + f)


# --------------------------------------------------------------------------- parts


def scene_truth(scene) -> tuple[list, np.ndarray, Affine]:
    """What a scene is scored against: its truth in map coordinates with each field
    taken as the definition's flat area around it (``field_truth``), the tiles where the
    flat-area definition holds on the exact surface, and the tile grid's transform."""
    exact = surface_raster(scene, 0.5)
    tt = Affine(TILE, 0, ORIGIN[0], 0, -TILE, ORIGIN[1] + scene.size)
    cell_t = Affine(0.5, 0, ORIGIN[0], 0, -0.5, ORIGIN[1] + scene.size)
    cover, objects = _flat_definition(exact, 0.5, cell_t)
    return field_truth(_shifted_truth(scene), objects), cover, tt


def _shifted_truth(scene):
    from terrasift.synthetic.features import TruthFeature

    return [TruthFeature(t.kind, translate(t.polygon, *ORIGIN), t.length_m) for t in scene.truth]


def run_job_scene(
    seed: int, workers: int, keep: Path | None, make=make_family_scene
) -> tuple[str, dict, float]:
    from terrasift.cli import process
    from terrasift.synthetic.terrain import write_las

    scene = make(seed)
    pts = point_scene(scene, ORIGIN)
    tmp = Path(tempfile.mkdtemp(prefix="features-job-"))
    try:
        las = write_las(pts, tmp / f"scene{seed}.laz", scale=scene.las_scale)
        t = time.perf_counter()
        process([las], tmp / "out", {"workers": workers}, progress=False)
        seconds = time.perf_counter() - t
        fc = json.loads((tmp / "out" / "features.native.geojson").read_text())
        if keep is not None:
            keep.mkdir(parents=True, exist_ok=True)
            shutil.copy(tmp / "out" / "features.native.geojson", keep / f"scene{seed}.geojson")
            shutil.copy(tmp / "out" / "dtm.tif", keep / f"scene{seed}_dtm.tif")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    dets = [
        (f["properties"]["kind"], shape(f["geometry"]), f["properties"]["length_m"])
        for f in fc["features"]
    ]
    truth, flat, tt = scene_truth(scene)
    sc = score_scene(truth, dets, flat, tt)
    return scene.describe(), sc, seconds


def score_kept_scene(seed: int, keep: Path, make=make_family_scene) -> tuple[str, dict]:
    """Score the features a ``--part job --keep`` run kept for ``seed`` (no job is run)."""
    scene = make(seed)
    fc = json.loads((keep / f"scene{seed}.geojson").read_text())
    dets = [
        (f["properties"]["kind"], shape(f["geometry"]), f["properties"]["length_m"])
        for f in fc["features"]
    ]
    truth, flat, tt = scene_truth(scene)
    return scene.describe(), score_scene(truth, dets, flat, tt)


def rerun_kept_scene(seed: int, keep: Path, make=make_family_scene) -> tuple[str, dict]:
    """Score this code's filters on the DTM a ``--part job --keep`` run kept for ``seed``."""
    import rasterio

    scene = make(seed)
    with rasterio.open(keep / f"scene{seed}_dtm.tif") as ds:
        dtm = ds.read(1, masked=True).filled(np.nan).astype(np.float64)
        transform = ds.transform
    filters = [load_filter(n) for n in builtin_filter_names()]
    cats, stepped = categories_for(dtm, abs(transform.a), filters)
    res = detect_features(cats, filters, transform, cats.tile_size, stepped=stepped, dtm=dtm)
    dets = [(f.kind, f.geometry, f.length_m) for f in res.objects]
    truth, flat, tt = scene_truth(scene)
    return scene.describe(), score_scene(truth, dets, flat, tt)


def part_rerun(seeds: list[int], keep: Path, make=make_family_scene) -> None:
    rows = []
    for s in seeds:
        label, sc = rerun_kept_scene(s, keep, make)
        rows.append((label, sc))
        brief = ", ".join(
            f"{k} {v[1]}/{v[0]} ({v[3]}/{v[2]})" for k, v in sc.items() if v[0] or v[2]
        )
        print(f"{label}: {brief or 'none'}", flush=True)
    summarise(rows, f"this code's filters on the job DTMs kept in {keep}")
    if make is not make_family_scene:  # a counter-case family: every detection is false
        print("false detections per kind (total, scenes with any):")
        for kind in KINDS:
            false = [sc[kind][2] - sc[kind][3] for _, sc in rows]
            print(f"  {kind:<10} {sum(false):4d} {sum(1 for f in false if f):4d} of {len(rows)}")


def part_kept(seeds: list[int], keep: Path) -> None:
    rows = [score_kept_scene(s, keep) for s in seeds]
    summarise(rows, f"whole job, features kept in {keep}")


def part_sparse(
    seeds: list[int],
    workers: int,
    keep: Path | None,
    make=make_sparse_scene,
    title: str = "counter-case family, sparse fields with no object, through the whole job",
) -> None:
    """A counter-case family through the whole job: no object in any scene, so every
    detection but a flat area on naturally flat ground is false."""
    rows = []
    for s in seeds:
        label, sc, seconds = run_job_scene(s, workers, keep, make)
        rows.append((label, sc))
        brief = ", ".join(f"{k} {v[3]}/{v[2]}" for k, v in sc.items() if v[2])
        print(f"{label} [{seconds:.0f} s]: correct/detections {brief or 'none'}", flush=True)
    summarise(rows, title)
    print("false detections per kind (total, scenes with any):")
    for kind in KINDS:
        false = [sc[kind][2] - sc[kind][3] for _, sc in rows]
        print(f"  {kind:<10} {sum(false):4d} {sum(1 for f in false if f):4d} of {len(rows)}")


def run_dtm_scene(seed: int) -> tuple[str, dict]:
    scene = make_family_scene(seed)
    exact = surface_raster(scene, 0.5)
    rng = np.random.default_rng([7, seed])
    dtm = exact + rng.normal(0, scene.noise, exact.shape)
    tt = Affine(0.5, 0, ORIGIN[0], 0, -0.5, ORIGIN[1] + scene.size)
    filters = [load_filter(n) for n in builtin_filter_names()]
    cats, stepped = categories_for(dtm, 0.5, filters)
    res = detect_features(cats, filters, tt, cats.tile_size, stepped=stepped, dtm=dtm)
    dets = [(f.kind, f.geometry, f.length_m) for f in res.objects]
    flat, objects = _flat_definition(exact, 0.5, tt)
    sc = score_scene(field_truth(_shifted_truth(scene), objects), dets, flat, cats.transform(tt))
    return scene.describe(), sc


def part_job(seeds: list[int], workers: int, keep: Path | None) -> None:
    rows = []
    for s in seeds:
        label, sc, seconds = run_job_scene(s, workers, keep)
        rows.append((label, sc))
        brief = ", ".join(
            f"{k} {v[1]}/{v[0]} ({v[3]}/{v[2]})" for k, v in sc.items() if v[0] or v[2]
        )
        print(f"{label} [{seconds:.0f} s]: {brief}", flush=True)
    summarise(rows, "whole job (LAS -> terrasift process -> features.native.geojson)")


def part_dtm(seeds: list[int], title: str) -> None:
    rows = []
    for s in seeds:
        label, sc = run_dtm_scene(s)
        rows.append((label, sc))
        brief = ", ".join(
            f"{k} {v[1]}/{v[0]} ({v[3]}/{v[2]})" for k, v in sc.items() if v[0] or v[2]
        )
        print(f"{label}: {brief}", flush=True)
    summarise(rows, title)


def part_scene(seeds: list[int]) -> None:
    filters = [load_filter(n) for n in builtin_filter_names()]
    rows = []
    for seed in seeds:
        scene = make_feature_scene(seed=seed)
        cats, stepped = categories_for(scene.dtm, scene.cell, filters)
        res = detect_features(
            cats, filters, scene.transform, cats.tile_size, stepped=stepped, dtm=scene.dtm
        )
        dets = [(f.kind, f.geometry, f.length_m) for f in res.objects]
        rows.append(
            (f"hillside seed {seed}", score_scene(scene.truth, dets, None, Affine.identity()))
        )
    summarise(rows, "single-layout hillside scene as a DTM")


def speed() -> None:
    scene = make_feature_scene(size=1000.0, seed=1)
    run_speed("synthetic feature terrain", scene.dtm, scene.cell, scene.transform)
    # a harder case for the search: rough random terrain, every tile inclined somewhere
    rng = np.random.default_rng(0)
    rough = ndimage.gaussian_filter(rng.normal(0, 1, scene.dtm.shape), 6) * 40
    run_speed("rough random terrain", rough, scene.cell, scene.transform)


def run_speed(label: str, dtm, cell: float, transform) -> None:
    filters = [load_filter(n) for n in builtin_filter_names()]
    t0 = time.process_time()
    cats, stepped = categories_for(dtm, cell, filters)
    t1 = time.process_time()
    times = {}
    for f in filters:
        s = time.process_time()
        res = detect_features(cats, [f], transform, cats.tile_size, stepped=stepped, dtm=dtm)
        times[f.name] = (time.process_time() - s, len(res.objects))
    t2 = time.process_time()
    print(
        f"\nspeed, {label}: {dtm.shape[0]}x{dtm.shape[1]} cells -> {cats.shape[0]}x{cats.shape[1]} tiles (1 core, CPU seconds: the machine may be shared)"
    )
    print(f"  categories        {t1 - t0:6.2f} s")
    for name, (t, n) in times.items():
        print(f"  filter {name:10s} {t:6.2f} s   {n:5d} objects")
    print(f"  total             {t2 - t0:6.2f} s   (target <= 10 s)")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--part", nargs="+", default=["job", "dtm", "scene", "speed"])
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(32, 48)))
    ap.add_argument("--tune-seeds", type=int, nargs="+", default=list(range(100, 112)))
    ap.add_argument("--sparse-seeds", type=int, nargs="+", default=list(range(12)))
    ap.add_argument("--rough-seeds", type=int, nargs="+", default=list(range(12)))
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--keep", type=Path, default=None, help="copy each job's features and DTM here")
    args = ap.parse_args()
    if "job" in args.part:
        part_job(args.seeds, args.workers, args.keep)
    if "kept" in args.part:  # several job runs (e.g. seeds split over processes) scored together
        if args.keep is None:
            ap.error("--part kept needs --keep DIR")
        part_kept(args.seeds, args.keep)
    if "rerun" in args.part:  # this code's filters on DTMs kept by earlier job runs
        if args.keep is None:
            ap.error("--part rerun needs --keep DIR")
        part_rerun(args.seeds, args.keep)
    for fam, seeds, make in (
        ("sparse", args.sparse_seeds, make_sparse_scene),
        ("rough", args.rough_seeds, make_rough_scene),
    ):
        if f"rerun-{fam}" in args.part:  # the same on a counter-case family's kept DTMs
            if args.keep is None:
                ap.error(f"--part rerun-{fam} needs --keep DIR")
            part_rerun(seeds, args.keep, make)
    if "sparse" in args.part:  # counter-case family: tune on 100-111, report on 0-11
        part_sparse(args.sparse_seeds, args.workers, args.keep)
    if "rough" in args.part:  # counter-case family: tune on 100-111, report on 0-11
        part_sparse(
            args.rough_seeds,
            args.workers,
            args.keep,
            make_rough_scene,
            "counter-case family, rough steep hummocky slopes with no object, whole job",
        )
    if "dtm" in args.part:
        part_dtm(args.tune_seeds, "DTM handed in directly (tuning seeds)")
    if "scene" in args.part:
        part_scene([0, 1, 2])
    if "speed" in args.part:
        speed()
