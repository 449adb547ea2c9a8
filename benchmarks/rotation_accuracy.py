"""Rotated classification on cliffs, its cost on flat blocks, and its effect on ISPRS.

    python benchmarks/rotation_accuracy.py [--method ground.nist] [--square 130] [--density 8]
        [--no-isprs] [--no-cost]

``--method`` is the ground stage (``ground.ptd`` or ``ground.nist``; default the
job default, ``terrasift.jobs.params.DEFAULT_GROUND``). Every run goes through the
registry stage as a block does (``terrasift.workers.block._ground``): the
method's default preset on the block, the steepness test on its ground, and on
a steep block the rotation parameters of the method (``RotationParams.presets``,
e.g. 45° and the default labels kept for ground.nist; the seed's settings for
ground.ptd) with ``ground_preset`` for the rotated runs, seeded with the labels
found so far only where the stage takes a ``seed_mask`` (ground.ptd). Isolated
low points are not taken out here.

Cliff scene (``terrasift.synthetic.cliffs``): Type I on ground of faces steeper
than 60°, Type I/II overall, share of covered ground found (under the lip),
for the unrotated conservative/aggressive/default filters, rotation with the
seed's settings (``RotationParams()``: 30°, nine conservative runs; seeded
where the method can) and the block's flow (``auto``).
Cost: steepness test vs a default run of the method on a flat block, and a
steep block (steepness + rotation) vs a flat block of similar point count, for
the ground alone and for the whole block task (``ground=<method>``). ISPRS:
mean kappa of the method (default) with and without rotation=auto, where the
steepness test runs on the unrotated ground (the seed's step 1 preliminary
classification).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from terrasift.workers.executors import single_threaded_blas  # noqa: E402

single_threaded_blas()  # as in the workers; CPU times otherwise count BLAS threads spinning

import numpy as np  # noqa: E402

from terrasift.jobs.params import DEFAULT_GROUND, stage_params  # noqa: E402
from terrasift.metrics import ground_score  # noqa: E402
from terrasift.synthetic.cliffs import make_cliffs  # noqa: E402
from terrasift.synthetic.terrain import make_scene  # noqa: E402
from terrasift.workers.ground.rotation import (  # noqa: E402
    RotationParams,
    SteepParams,
    bind_ground,
    can_seed,
    classify_rotated,
    steepness,
)
from terrasift.workers.registry import get_stage  # noqa: E402

METHOD = f"ground.{DEFAULT_GROUND}"


def ground(preset: str, method: str | None = None, seeded: bool = False):
    """The registry stage ``method`` bound to its ``preset``: ``f(points)``, or
    with ``seeded`` ``f(points, known)`` (None when the stage cannot seed)."""
    stage = get_stage(method or METHOD)
    plain, seed = bind_ground(stage, stage.params.preset(preset))
    return seed if seeded else plain


def rotation_runs(**rotation) -> tuple[RotationParams, object, object]:
    """Rotation parameters (the method's preset, ``rotation`` on top) and the
    ground runs a steep block uses (block.py)."""
    rp = stage_params(
        {f"ground.rotation.{k}": v for k, v in rotation.items()}, "ground.rotation", METHOD
    )
    return rp, ground(rp.ground_preset), ground(rp.ground_preset, seeded=True)


def auto(xyz: np.ndarray, **rotation) -> tuple[np.ndarray, dict]:
    """The block flow: the default method, steepness on its ground; if steep, an
    unrotated and eight rotated runs with ``ground_preset`` OR'ed (seeded where
    the method can; with ``rerun_unrotated=False``, the default labels instead
    of the first), with the method's rotation preset and ``rotation`` on top."""
    t0 = time.perf_counter()
    g = ground("default")(xyz)
    t1 = time.perf_counter()
    test = steepness(xyz[g], SteepParams())
    t2 = time.perf_counter()
    info = {"ground_s": t1 - t0, "steep_s": t2 - t1, "share": test.facet_share, "steep": test.steep}
    if test.steep:
        rp, plain, seeded = rotation_runs(**rotation)
        res = classify_rotated(
            xyz,
            plain,
            rp,
            unrotated=None if rp.rerun_unrotated else g,
            seeded=seeded,
        )
        g = res.is_ground
        info["added"] = res.added
    info["total_s"] = time.perf_counter() - t0
    return g, info


