"""Accuracy (and speed) of every ground method (the choices of the ``ground``
job parameter) with its default parameters.

    python benchmarks/ground_accuracy.py [--only PARTS] [--method ground.nist] [--baseline DIR]
        [--seeds 300-311] [--family railway_yard]

PARTS (comma list; default all but ``shifted``): isprs, loo, moved, topo,
synthetic, families, jobs, blocks, speed; ``shifted`` is the translation half of
``moved`` alone.

Data: the five ISPRS reference samples (class 2 = ground), lidR's Topography.laz
against the provider's ground (class 2; water, class 9, is left out of the
score because the provider labels it neither ground nor object), and the
synthetic scenes of ``terrasift.synthetic.slopes`` (truth class 2). The steep
hillside is run twice more with ``bin_fit`` level and plane. ``speed`` times
``classify_ground`` on ``make_scene(size=790, density=8)`` (~5.6 M points).
``shifted`` (not in the default run: 8× the ISPRS work) scores the ISPRS
samples again with the data moved by a few metres: a translation changes no
terrain, only where the bins of each pass fall, so the spread it causes is the
part of a score that is luck of the grid.
``loo`` is leave-one-out over the five samples: for each sample, the
parameter set (the defaults or one of ``CANDIDATES``, every change that was
considered) with the best mean kappa on the other four is scored on it; a
change that helps one sample and costs another does not survive.
``moved`` scores every sample under the translations of ``shifted`` and under
rotations by 90, 180 and 270 degrees about its centre.
``families`` draws 12 scenes (seeds 100-111, then 200-211) of each family of
``terrasift.synthetic.rural`` (railway yards and parked rows, rural slopes with
low vegetation) and prints
the worst case, 10th percentile and median, and the seeds where the issue's
figure (Type II <= 5 %, Type I <= 3 %) fails, scoring the stage alone on the
points' x, y, z (``--seeds`` and ``--family``: other seed ranges, one family).
A failing seed is listed with
its Type II split by the plant its wrong ground returns came from (shrubs, hedges,
scrub; shares of all object points).
``jobs`` scores the same scenes through the whole job: each written as a LAS
tile with its return numbers (the families write a second, last return from
the ground under vegetation taller than the scene's dead zone) and processed
alone, so the job's low-vegetation rule (``ground.lowveg``: echoes, then local
roughness where echoes show vegetation) counts as on real data that carries
returns.
``blocks`` cuts each ISPRS sample and two family scenes into 2 x 2 blocks with
the stage's halo and compares the labels of each block's core with one run
over the whole tile (share of core points labelled alike, overall and within
20 m of a block edge).
``speed`` with ``--baseline DIR`` (a checkout of another commit, e.g. from
``git worktree add``) also times that commit's code on the same tile in a
subprocess, alternated, and prints the ratio of medians.
Real data is looked up in ``../shared/data`` next to the repository and
skipped with a note when missing.
"""

from __future__ import annotations

import argparse
import inspect
import sys
import time
import typing
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from two_trees import run_code  # noqa: E402

from terrasift.metrics import ground_score  # noqa: E402
from terrasift.synthetic import rural, slopes  # noqa: E402
from terrasift.synthetic.terrain import make_scene  # noqa: E402
from terrasift.tiling.blocks import occupancy_cell, occupied_cells, occupied_density  # noqa: E402
from terrasift.workers import registry  # noqa: E402

DATA = ROOT / ".." / "shared" / "data"
SMRF_KAPPA = {"samp11": 79.9, "samp12": 94.1, "samp31": 93.2, "samp52": 74.9, "samp61": 85.5}


