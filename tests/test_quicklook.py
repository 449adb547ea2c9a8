"""Quicklook rendering: PNG bytes any reader opens, hillshade lit from the northwest,
nodata transparent, class colours exact."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio

from terrasift.tiling import quicklook as ql


def read_png(data: bytes, tmp_path: Path) -> np.ndarray:
    path = tmp_path / "q.png"
    path.write_bytes(data)
    with rasterio.open(path) as ds:
        return np.moveaxis(ds.read(), 0, -1)


def test_png_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, (37, 53, 4), dtype=np.uint8)
    assert np.array_equal(read_png(ql.png(image), tmp_path), image)


def test_hillshade_faces_and_nodata() -> None:
    y, x = np.mgrid[0:50, 0:50].astype(float)
    west_face = x * 0.5  # rises to the east: faces west, toward a light from the northwest
    east_face = -x * 0.5
    lit = ql.hillshade(west_face, 1.0)
    dark = ql.hillshade(east_face, 1.0)
    assert np.nanmean(lit) > np.nanmean(ql.hillshade(np.zeros((50, 50)), 1.0)) > np.nanmean(dark)
    north_face = y * 0.5  # rows run south: rises to the south, faces north
    assert np.nanmean(ql.hillshade(north_face, 1.0)) > np.nanmean(ql.hillshade(-north_face, 1.0))
    dem = west_face.copy()
    dem[:5] = np.nan
    rgba = ql.grey(ql.hillshade(dem, 1.0))
    assert (rgba[:5, :, 3] == 0).all() and (rgba[5:, :, 3] == 255).all()


def test_classes_and_ramp_colours() -> None:
    cov = np.array([[0, 1], [2, 255]], np.uint8)
    rgba = ql.classes(cov, ql.COVERAGE_CLASSES, 255)
    assert tuple(rgba[1, 0, :3]) == ql.COVERAGE_CLASSES[2][1] and rgba[1, 1, 3] == 0
    chm = np.array([[0.0, 10.0], [20.0, np.nan]])
    r = ql.ramp(chm, 20.0)
    assert tuple(r[0, 0, :3]) == ql.CHM_RAMP[0][1] and tuple(r[1, 0, :3]) == ql.CHM_RAMP[-1][1]
    assert r[1, 1, 3] == 0
    legend = ql.legend(ql.COVERAGE_CLASSES)
    assert legend[3] == {"value": 3, "description": "tree", "color_hint": "1a6e2e"}


def test_job_quicklooks_show_steep_blocks_and_features(tmp_path: Path) -> None:
    from terrasift import jobs
    from terrasift.synthetic.terrain import make_scene, write_las
    from terrasift.workers.executors import InlineExecutor

    tile = write_las(make_scene(size=60, density=4, seed=3), tmp_path / "t.laz")
    job = tmp_path / "job"
    params = {"block_size": 30, "buffer": 5, "resolution": 1.0, "rotation": "always"}
    jobs.prepare_job(job, [tile], jobs.validate_params(params))
    names = jobs.run_job(job, InlineExecutor())
    assert {"features.png", "steep_blocks.png", "thumbnail.png"} <= set(names)
    steep = read_png((job / "outputs" / "steep_blocks.png").read_bytes(), tmp_path)
    plain = read_png((job / "outputs" / "hillshade.png").read_bytes(), tmp_path)
    inside = plain[..., 3] == 255
    # every block was rotated: the whole footprint is tinted red over the grey hillshade
    red = steep[..., 0].astype(int) - steep[..., 1].astype(int)
    assert inside.mean() > 0.8 and (red[inside] > 40).mean() > 0.95
    assert (np.abs(plain[..., 0].astype(int) - plain[..., 1])[inside] == 0).all()
