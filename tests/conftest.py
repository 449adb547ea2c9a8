"""Shared fixtures: small synthetic tiles with exact truth, and the real data folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from terrasift.synthetic.scan import make_scan
from terrasift.synthetic.terrain import make_scene, write_las

# The suite's jobs run at the suite's own CPU priority: with a worker nice value the
# service's workers take a low-priority scheduling group of their own (test_pool checks
# that), and on a machine busy with other work the suite would crawl.
os.environ.setdefault("TERRASIFT_WORKER_NICE", "0")

REPO = Path(__file__).resolve().parents[1]
# The real labelled point clouds: ../shared/data beside the repository, or wherever
# TERRASIFT_SHARED_DATA points (.ci/run sets it for a clone made elsewhere).
SHARED_DATA = Path(os.environ.get("TERRASIFT_SHARED_DATA") or REPO.parent / "shared" / "data")


def shared_data(*parts: str) -> Path:
    """A file of the real data folder, or skip the test when the folder is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"reference data not found at {path} (set TERRASIFT_SHARED_DATA)")
    return path


@pytest.fixture(scope="session")
def small_scene():
    """A 160 m square scene at 6 pulses/m²: slopes, buildings, trees, bushes, outliers."""
    return make_scene(size=160, density=6, seed=3)


@pytest.fixture(scope="session")
def small_tile(tmp_path_factory, small_scene):
    """``small_scene`` written as LAZ with a ``truth`` extra dimension."""
    path = tmp_path_factory.mktemp("tiles") / "small.laz"
    write_las(small_scene, path, extra_bytes=True)
    return path


@pytest.fixture(scope="session")
def near_coarse_scan():
    """A ground-based scan at 0.035° with 1 cm coordinates and every return within about
    14 m: each angle is blurred by half a step and more, so the angles alone show no grid."""
    return make_scan(
        step_deg=0.035,
        footprint_steps=2.0,
        azimuth_deg=(-2.0, 2.0),
        elevation_deg=(-30.0, 5.0),
        n_boards=2,
        n_poles=1,
        object_range=(3.0, 7.0),
        wall_gap=(1.0, 2.0),
        las_scale=0.01,
        seed=3,
    )
