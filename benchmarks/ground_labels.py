"""Ground-stage labels and CPU time of this tree against another checkout.

Runs one ground stage (default ``ground.nist``, default parameters, the stage
alone) on a set of cases in fresh processes, once with this tree and once with
``--baseline DIR`` (a checkout of another commit), alternated, and prints per
case whether the labels are bit-identical and the median CPU seconds of each
(``--runs``). A speed-up that must not change any label is checked with it::

    python benchmarks/ground_labels.py --baseline ../other-checkout --runs 3
    python benchmarks/ground_labels.py --baseline DIR --cases samp61,samp11,rural_slope:4

Cases: ``speed`` (``make_scene(790, 8)``, the speed row's tile), ``sampNN`` (an
ISPRS sample at its own density; ``sampNN@job`` at the density a job passes),
``FAMILY:SEED`` (a scene of ``terrasift.synthetic.rural.FAMILIES``). The ISPRS
samples are read from ``../shared/data/isprs``; missing ones are skipped.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from two_trees import alternate  # noqa: E402

DATA = ROOT / ".." / "shared" / "data"
DEFAULT_CASES = (
    "speed,samp11,samp12,samp31,samp52,samp61,samp11@job,samp61@job,"
    "railway_yard:0,railway_yard:104,railway_yard:206,railway_yard:618,railway_yard:721,"
    "rural_slope:0,rural_slope:2,rural_slope:4,rural_slope:6,rural_slope:523"
)

# One run in a fresh process: the code of argv[1], labels written to argv[2], points
# and density from argv[3], stage argv[4]; CPU seconds of the run printed.
WORKER = (
    "import sys, time; sys.path.insert(0, sys.argv[1]); import numpy as np;"
    "from terrasift.workers import registry;"
    "st = registry.get_stage(sys.argv[4]); d = np.load(sys.argv[3]); xyz = d['xyz'];"
    "over = {'density': float(d['density'])} if float(d['density']) > 0 else {};"
    "p = st.params.preset('default', **over); st.run(xyz[:20000], p);"
    "c = time.process_time(); g = st.run(xyz, p); t = time.process_time() - c;"
    "np.save(sys.argv[2], np.asarray(g, dtype=bool)); print(t)"
)


def _points(case: str) -> tuple[np.ndarray, float] | None:
    """The (n, 3) points of ``case`` and the density to pass (0: the stage's own)."""
    if case == "speed":
        from terrasift.synthetic.terrain import make_scene

        return make_scene(size=790, density=8).xyz, 0.0
    if case.startswith("samp"):
        import laspy

        name, _, how = case.partition("@")
        path = DATA / "isprs" / f"{name}.laz"
        if not path.exists():
            return None
        las = laspy.read(str(path))
        xyz = np.column_stack([las.x, las.y, las.z]).astype(np.float64)
        if how != "job":
            return xyz, 0.0
        from ground_accuracy import job_density

        return xyz, job_density(xyz)
    from terrasift.synthetic import rural

    family, seed = case.split(":")
    return rural.FAMILIES[family](int(seed)).xyz, 0.0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--baseline", required=True, help="checkout of another commit")
    ap.add_argument("--cases", default=DEFAULT_CASES)
    ap.add_argument("--runs", type=int, default=1, help="alternated runs per tree (CPU medians)")
    ap.add_argument("--stage", default="ground.nist")
    a = ap.parse_args()
    base = Path(a.baseline).resolve()
    same_all = True
    print(
        f"{'case':<20} {'points':>9} {'labels':>10} {'ground':>9} {'CPU this':>9} {'baseline':>9} {'ratio':>6}"
    )
    with tempfile.TemporaryDirectory(prefix="ground-labels-") as tmp:
        for case in a.cases.split(","):
            pts = _points(case)
            if pts is None:
                print(f"{case:<20} not found: skipped")
                continue
            scene = Path(tmp) / "scene.npz"
            np.savez(scene, xyz=pts[0], density=pts[1])
            pair = alternate(WORKER, ROOT, base, Path(tmp), a.runs, str(scene), a.stage)
            same_all &= pair.same
            g = pair.ours
            print(
                f"{case:<20} {len(g):>9} {pair.verdict:>10} {g.mean():>9.4f} "
                f"{pair.cpu_ours:>9.2f} {pair.cpu_theirs:>9.2f} {pair.ratio:>6.3f}",
                flush=True,
            )
    print("all labels identical" if same_all else "LABELS DIFFER")
    sys.exit(0 if same_all else 1)


if __name__ == "__main__":
    main()