def row(name: str, scene, pred: np.ndarray, seconds: float) -> None:
    core = scene.extra["core"]
    t = scene.is_ground[core]
    pred = pred[core]
    steep = scene.extra["steep"][core]
    cov = scene.extra["covered"][core]
    sc = ground_score(t, pred).as_percent()
    t1_steep = 100.0 * np.count_nonzero(steep & ~pred) / max(np.count_nonzero(steep), 1)
    found_cov = 100.0 * np.count_nonzero(cov & pred) / max(np.count_nonzero(cov), 1)
    print(
        f"{name:28} {t1_steep:10.2f} {sc['type1']:7.2f} {sc['type2']:8.2f} {sc['kappa']:7.2f} {found_cov:9.1f} {seconds:7.1f}"
    )


def cliffs(square: float, density: float, buffer: float) -> None:
    """A block of side ``square`` plus a ``buffer`` halo, as the spine cuts it;
    scores count the core only (the halo is another block's core)."""
    scene = make_cliffs(length=200.0, density=density, seed=3, square=square + 2 * buffer)
    xy = scene.xyz[:, :2]
    centre = 0.5 * (xy.min(axis=0) + xy.max(axis=0))
    scene.extra["core"] = np.all(np.abs(xy - centre) <= square / 2, axis=1)
    n_steep = int((scene.extra["steep"] & scene.extra["core"]).sum())
    print(
        f"cliff block: {len(scene)} points ({square:.0f} m core + {buffer:.0f} m halo), "
        f"{int(scene.extra['core'].sum())} in the core, {n_steep} core ground points on faces > 60°"
    )
    print(
        f"{'run':28} {'TypeI>60%':>10} {'TypeI%':>7} {'TypeII%':>8} {'kappa%':>7} {'covered%':>9} {'s':>7}"
    )
    for preset in ("default", "conservative", "aggressive"):
        t = time.perf_counter()
        g = ground(preset)(scene.xyz)
        row(f"unrotated {preset}", scene, g, time.perf_counter() - t)
    t = time.perf_counter()
    res = classify_rotated(scene.xyz, ground("conservative"), RotationParams())
    row("rotated, all conservative", scene, res.is_ground, time.perf_counter() - t)
    print(f"  added per direction N..NW: {res.added}")
    if can_seed(get_stage(METHOD)):
        t = time.perf_counter()
        res = classify_rotated(
            scene.xyz,
            ground("conservative"),
            RotationParams(),
            seeded=ground("conservative", seeded=True),
        )
        row("rotated conservative, seeded", scene, res.is_ground, time.perf_counter() - t)
        print(f"  added per direction N..NW: {res.added}")
    else:
        print(f"  ({METHOD} takes no seed_mask: no seeded rotated runs)")
    g, info = auto(scene.xyz)
    row("auto (the block's flow)", scene, g, info["total_s"])
    print(f"  steep share {info['share']:.3f}, added {info.get('added')}")
    g, info = auto(scene.xyz, rerun_unrotated=False)
    row("auto, default labels kept", scene, g, info["total_s"])


def cost() -> None:
    flat = make_scene(size=130, density=8, seed=5)
    xyz = flat.xyz
    t = time.perf_counter()
    g = ground("default")(xyz)
    t_ground_run = time.perf_counter() - t
    t = time.perf_counter()
    for _ in range(5):
        steepness(xyz, SteepParams())
    t_raw = (time.perf_counter() - t) / 5
    t = time.perf_counter()
    for _ in range(5):
        test = steepness(xyz[g], SteepParams())
    t_ground = (time.perf_counter() - t) / 5
    print(
        f"flat block {len(flat)} pts: {METHOD} {t_ground_run:.2f} s; steepness on all points {t_raw:.3f} s "
        f"({100 * t_raw / t_ground_run:.1f} %), on its ground {t_ground:.3f} s "
        f"({100 * t_ground / t_ground_run:.1f} %), "
        f"share {test.facet_share:.3f} steep={test.steep}"
    )

    # CPU seconds, median of 3: other processes share the machine's cores.
    def cpu(points: np.ndarray) -> tuple[float, dict]:
        times, info = [], {}
        for _ in range(3):
            t0 = time.process_time()
            _, info = auto(points)
            times.append(time.process_time() - t0)
        return float(np.median(times)), info

    t_flat, info_flat = cpu(xyz)
    steep_scene = make_cliffs(length=200.0, density=8, seed=6, square=130.0)
    t_steep, info = cpu(steep_scene.xyz)
    ratio = (t_steep / len(steep_scene)) / (t_flat / len(flat))
    print(
        f"auto flat block {len(flat)} pts {t_flat:.2f} s CPU (steep={info_flat['steep']}); "
        f"auto steep block {len(steep_scene)} pts {t_steep:.2f} s CPU (steep={info['steep']}); "
        f"per-point cost ratio {ratio:.1f}x (medians of 3)"
    )
    # The whole block task (ground, low points, vegetation, DTM/DSM, classes).
    b_flat, s_flat = block_cpu(flat.xyz)
    b_steep, s_steep = block_cpu(steep_scene.xyz)
    ratio = (b_steep / len(steep_scene)) / (b_flat / len(flat))
    print(
        f"block task: flat {b_flat:.2f} s CPU (steep={s_flat}), steep {b_steep:.2f} s CPU (steep={s_steep}); "
        f"per-point cost ratio {ratio:.1f}x (medians of 3)"
    )


