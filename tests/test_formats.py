"""Every LAS version and point format the readers support round-trips through a job."""

from __future__ import annotations

import laspy
import numpy as np
import pytest

from terrasift import jobs
from terrasift.synthetic.terrain import make_scene, write_las
from terrasift.workers.executors import InlineExecutor


@pytest.mark.parametrize(
    "version, point_format, suffix",
    [
        ("1.0", 1, ".las"),
        ("1.2", 3, ".laz"),
        ("1.3", 0, ".las"),
        ("1.4", 7, ".laz"),
        ("1.4", 8, ".las"),
    ],
)
def test_classified_copy_keeps_everything(tmp_path, version, point_format, suffix):
    scene = make_scene(size=50, density=3, seed=11, n_buildings=1)
    src = write_las(
        scene,
        tmp_path / f"in{suffix}",
        version="1.2" if version == "1.0" else version,
        point_format=point_format,
        crs=None if version in ("1.0", "1.3") else "EPSG:32632",
    )
    if (
        version == "1.0"
    ):  # laspy writes from 1.1 on; a 1.0 header differs only in its minor version byte
        data = bytearray(src.read_bytes())
        data[25] = 0
        src.write_bytes(bytes(data))
    job = tmp_path / "job"
    params = jobs.validate_params(
        {"block_size": 40, "buffer": 5, "features": "none", "crs": "EPSG:32632"}
    )
    jobs.prepare_job(job, [src], params)
    jobs.run_job(job, InlineExecutor(), products="classified")
    a, b = laspy.read(src), laspy.read(jobs.output_path(job, "classified.laz"))
    assert b.header.point_format.id == point_format
    assert len(b.points) == len(a.points)
    for dim in a.point_format.dimension_names:
        if dim != "classification":
            assert np.array_equal(a[dim], b[dim]), dim
    assert (np.asarray(b.classification) == 2).mean() > 0.5
    assert b.header.parse_crs().to_epsg() == 32632  # the crs parameter is written into the copy
