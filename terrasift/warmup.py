"""``python -m terrasift.warmup``: small synthetic jobs that compile every numba kernel
a job uses, with the argument types a job passes, into numba's cache (see
``terrasift.jobs.warm``). An install step: the first job then loads the kernels
(about 0.2 s per worker) instead of compiling them in each worker."""

from __future__ import annotations

import tempfile
from pathlib import Path


def warm() -> None:
    """Run small synthetic jobs (town, sparse and cliff tiles, all products) in this process."""
    from terrasift.jobs.params import validate_params
    from terrasift.jobs.plan import prepare_job
    from terrasift.jobs.run import run_job
    from terrasift.synthetic.cliffs import make_cliffs
    from terrasift.synthetic.terrain import make_scene, write_las
    from terrasift.workers.executors import InlineExecutor

    with tempfile.TemporaryDirectory(prefix="terrasift-warm-") as tmp:
        tiles = [
            write_las(make_scene(60, 4, n_buildings=2, seed=1), Path(tmp) / "town.laz"),
            # sparse: the roughness, half-disc and close-fit tests of ground.nist
            write_las(make_scene(80, 0.5, n_buildings=1, seed=2), Path(tmp) / "sparse.laz"),
            # steep blocks: their rotations
            write_las(make_cliffs(length=24, density=5, seed=11), Path(tmp) / "cliff.laz"),
        ]
        for i, tile in enumerate(tiles):
            work = Path(tmp) / f"job{i}"
            prepare_job(work, [tile], validate_params({}))
            run_job(work, InlineExecutor())


if __name__ == "__main__":
    warm()
