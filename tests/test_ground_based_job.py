"""A ground-based scan runs mixed → ground → vegetation end to end when a sensor origin is given."""

from __future__ import annotations

import json

import laspy
import numpy as np

from terrasift import jobs
from terrasift.synthetic.scan import make_scan
from terrasift.synthetic.terrain import Scene, write_las
from terrasift.workers.executors import InlineExecutor


def _scan_tile(tmp_path):
    scan = make_scan(step_deg=0.4, seed=4)
    n = len(scan)
    ones = np.ones(n, np.uint8)
    scene = Scene(scan.xyz, scan.truth, ones, ones, lambda x, y: np.zeros_like(x), (0, 0, 0, 0))
    return scan, write_las(scene, tmp_path / "scan.laz")


def test_scan_job_marks_mixed_points_class_7(tmp_path):
    scan, path = _scan_tile(tmp_path)
    origin = ",".join(str(v) for v in scan.origin)
    job = tmp_path / "job"
    # the mixed filter's angles and distances follow from the scan, measured once per
    # job and scan position from all blocks (plan.json), not in each block
    params = jobs.validate_params(
        {"sensor_origin": origin, "features": "none", "block_size": 40, "buffer": 4}
    )
    jobs.prepare_job(job, [path], params)
    jobs.run_job(job, InlineExecutor())
    classes = np.asarray(laspy.read(jobs.output_path(job, "classified.laz")).classification)
    marked = classes == 7
    assert marked.any()
    # most marked points are real mixed or ghost returns, and few correct points are lost
    precision = np.mean(scan.is_mixed[marked])
    fpr = np.mean(marked[~scan.is_mixed])
    tpr = np.mean(marked[scan.is_mixed])
    # measured: tpr 0.948, precision 0.734, fpr 0.0114 on this coarse (0.4°) scan with
    # 1 cm coordinates, in the scan's angular grid (the interest boxes alone, 1° cells
    # from the measured step: 0.46, 0.43, 0.020). The footprint (0.25° across, 0.6
    # step) is measured 1.02 steps, which adds a beam to the reach, thin runs and span
    # (at 1.00: precision 0.807, fpr 0.0075).
    assert tpr > 0.9 and precision > 0.7 and fpr < 0.013, (tpr, precision, fpr)
    report = json.loads(jobs.output_path(job, "report.json").read_text())
    assert report["mixed_measurements"]["marked"] == int(marked.sum())
    geo = report["mixed_measurements"]["geometry"]["0"]
    assert geo["grid_share"] > 0.95  # judged in the grid, not left to the boxes
    assert abs(geo["step_az"] - 0.4) < 0.02 and abs(geo["cell_angle"] - 2.5 * geo["step"]) < 1e-3
    assert set(geo["how"]) == {
        "las_scale",
        "step",
        "range_noise",
        "surface_sigma",
        "footprint",
        "scope",
    }
    (planned,) = json.loads((job / "plan.json").read_text())["scan_geometry"]
    assert planned["step_az"] == geo["step_az"] and planned["n_points"] == len(scan)
    assert report["counts_per_class"]["7"] == int(marked.sum())
    assert (classes == 2).sum() > 0.2 * len(scan)  # the ground plane in front of the mast


def test_without_origin_the_report_says_mixed_did_not_run(tmp_path):
    _, path = _scan_tile(tmp_path)
    job = tmp_path / "job"
    jobs.prepare_job(
        job, [path], jobs.validate_params({"features": "none", "block_size": 40, "buffer": 4})
    )
    jobs.run_job(job, InlineExecutor(), products="classified")
    report = json.loads(jobs.output_path(job, "report.json").read_text())
    assert report["mixed_measurements"].startswith("not run")
    assert "7" not in report["counts_per_class"]


def test_concentric_grid_holds_where_square_bins_fail_on_a_dense_scan():
    from terrasift.metrics import ground_score
    from terrasift.synthetic.slopes import ground_based
    from terrasift.workers.ground import nist

    # 400 pts/m² out to 5 m, falling as 1/r² to 50 m: square bins sized from
    # the mean spacing are far too fine out there (measured kappa 0.66).
    scene, origin = ground_based(near_density=400.0)
    ring = ground_score(
        scene.is_ground, nist.classify_ground(scene.xyz, nist.NistParams(), sensor_origin=origin)
    )
    square = ground_score(
        scene.is_ground, nist.classify_ground(scene.xyz, nist.NistParams(grid="regular"))
    )
    assert ring.kappa > 0.95 and ring.type1 < 0.01, ring  # measured 0.974, 0.0001
    assert square.kappa < ring.kappa - 0.1, square


def test_scan_job_places_returns_by_gps_time(tmp_path):
    # the same scan as a LAS file with each return's GPS time (point format 6): the shards
    # carry the times and every block places its returns on the grid by firing order
    scan = make_scan(step_deg=0.4, seed=4)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(scan.xyz.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = scan.xyz.T
    las.gps_time = scan.gps_time
    path = tmp_path / "timed.laz"
    las.write(str(path))
    origin = ",".join(str(v) for v in scan.origin)
    job = tmp_path / "job"
    params = jobs.validate_params(
        {"sensor_origin": origin, "features": "none", "block_size": 40, "buffer": 4}
    )
    jobs.prepare_job(job, [path], params)
    jobs.run_job(job, InlineExecutor(), products="classified")
    marked = np.asarray(laspy.read(jobs.output_path(job, "classified.laz")).classification) == 7
    report = json.loads(jobs.output_path(job, "report.json").read_text())
    geo = report["mixed_measurements"]["geometry"]["0"]
    assert geo["grid_index"] == {"GPS time (firing order)": geo["blocks"]}
    assert geo["grid_share"] == 1.0
    tpr = np.mean(marked[scan.is_mixed])
    fpr = np.mean(marked[~scan.is_mixed])
    assert tpr > 0.9 and fpr < 0.013, (tpr, fpr)
    # each block also holds the returns in front of it along the rays (shadow copies),
    # so it sees every neighbouring beam the whole scan has: the job marks what the
    # stage alone marks on the whole scan
    from terrasift.workers.mixed import MixedParams, mark_mixed

    xyz = np.column_stack([las.x, las.y, las.z])
    alone = mark_mixed(xyz, MixedParams(), scan.origin, gps_time=scan.gps_time).marked
    assert np.array_equal(alone, marked)
