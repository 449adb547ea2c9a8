"""Mixed-stage marks and CPU time of this tree against another checkout.

Runs the mixed stage (default parameters: the grid method; ``--method box`` for the
interest boxes) alone on a set of scans in fresh processes, with this tree and with
``--baseline DIR`` (a checkout of another commit), alternated, with each return's GPS
time and without it, and prints per scan whether the marks are bit-identical and the
median CPU seconds of each (``--runs``). A speed-up that must not change any mark is
checked with it::

    python benchmarks/mixed_marks.py --baseline ../other-checkout --runs 3
    python benchmarks/mixed_marks.py --baseline DIR --cases speed,report:0,coarse:2001

Cases: ``speed`` (the 0.05° scan of ``mixed_accuracy.py``'s speed part) and
``FAMILY:SEED`` (a scene of ``mixed_accuracy.py``'s families: report, shared-report,
coarse, ...; several scan positions where the family has them).
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

DEFAULT_CASES = (
    "speed,report:0,report:1,report:2,report:7000,shared-report:4100,shared-report:4300,"
    "shared-report:4301,coarse:2000,coarse:2001,coarse:2002"
)

# One run in a fresh process: the code of argv[1], marks written to argv[2], the scan
# from argv[3], GPS time used when argv[4] is 1, method argv[5]; CPU seconds printed.
WORKER = (
    "import sys, time; sys.path.insert(0, sys.argv[1]); import numpy as np;"
    "from terrasift.workers.mixed import MixedParams, mark_mixed;"
    "d = np.load(sys.argv[3]); xyz = d['xyz']; o = d['origins'];"
    "ids = d['scan_id'] if o.shape[0] > 1 else None; o = o if o.shape[0] > 1 else o[0];"
    "t = d['gps_time'] if sys.argv[4] == '1' else None; p = MixedParams(method=sys.argv[5]);"
    "mark_mixed(xyz[:2000], p, o if ids is None else o[0]);"
    "c = time.process_time(); m = mark_mixed(xyz, p, o, ids, gps_time=t).marked;"
    "u = time.process_time() - c; np.save(sys.argv[2], m); print(u)"
)


def _scan(case: str) -> dict[str, np.ndarray]:
    """Points, scan positions, each point's position and GPS time of ``case``."""
    from mixed_accuracy import draw_scene, speed_scan

    if case == "speed":
        big = speed_scan()
        n = len(big.xyz)
        return dict(
            xyz=big.xyz,
            origins=np.asarray(big.origin, dtype=np.float64)[None, :],
            scan_id=np.zeros(n, dtype=np.int64),
            gps_time=big.gps_time,
        )
    family, seed = case.split(":")
    _, tile = draw_scene(int(seed), family)
    return dict(
        xyz=tile.xyz,
        origins=np.asarray(tile.origins, dtype=np.float64).reshape(-1, 3),
        scan_id=np.asarray(tile.scan_id, dtype=np.int64),
        gps_time=tile.gps_time,
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--baseline", required=True, help="checkout of another commit")
    ap.add_argument("--cases", default=DEFAULT_CASES)
    ap.add_argument("--runs", type=int, default=1, help="alternated runs per tree (CPU medians)")
    ap.add_argument("--method", default="grid", choices=("grid", "box"))
    ap.add_argument("--gps", choices=("both", "with", "without"), default="both")
    a = ap.parse_args()
    base = Path(a.baseline).resolve()
    gps_runs = {"both": (True, False), "with": (True,), "without": (False,)}[a.gps]
    same_all = True
    print(
        f"{'case':<20} {'GPS':>4} {'points':>8} {'marks':>10} {'marked':>7} "
        f"{'CPU this':>9} {'baseline':>9} {'ratio':>6}"
    )
    with tempfile.TemporaryDirectory(prefix="mixed-marks-") as tmp:
        for case in a.cases.split(","):
            scene = Path(tmp) / "scene.npz"
            np.savez(scene, **_scan(case))
            for gps in gps_runs:
                flag = "1" if gps else "0"
                pair = alternate(WORKER, ROOT, base, Path(tmp), a.runs, str(scene), flag, a.method)
                same_all &= pair.same
                g = pair.ours
                print(
                    f"{case:<20} {'yes' if gps else 'no':>4} {len(g):>8} {pair.verdict:>10} "
                    f"{int(g.sum()):>7} {pair.cpu_ours:>9.2f} {pair.cpu_theirs:>9.2f} "
                    f"{pair.ratio:>6.3f}",
                    flush=True,
                )
    print("all marks identical" if same_all else "MARKS DIFFER")
    sys.exit(0 if same_all else 1)


if __name__ == "__main__":
    main()