def block_cpu(xyz: np.ndarray) -> tuple[float, bool]:
    """CPU seconds (median of 3) of the block task on ``xyz`` as one block with
    default parameters, and whether it was found steep."""
    from terrasift.jobs import validate_params
    from terrasift.jobs.params import block_models
    from terrasift.tiling.blocks import SHARD_DTYPE, BlockGrid
    from terrasift.workers.block import classify_block

    pts = np.zeros(xyz.shape[0], dtype=SHARD_DTYPE)
    pts["x"], pts["y"], pts["z"] = xyz.T
    pts["index"] = np.arange(xyz.shape[0])
    pts["core"] = 1
    pts["return_number"] = pts["number_of_returns"] = 1
    mins, maxs = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    span = float(np.max(maxs - mins)) + 2.0
    grid = BlockGrid.over(tuple(mins), tuple(maxs), 1.0, block_size=span, buffer=0.0)
    models = block_models(validate_params({"ground": METHOD.removeprefix("ground.")}))
    density = xyz.shape[0] / float(np.prod(maxs - mins))
    times, steep = [], False
    for _ in range(3):
        t0 = time.process_time()
        result = classify_block(pts, grid, 0, 0, models, density)
        times.append(time.process_time() - t0)
        steep = bool(result.stats["steep"].get("steep"))
    return float(np.median(times)), steep


def isprs() -> None:
    from ptd_accuracy import ISPRS, load_isprs

    if not ISPRS.is_dir():
        print(f"ISPRS samples not found at {ISPRS}: skipped")
        return
    k0, k1, k2 = [], [], []
    print(f"{'sample':8} {'kappa off':>10} {'kappa auto':>10} {'share':>6} steep")
    for name, (xyz, truth) in load_isprs().items():
        g0 = ground("default")(xyz)
        g1, info = auto(xyz)
        g2, _ = auto(xyz, rerun_unrotated=False)
        k2.append(100 * ground_score(truth, g2).kappa)
        a = 100 * ground_score(truth, g0).kappa
        b = 100 * ground_score(truth, g1).kappa
        k0.append(a)
        k1.append(b)
        print(f"{name:8} {a:10.2f} {b:10.2f} {info['share']:6.3f} {info['steep']}")
    print(
        f"{'mean':8} {np.mean(k0):10.2f} {np.mean(k1):10.2f}  difference {np.mean(k1) - np.mean(k0):+.2f}"
    )
    print(
        f"default labels kept: mean kappa {np.mean(k2):.2f}, difference {np.mean(k2) - np.mean(k0):+.2f}"
    )


def main() -> None:
    global METHOD
    ap = argparse.ArgumentParser()
    ap.add_argument(
        "--square", type=float, default=130.0, help="side of the block cut from the cliff scene"
    )
    ap.add_argument("--density", type=float, default=8.0)
    ap.add_argument(
        "--buffer", type=float, default=20.0, help="halo around the block (spine default 20 m)"
    )
    ap.add_argument("--no-isprs", action="store_true")
    ap.add_argument("--no-cost", action="store_true")
    ap.add_argument(
        "--method",
        default=METHOD,
        choices=["ground.ptd", "ground.nist"],
        help=f"ground stage (default {METHOD})",
    )
    args = ap.parse_args()
    METHOD = args.method
    print(f"ground method {METHOD}")
    cliffs(args.square, args.density, args.buffer)
    if not args.no_cost:
        cost()
    if not args.no_isprs:
        isprs()


if __name__ == "__main__":
    main()
