"""Buildings (6), noise (7), kept input classes (9) and the pit-free CHM."""

from __future__ import annotations

import laspy
import numpy as np
import pytest
import rasterio

from terrasift import jobs
from terrasift.synthetic.terrain import make_scene, write_las
from terrasift.synthetic.town import make_town
from terrasift.workers.chm import layered_chm
from terrasift.workers.dem import Window
from terrasift.workers.executors import InlineExecutor
from terrasift.workers.objects import ObjectParams, label_objects


@pytest.fixture(scope="module")
def town():
    return make_town(size=100, density=4, seed=5, n_buildings=5, building_size=(5, 60))


def _labels(scene, **kw):
    h = scene.xyz[:, 2] - scene.surface(scene.xyz[:, 0], scene.xyz[:, 1])
    return label_objects(
        scene.xyz,
        scene.truth == 2,
        h,
        ObjectParams(**kw),
        len(scene) / 100**2,
        scene.return_number,
        scene.number_of_returns,
    )


def test_roofs_are_buildings_and_crowns_over_them_are_not(town):
    got = _labels(town)
    roof = town.truth == 6
    veg = np.isin(town.truth, (3, 4, 5))
    tp = np.count_nonzero(got.building & roof)
    assert tp / got.building.sum() > 0.97
    assert tp / roof.sum() > 0.95
    assert np.mean(got.building[veg]) < 0.02
    # crowns standing over roofs: the vegetation points above a roof stay vegetation
    assert np.mean(got.building[veg & (town.number_of_returns > 1)]) < 0.02


def test_without_returns_roofs_are_still_found(town):
    h = town.xyz[:, 2] - town.surface(town.xyz[:, 0], town.xyz[:, 1])
    got = label_objects(town.xyz, town.truth == 2, h, ObjectParams(), len(town) / 100**2)
    roof = town.truth == 6
    assert np.count_nonzero(got.building & roof) / roof.sum() > 0.9


def test_isolated_high_and_low_points_are_noise(town):
    got = _labels(town)
    noise = town.truth == 7
    assert noise.sum() > 0
    assert np.mean(got.noise[noise]) > 0.9
    assert np.mean(got.noise[~noise]) < 0.002
    assert not (got.noise & got.building).any()


def test_buildings_off_leaves_roofs_alone(town):
    assert not _labels(town, buildings=False).building.any()


def test_keep_classes_parse():
    assert ObjectParams.preset(keep="9,17").keep == [9, 17]
    assert ObjectParams.preset(keep="none").keep == []
    with pytest.raises(Exception, match="0-255"):
        ObjectParams.preset(keep="300")


def test_layered_chm_has_no_pits_where_the_top_layer_covers():
    rng = np.random.default_rng(0)
    # one crown: a cone 20 m high, 6 m radius, with returns inside it below its surface
    n = 4000
    r = 6 * np.sqrt(rng.random(n))
    a = rng.uniform(0, 2 * np.pi, n)
    xy = np.column_stack([r * np.cos(a), r * np.sin(a)]) + 10
    top = 20 * (1 - r / 6)
    inside = rng.random(n) < 0.4
    h = np.where(inside, top * rng.random(n), top)
    win = Window(0.0, 20.0, 0.5, 40, 40)
    chm = layered_chm(xy, h, win, max_edge=1.5)
    gx, gy = win.centers()
    rc = np.hypot(gx - 10, gy - 10)
    core = rc < 5
    truth = 20 * (1 - rc / 6)
    # a return inside the crown dips the highest layer holding it by less than a step (2 m)
    assert np.max(truth[core] - chm[core]) < 2.5
    # the highest point per cell would have pits deep inside
    row, col, ins = win.cell_of(xy[:, 0], xy[:, 1])
    top_cell = np.full((40, 40), -np.inf)
    np.maximum.at(top_cell, (row[ins], col[ins]), h[ins])
    assert np.max(np.where(core & np.isfinite(top_cell), truth - top_cell, 0)) > 3.0


def test_job_keeps_water_and_keeps_spikes_out_of_dsm_and_chm(tmp_path):
    scene = make_scene(size=80, density=4, seed=21, n_buildings=2, outlier_rate=0.0)
    xyz = scene.xyz.copy()
    # a bird 40 m above its neighbours, and a pond the provider labelled water
    spike = np.array([[xyz[:, 0].mean(), xyz[:, 1].mean(), xyz[:, 2].max() + 40.0]])
    scene.xyz = np.vstack([xyz, spike])
    scene.truth = np.r_[scene.truth, 7].astype(np.uint8)
    scene.return_number = np.r_[scene.return_number, 1].astype(np.uint8)
    scene.number_of_returns = np.r_[scene.number_of_returns, 1].astype(np.uint8)
    given = np.ones(len(scene), np.uint8)
    pond = (scene.truth == 2) & (np.hypot(*(scene.xyz[:, :2] - scene.xyz[:, :2].min(0) - 15).T) < 8)
    given[pond] = 9
    tile = write_las(scene, tmp_path / "pond.laz", classification=given)
    job = tmp_path / "job"
    jobs.prepare_job(job, [tile], jobs.validate_params({}))
    jobs.run_job(job, InlineExecutor())
    out = np.asarray(laspy.read(job / "outputs" / "classified.laz").classification)
    assert np.all(out[pond] == 9)
    assert out[-1] == 7
    with rasterio.open(job / "outputs" / "dsm.tif") as ds:
        dsm = ds.read(1, masked=True)
    with rasterio.open(job / "outputs" / "chm.tif") as ds:
        chm = ds.read(1, masked=True)
    assert dsm.max() < spike[0, 2] - 30
    assert chm.max() < 30