def _read(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import laspy

    las = laspy.read(str(path))
    return np.column_stack([las.x, las.y, las.z]).astype(np.float64), np.asarray(las.classification)


def _row(name: str, s, seconds: float, note: str = "") -> str:
    p = s.as_percent()
    return (
        f"{name:<22} {s.n:>8} {p['type1']:>7.2f} {p['type2']:>7.2f} {p['total']:>7.2f} "
        f"{p['kappa']:>7.2f} {s.n / seconds / 1e3:>8.0f}  {note}"
    )


HEADER = f"{'data':<22} {'points':>8} {'typeI%':>7} {'typeII%':>7} {'total%':>7} {'kappa%':>7} {'kpts/s':>8}  (CPU time, one process)"


def _run(stage, xyz, sensor_origin=None, window=None, **over):
    params = stage.params.preset("default", **over)
    kw = {} if sensor_origin is None else {"sensor_origin": sensor_origin}
    if window is not None:
        kw["window"] = window
    t, c = time.perf_counter(), time.process_time()
    g = stage.run(xyz, params, **kw)
    _run.wall = time.perf_counter() - t
    return g, time.process_time() - c  # CPU seconds: the machine may be shared


def job_density(xyz: np.ndarray) -> float:
    """The density a job passes to the ground stage for this one tile: points
    per m² of occupied area, cells two header spacings wide (``jobs/run.py``)."""
    n = xyz.shape[0]
    header = n / max(float(np.prod(np.ptp(xyz[:, :2], axis=0))), 1.0)
    cell = occupancy_cell(header)
    return occupied_density(n, [occupied_cells(xyz[:, 0], xyz[:, 1], cell)], cell)


def isprs(stage) -> None:
    files = sorted((DATA / "isprs").glob("samp*.laz"))
    if not files:
        print("ISPRS samples not found: skipped")
        return
    # "job density": the stage is given the density a job measures while sharding.
    common = "density" in stage.params.model_fields
    print(
        f"\n== {stage.id}: ISPRS samples (reference class 2)\n{HEADER}"
        + ("  job density: kappa%" if common else "")
    )
    kap, tot, kap_job = [], [], []
    for f in files:
        xyz, cls = _read(f)
        g, sec = _run(stage, xyz)
        s = ground_score(cls == 2, g)
        kap.append(s.kappa)
        tot.append(s.total)
        smrf = SMRF_KAPPA.get(f.stem)
        note = f"SMRF {smrf}: {'beats' if 100 * s.kappa > smrf else 'BELOW'}" if smrf else ""
        if common:
            d = job_density(xyz)
            kj = ground_score(cls == 2, _run(stage, xyz, density=d)[0]).kappa
            kap_job.append(kj)
            note += f"  {100 * kj:.2f} ({d:.4f} pts/m²)"
        print(_row(f.stem, s, sec, note))
    print(
        f"{'mean':<22} {'':>8} {'':>7} {'':>7} {100 * np.mean(tot):>7.2f} {100 * np.mean(kap):>7.2f}"
        + (f"  job density {100 * np.mean(kap_job):.2f}" if common else "")
    )


def topo(stage) -> None:
    f = DATA / "lidr" / "Topography.laz"
    if not f.exists():
        print("Topography.laz not found: skipped")
        return
    xyz, cls = _read(f)
    g, sec = _run(stage, xyz)
    keep = cls != 9
    s = ground_score(cls[keep] == 2, g[keep])
    print(f"\n== {stage.id}: Topography.laz vs provider ground (class 9 water excluded)\n{HEADER}")
    print(_row("Topography", s, sec, f"water points called ground: {g[~keep].mean():.1%}"))


def synthetic(stage) -> None:
    print(f"\n== {stage.id}: synthetic scenes (200 m, 8 pts/m², truth class 2)\n{HEADER}")
    for name, make in slopes.SCENES.items():
        sc = make()
        g, sec = _run(stage, sc.xyz)
        print(_row(name, ground_score(sc.is_ground, g), sec))
        if name == "steep_hillside" and "bin_fit" in stage.params.model_fields:
            for fit in ("level", "plane"):
                g, sec = _run(stage, sc.xyz, bin_fit=fit)
                print(_row(f"  bin_fit={fit}", ground_score(sc.is_ground, g), sec))
    for dens in (1.0, 20.0):
        sc = make_scene(200, dens, seed=5)
        g, sec = _run(stage, sc.xyz)
        print(_row(f"make_scene {dens:g} pts/m²", ground_score(sc.is_ground, g), sec))
    if "ring_step_deg" not in stage.params.model_fields:
        return
    # Ground-based scans: density ∝ 1/range²; the sensor origin picks the concentric grid.
    for near in (100.0, 400.0):
        sc, origin = slopes.ground_based(near_density=near)
        g, sec = _run(stage, sc.xyz, sensor_origin=origin)
        print(
            _row(
                f"scan {near:g}/m² near",
                ground_score(sc.is_ground, g),
                sec,
                "concentric grid (sensor origin)",
            )
        )
        g, sec = _run(stage, sc.xyz, grid="regular")
        print(_row("  grid=regular", ground_score(sc.is_ground, g), sec))


# Translations (m) of the ISPRS samples for ``shifted``: none, then offsets that
# are not multiples of the bin sizes in use (1.5 to 25 m).
SHIFTS = (
    (0.0, 0.0),
    (5.0, 0.0),
    (0.0, 5.0),
    (11.0, 7.0),
    (17.0, 13.0),
    (3.3, 21.1),
    (29.0, 2.0),
    (40.0, 40.0),
)

# Every parameter change considered for ground.nist (one override set each),
# kept so ``loo`` re-judges all of them: a fold may only pick among these.
CANDIDATES: dict[str, list[dict]] = {
    "ground.nist": [
        {"screen_tol": 0.7},
        {"screen_tol": 0.8},
        {"screen_tol": 1.0},
        {"grow_bend_down": 5.0},
        {"grow_bend_down": 10.0},
        {"raised_step": 0.5},
        {"ground_tol_cell": 0.1},
        {"grow_peak_area": 10.0},
        {"ground_slope": 0.5},
        {"ground_slope": 0.0},
        {"support_k": 0},
        {"screen_tol": 0.5},
        {"snap_cells": False},
        {"raised_relative": True},
        {"raised_slope": 20.0},
        {"raised_walls": 0.0},
        {"raised_walls": 0.34},
        {"raised_walls": 0.67},
        {"raised_rise": 0.0},
        {"raised_rise": 0.5},
        {"raised_rise": 1.0},
        {"raised_rim": 0.0},
        {"raised_rim": 3.0},
        {"raised_rim": 6.0},
        {"grow_agree": 0.34},
        {"grow_agree": 0.5},
        {"grow_agree": 0.67},
        {"mask": True},
        {"vote_phases": 1},
        {"vote_phases": 4},
        {"vote_phases": 4, "grow_share": 0.3},
        {"bin_phases": 2},
        {"plateau_step": 0.0},
        {"plateau_step": 1.0},
        {"plateau_share": 0.5},
        {"vote_share": 0.75},
        {"vote_weight": "centre"},
        {"vote_weight": "centre", "vote_share": 0.3},
        {"rough_k": 0},
        {"rough_k": 32},
        {"rough_k": 64},
        {"rough_factor": 4.0},
        {"rough_factor": 6.0},
        {"grow_reach": 6.0},
        {"mow_share": 0.25},
        {"grow_share": 0.25},
        {"grow_phases": 2},
        {"rough_envelope": True, "rough_factor": 6.0},
        {"rough_shrub": 0.2},
        {"rough_shrub": 0.2, "rough_near": 2},
        {"rough_shrub": 0.2, "rough_sectors": 8, "rough_near": 2},
        {"rough_half": 0},
        {"rough_half_curve": 0},
        {"rough_fit": 0},
        # The close fit as it was before its guards followed the rural family's scrub.
        {
            "rough_fit_local": 6.0,
            "rough_fit_step_plane": False,
            "rough_fit_clip_noise": 0.0,
            "rough_fit_ceiling": 0.8,
            "rough_fit_step_slope": 0.0,
        },
        {"rough_fit_local": 6.0},
        {"rough_fit_clip_noise": 0.0},
        {"rough_fit_step_plane": True},
        {"rough_fit_step_slope": 0.0},
        {"rough_fit_step_slope": 2.0},
        {"rough_fit_step_slope": 3.0},
        {"final_nodes": "square"},
        # Bins on absolute multiples of the cell (the default before bins followed the data).
        {"bin_anchor": "absolute"},
        {"grow_low": False},
        {"raised_over_walls": False},
        {"rough_edge": 0.0},
        {"rough_edge": 1.5},
        {"rough_edge": 3.0},
        {"rough_edge_density": 0.0},
        {"rough_edge_density": 0.5},
        {"rough_edge_slope": 10.0},
    ],
}


def _samples() -> list[tuple[str, np.ndarray, np.ndarray]]:
    files = sorted((DATA / "isprs").glob("samp*.laz"))
    return [(f.stem, *_read(f)) for f in files]


def _stats(values) -> str:
    v = np.asarray(values, dtype=float)
    return (
        f"worst {v.min():6.2f}  p10 {np.percentile(v, 10):6.2f}  median {np.median(v):6.2f}  "
        f"mean {v.mean():6.2f}  range {np.ptp(v):5.2f}"
    )


def loo(stage) -> None:
    samples = _samples()
    if not samples:
        print("ISPRS samples not found: skipped")
        return
    sets = [{}] + CANDIDATES.get(stage.id, [])
    names = [", ".join(f"{k}={v}" for k, v in o.items()) or "defaults" for o in sets]
    # kappa[i, j]: parameter set i on sample j
    kappa = np.array(
        [
            [
                100 * ground_score(cls == 2, _run(stage, xyz, **o)[0]).kappa
                for _, xyz, cls in samples
            ]
            for o in sets
        ]
    )
    print(f"\n== {stage.id}: ISPRS leave-one-out over {len(sets)} parameter sets (kappa %)")
    print(f"{'set':<34} " + " ".join(f"{n:>7}" for n, _, _ in samples) + f" {'mean':>7}")
    for name, row in zip(names, kappa, strict=True):
        print(f"{name[:34]:<34} " + " ".join(f"{k:>7.2f}" for k in row) + f" {row.mean():>7.2f}")
    held = []
    for j, (stem, _, _) in enumerate(samples):
        others = np.delete(kappa, j, axis=1).mean(axis=1)
        pick = int(np.argmax(others))
        held.append(kappa[pick, j])
        smrf = SMRF_KAPPA.get(stem)
        flag = "" if smrf is None else ("beats SMRF" if kappa[pick, j] > smrf else "BELOW SMRF")
        print(
            f"  held out {stem}: tuned on the others -> {names[pick]}: {kappa[pick, j]:.2f} {flag}"
        )
    print(f"  leave-one-out kappa: {_stats(held)}")


def _rotate(xyz: np.ndarray, quarter: int) -> np.ndarray:
    """``xyz`` rotated by ``quarter`` × 90 degrees about its bounding box centre."""
    c = (xyz[:, :2].min(axis=0) + xyz[:, :2].max(axis=0)) / 2
    u = xyz[:, :2] - c
    for _ in range(quarter % 4):
        u = np.column_stack([-u[:, 1], u[:, 0]])
    return np.column_stack([u + c, xyz[:, 2]])


def _moved(stage, moves: list[tuple[str, typing.Callable]]) -> None:
    samples = _samples()
    if not samples:
        print("ISPRS samples not found: skipped")
        return
    print(f"\n== {stage.id}: ISPRS kappa % with the data moved (terrain unchanged)")
    print(
        f"{'data':<8} "
        + " ".join(f"{n:>9}" for n, _ in moves)
        + f" {'median':>7} {'min':>7} {'range':>6}"
    )
    rows = []
    for stem, xyz, cls in samples:
        row = [100 * ground_score(cls == 2, _run(stage, m(xyz))[0]).kappa for _, m in moves]
        rows.append(row)
        print(
            f"{stem:<8} "
            + " ".join(f"{k:>9.2f}" for k in row)
            + f" {np.median(row):>7.2f} {min(row):>7.2f} {np.ptp(row):>6.2f}"
        )
    mean = np.mean(rows, axis=0)
    print(
        f"{'mean':<8} "
        + " ".join(f"{k:>9.2f}" for k in mean)
        + f" {np.median(mean):>7.2f} {mean.min():>7.2f} {np.ptp(mean):>6.2f}"
    )
    print(f"  mean kappa over moves: {_stats(mean)}; unmoved {mean[0]:.2f}")


def _shift(dx: float, dy: float) -> typing.Callable:
    return lambda xyz: xyz + np.array([dx, dy, 0.0])


def shifted(stage) -> None:
    _moved(stage, [(f"{dx:g},{dy:g}", _shift(dx, dy)) for dx, dy in SHIFTS])


def moved(stage) -> None:
    moves = [(f"{dx:g},{dy:g}", _shift(dx, dy)) for dx, dy in SHIFTS]
    moves += [(f"rot{90 * q}", lambda xyz, q=q: _rotate(xyz, q)) for q in (1, 2, 3)]
    _moved(stage, moves)


# Not the seeds the rules were tried on (0-99). Seeds 100-111 were later used to
# diagnose failures (103, 107), so 200-211 are kept as a second, untouched hold-out.
FAMILY_SEEDS = (range(100, 112), range(200, 212))
FAMILY_NAMES = tuple(rural.FAMILIES)


def _job_ground(scene, method: str) -> np.ndarray:
    """Ground labels of ``scene`` written as one LAS tile (with its return numbers)
    and processed alone through the whole job with ``ground=method``: blocks with
    halos, the ground stage, then the job's low-vegetation rule (echoes and local
    roughness) and low points, classified output."""
    import tempfile

    import laspy

    from terrasift import jobs as pipeline
    from terrasift.synthetic.terrain import write_las
    from terrasift.workers.executors import InlineExecutor

    with tempfile.TemporaryDirectory(prefix="bench-ground-") as tmp:
        tile = write_las(scene, Path(tmp) / "tile.las")
        job = Path(tmp) / "job"
        params = {"crs": "EPSG:32632", "ground": method.removeprefix("ground.")}
        pipeline.prepare_job(job, [tile], pipeline.validate_params(params))
        pipeline.run_job(job, InlineExecutor(), products="classified")
        out = laspy.read(pipeline.output_path(job, "classified.laz"))
        return np.asarray(out.classification) == 2


def _families(stage, through_job: bool) -> None:
    path = "whole job, return numbers written" if through_job else "stage alone, xyz only"
    print(
        f"\n== {stage.id}: scene families ({path}; 12 seeds each; "
        "figure: Type II <= 5 %, Type I <= 3 %; p90 = the worst tenth)"
    )
    print(HEADER)
    for (name, make), seeds in (
        (item, seeds)
        for seeds in FAMILY_SEEDS
        for item in rural.FAMILIES.items()
        if item[0] in FAMILY_NAMES
    ):
        name = f"{name} {seeds.start}-{seeds.stop - 1}"
        t1, t2, kap, fails = [], [], [], []
        for seed in seeds:
            sc = make(seed)
            g = _job_ground(sc, stage.id) if through_job else _run(stage, sc.xyz)[0]
            p = ground_score(sc.is_ground, g).as_percent()
            t1.append(p["type1"])
            t2.append(p["type2"])
            kap.append(p["kappa"])
            dens = len(sc) / ((sc.bounds[2] - sc.bounds[0]) * (sc.bounds[3] - sc.bounds[1]))
            multi = np.mean(sc.number_of_returns > 1)
            if p["type1"] > 3 or p["type2"] > 5:
                fails.append(
                    f"{seed} ({dens:.2f} pts/m², {100 * multi:.1f} % multi-return, "
                    f"I {p['type1']:.1f}, II {p['type2']:.1f}{_taken(sc, g)})"
                )
        for label, v in (("Type I ", t1), ("Type II", t2)):
            print(
                f"{name if label == 'Type I ' else '':<{len(name)}}  {label} worst {max(v):6.2f}  "
                f"p90 {np.percentile(v, 90):6.2f}  median {np.median(v):6.2f}"
            )
        print(f"{'':<{len(name)}}  kappa   {_stats(kap)}")
        print(f"{'':<{len(name)}}  fails: {', '.join(fails) or 'none'}")


def _taken(scene, ground: np.ndarray) -> str:
    """Which plants the Type II returns of ``scene`` came from (``rural``'s
    ``extra["vegetation"]``): points of Type II by kind, as a share of the object points."""
    plant = scene.extra.get("vegetation")
    if plant is None:
        return ""
    wrong = ground & ~scene.is_ground
    objects = max(int(np.count_nonzero(~scene.is_ground)), 1)
    parts = [
        f"{name} {100 * np.count_nonzero(wrong & (plant == k)) / objects:.1f}"
        for name, k in (("shrubs", rural.SHRUB), ("hedges", rural.HEDGE), ("scrub", rural.SCRUB))
    ]
    return "; of it " + ", ".join(parts)


def families(stage) -> None:
    _families(stage, through_job=False)


def jobs(stage) -> None:
    _families(stage, through_job=True)


def _block_agreement(stage, xyz: np.ndarray, **over) -> tuple[float, float, int]:
    """Share of points labelled alike by one run and by 2 × 2 blocks with the
    stage's halo (each block labels its core), overall and within 20 m of a block edge.
    Each block is told the box it was cut to when the stage takes ``window``."""
    windows = "window" in inspect.signature(stage.run).parameters
    lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    mid = (lo + hi) / 2
    area = float(np.prod(hi - lo))
    params = stage.params.preset("default")
    halo = max(params.halo(xyz.shape[0] / area), 20.0)
    whole = _run(stage, xyz, **over)[0]
    split = np.zeros_like(whole)
    qx, qy = xyz[:, 0] >= mid[0], xyz[:, 1] >= mid[1]
    for bx in (False, True):
        for by in (False, True):
            core = (qx == bx) & (qy == by)
            x0 = lo[0] if not bx else mid[0]
            x1 = mid[0] if not bx else hi[0]
            y0 = lo[1] if not by else mid[1]
            y1 = mid[1] if not by else hi[1]
            sub = (
                (xyz[:, 0] >= x0 - halo)
                & (xyz[:, 0] <= x1 + halo)
                & (xyz[:, 1] >= y0 - halo)
                & (xyz[:, 1] <= y1 + halo)
            )
            idx = np.flatnonzero(sub)
            # The box the block was cut to, for a stage that takes it (as a job's block does).
            box = (x0 - halo, y0 - halo, x1 + halo, y1 + halo) if windows else None
            g = _run(stage, xyz[idx], window=box, **over)[0]
            keep = core[idx]
            split[idx[keep]] = g[keep]
    near = (np.abs(xyz[:, 0] - mid[0]) < 20) | (np.abs(xyz[:, 1] - mid[1]) < 20)
    same = whole == split
    return 100 * same.mean(), 100 * same[near].mean(), int(np.count_nonzero(~same))


def blocks(stage) -> None:
    # "job density": every run (the whole tile and each block) is given the
    # density a job measures while sharding (``job_density``) instead of
    # measuring its own (stages with a density field), as a job does.
    common = "density" in stage.params.model_fields
    print(f"\n== {stage.id}: labels of 2 x 2 blocks (stage halo) vs one run, % alike")
    print(
        f"{'data':<22} {'all':>7} {'<20 m':>7} {'differ':>7}"
        + ("   job density: all  <20 m" if common else "")
    )
    scenes = [(stem, xyz) for stem, xyz, _ in _samples()]
    scenes += [
        (f"{n} {s}", rural.FAMILIES[n](s).xyz)
        for n, s in (("railway_yard", 100), ("rural_slope", 101))
    ]
    worst, worst_common = 100.0, 100.0
    for name, xyz in scenes:
        a, near, k = _block_agreement(stage, xyz)
        worst = min(worst, a)
        row = f"{name:<22} {a:>7.2f} {near:>7.2f} {k:>7}"
        if common:
            job = {"density": job_density(xyz)}
            if "anchor" in stage.params.model_fields:
                # A job gives data-anchored bins the centre of its tiles' bounds.
                job["anchor"] = tuple((xyz[:, :2].min(axis=0) + xyz[:, :2].max(axis=0)) / 2)
            ca, cnear, _ = _block_agreement(stage, xyz, **job)
            worst_common = min(worst_common, ca)
            row += f"   {'':>12} {ca:>5.2f} {cnear:>6.2f}"
        print(row)
    print(
        f"  worst agreement {worst:.2f} %"
        + (f"; job density {worst_common:.2f} %" if common else "")
    )


SPEED_CODE = (
    "import sys, time; sys.path.insert(0, sys.argv[1]);"
    "from terrasift.synthetic.terrain import make_scene;"
    "from terrasift.workers import registry;"
    "st = registry.get_stage(sys.argv[2]); sc = make_scene(size=790, density=8);"
    "p = st.params.preset('default'); st.run(sc.xyz[:20000], p);"
    "c = time.process_time(); st.run(sc.xyz, p); print(len(sc) / (time.process_time() - c))"
)


def speed(stage, baseline: str = "", runs: int = 3) -> None:
    sc = make_scene(size=790, density=8)
    g, sec = _run(stage, sc.xyz)
    print(f"\n== {stage.id}: speed, make_scene(790, 8): {len(sc):,} points")
    print(HEADER)
    print(
        _row("tile", ground_score(sc.is_ground, g), sec, f"{sec:.1f} s CPU, {_run.wall:.1f} s wall")
    )
    if not baseline:
        return
    # Alternated runs in fresh processes (same compile cache state): this tree vs the baseline.
    ours, base = [], []
    for _ in range(runs):
        ours.append(run_code(ROOT, SPEED_CODE, stage.id))
        base.append(run_code(Path(baseline).resolve(), SPEED_CODE, stage.id))
    print(
        f"  this tree {np.median(ours) / 1e3:.0f} k points/s, baseline {np.median(base) / 1e3:.0f} k "
        f"(medians of {runs}, alternated): ratio {np.median(ours) / np.median(base):.3f}"
    )


PARTS = (
    "isprs",
    "loo",
    "moved",
    "topo",
    "synthetic",
    "families",
    "jobs",
    "blocks",
    "speed",
    "shifted",
)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", default=",".join(PARTS[:-1]))
    ap.add_argument("--method", default="")
    ap.add_argument("--baseline", default="", help="checkout of another commit for speed ratios")
    ap.add_argument(
        "--seeds",
        default="",
        help="families/jobs: seed ranges instead of 100-111,200-211 (300-311)",
    )
    ap.add_argument("--family", default="", help="families/jobs: one family only (railway_yard)")
    a = ap.parse_args()
    global FAMILY_SEEDS, FAMILY_NAMES
    if a.seeds:
        FAMILY_SEEDS = tuple(
            range(int(r.split("-")[0]), int(r.split("-")[-1]) + 1) for r in a.seeds.split(",")
        )
    if a.family:
        FAMILY_NAMES = (a.family,)
    parts = a.only.split(",")
    # The ground methods are the choices of the job parameter; other stages
    # under "ground." (low points, the steepness test) take other arguments.
    methods = registry.ground_methods()
    for stage in (registry.get_stage(f"ground.{m}") for m in methods):
        if a.method and stage.id != a.method:
            continue
        for part in PARTS:
            if part in parts:
                if part == "speed":
                    speed(stage, a.baseline)
                else:
                    globals()[part](stage)


if __name__ == "__main__":
    main()
