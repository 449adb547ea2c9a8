"""The block steps: each stage's science applied to a ``Block``, in one signature.

A step is ``run(block, models) -> None``: it reads what earlier steps left on
the block, calls its stage's pure function with its ready-built parameter
model and records labels, rasters and stats. ``halo(models, density)`` says
how many metres of neighbouring data the step needs around a block's core
(STYLE habit 5); the job's buffer is the largest of them.

Steps run in ``order``; a new stage is a module with its function, its
parameter model and its step, registered with ``registry.block_step``.
"""

from __future__ import annotations

import inspect
from functools import partial

import numpy as np
from numpy.typing import NDArray

from terrasift.errors import ProcessingError
from terrasift.workers import chm, dem, mixed, objects, terrain, vegetation
from terrasift.workers.bins import Grid
from terrasift.workers.block import (
    BUILDING,
    GROUND,
    HIGH_VEG,
    LOW_VEG,
    MED_VEG,
    NOISE,
    Block,
    BlockModels,
)
from terrasift.workers.ground import landforms, lowpoints, lowveg, rotation
from terrasift.workers.registry import Stage, block_step

#: bins of the widest vegetation support window (15) reach this far beyond the core
VEGETATION_PAD = 7


def _mixed_halo(models: BlockModels, density: float) -> float:
    if not models.sensor_origin:
        return 0.0
    p = models.mixed
    # the interest box of a core point reaches its depth along the ray and half its width across
    # (a box width measured from the scan is an angle: its height bounds it in practice)
    return float(p.box_depth + max(p.box_width or p.box_height, p.box_height))


@block_step("mixed", order=10, halo=_mixed_halo)
def mixed_step(block: Block, models: BlockModels) -> None:
    """Mixed measurements (class 7) leave the pipeline before anything else sees them."""
    if not models.sensor_origin:
        return
    block.check_cancel()
    with block.timer("mixed"):
        found = _mark_mixed(block.xyz, block.scan_id, models, block.gps_time)
    block.labels[found.marked] = NOISE
    core = block.core
    block.stats["mixed"] = {
        "marked": int(found.marked[core].sum()),
        "unclassified": int(found.unclassified[core].sum()),
        "loss_rate": float(found.unclassified[core].mean()) if core.any() else 0.0,
        "geometry": found.geometry,
    }
    keep = ~found.marked if block.shadow is None else ~found.marked & ~block.shadow
    block.act = np.flatnonzero(keep)
    block.sub = block.xyz[block.act]


def _mark_mixed(
    xyz: NDArray, scan_id: NDArray, models: BlockModels, gps_time: NDArray | None = None
) -> mixed.MixedResult:
    origin_arr = np.asarray(models.sensor_origin, dtype=np.float64)
    ids = None
    if origin_arr.shape[0] > 1:
        ids = scan_id.astype(np.int64)
        if ids.max(initial=0) >= origin_arr.shape[0]:
            raise ProcessingError(
                f"scan id {int(ids.max())} has no sensor origin ({origin_arr.shape[0]} given)"
            )
    else:
        origin_arr = origin_arr[0]
    # a scan position whose returns are not all timed falls back to their angles
    times = gps_time if gps_time is not None and np.isfinite(gps_time).any() else None
    return mixed.mark_mixed(xyz, models.mixed, origin_arr, ids, models.scan_geometry, times)


def _ground_halo(models: BlockModels, density: float) -> float:
    return float(models.ground_params.halo(density))


@block_step("ground", order=20, halo=_ground_halo)
def ground_step(block: Block, models: BlockModels) -> None:
    """Ground (class 2) and isolated low points (class 7), with the steepness
    test and rotated classification of DESIGN §5.3."""
    block.check_cancel()
    is_ground, low, block.stats["steep"] = _ground(block, models)
    block.ground, block.low = is_ground, low
    full = np.zeros(block.xyz.shape[0], dtype=bool)
    full[block.act] = is_ground
    block.labels[full] = GROUND
    block.labels[block.act[low]] = NOISE
    block.stats["low_points"] = int(np.count_nonzero(low[block.core[block.act]]))


def _window(block: Block, stage: Stage) -> dict[str, tuple[float, float, float, float]]:
    """``window=`` the box the block's points were cut to (core and halo), for a ground
    method that takes it: where the data meets that box it goes on beyond, so the
    method's rules for the edge of the data hold elsewhere only. Unrotated runs only
    (a tipped cloud no longer fills the box)."""
    if "window" not in inspect.signature(stage.run).parameters:
        return {}
    xmin, ymin, xmax, ymax = block.grid.core_bounds(block.ix, block.iy)
    b = float(block.grid.buffer)
    return {"window": (xmin - b, ymin - b, xmax + b, ymax + b)}


def _last_return(block: Block) -> NDArray[np.bool_] | None:
    """Per point still in the pipeline: the last (or only) return of its pulse; None when unknown."""
    if block.return_number is None or block.number_of_returns is None:
        return None
    return np.asarray(block.return_number >= block.number_of_returns)[block.act]


def _ground(block: Block, models: BlockModels) -> tuple[NDArray[np.bool_], NDArray[np.bool_], dict]:
    xyz, timer = block.sub, block.timer
    stage = models.ground
    origins = models.sensor_origin
    kwargs = {"sensor_origin": np.asarray(origins[0], float)} if origins else {}
    steep_info: dict = {}
    none = np.zeros(xyz.shape[0], dtype=bool)
    if xyz.shape[0] < 3:
        return none, none, steep_info

    def without_low(is_ground: NDArray[np.bool_]) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        with timer("low_points"):
            low = lowpoints.isolated_low_points(xyz, is_ground, models.lowpoints)
        return is_ground & ~low, low

    with timer("ground"):
        is_ground = np.asarray(
            stage.run(xyz, models.ground_params, **kwargs, **_window(block, stage)), dtype=bool
        )
        last = _last_return(block)
        if models.landforms is not None:
            # Mesas, buttes and steep hills the filter removed as if buildings.
            is_ground = landforms.restore_landforms(xyz, is_ground, models.landforms, last)
        if models.lowveg is not None:
            # Bush edges and grass in the filter's ground band, by echoes and roughness.
            is_ground = lowveg.reject_low_vegetation(xyz, is_ground, models.lowveg, last)
    is_ground, low = without_low(is_ground)
    if models.rotation_mode == "off":
        return is_ground, low, steep_info

    # The test runs on the block's ground points: on the raw cloud, building
    # walls would make most urban blocks "steep".
    with timer("steep_test"):
        test = rotation.steepness(xyz[is_ground], models.steep)
    steep_info = {
        "facet_share": float(test.facet_share),
        "steep": bool(test.steep),
        "facets": int(test.n_facets),
    }
    if not (test.steep or models.rotation_mode == "always"):
        return is_ground, low, steep_info
    rparams = models.rotation
    # Seeded rotated runs where the method can grow from the labels found so far (ptd).
    ground, seeded = rotation.bind_ground(stage, models.rotation_ground_params, **kwargs)
    # A mesa tipped by the first angle is still a raised body to the filter.
    lp = models.landforms
    restore = (
        None
        if lp is None
        else partial(
            landforms.restore_landforms,
            params=lp.model_copy(update={"spacings": lp.view_spacings}),
        )
    )
    with timer("rotation"):
        result = rotation.classify_rotated(
            xyz,
            ground,
            rparams,
            unrotated=None if rparams.rerun_unrotated else is_ground,
            seeded=seeded,
            last_return=_last_return(block),
            restore=restore,
        )
    steep_info["rotated"] = True
    steep_info["added_per_rotation"] = [int(a) for a in result.added]
    is_ground = np.asarray(result.is_ground, dtype=bool)
    if models.lowveg is not None:
        # Rotated runs add gentle ground within 1 m of the surface: bush edges too.
        is_ground = lowveg.reject_low_vegetation(xyz, is_ground, models.lowveg, last)
    is_ground, low = without_low(is_ground)
    return is_ground, low, steep_info


@block_step("surface", order=30)
def surface_step(block: Block, models: BlockModels) -> None:
    """One ground TIN (1 m vertices, lowest ground only) for vegetation heights and the DTM."""
    with block.timer("dtm"):
        block.surface = dem.ground_tin(block.sub[block.ground], max(block.grid.resolution, 1.0))


def _objects_halo(models: BlockModels, density: float) -> float:
    # the isolation radius and two rounds of roof growth (two spacings each);
    # a third round, rare, may reach a little beyond
    s = objects.spacing(density)
    radius = models.objects.noise_radius or max(5.0, 4.0 * s)
    return float(radius + 2 * max(1.0, 2.0 * s))


@block_step("objects", order=35, halo=_objects_halo)
def objects_step(block: Block, models: BlockModels) -> None:
    """Buildings (6) and noise (7): vegetation bins, the DSM and the CHM do without them."""
    sub = block.sub
    block.height = np.full(sub.shape[0], np.nan)
    if block.surface is not None:
        block.height = sub[:, 2] - block.surface(sub[:, 0], sub[:, 1])
    act = block.act
    rn = None if block.return_number is None else block.return_number[act]
    nr = None if block.number_of_returns is None else block.number_of_returns[act]
    with block.timer("objects"):
        found = objects.label_objects(
            sub, block.ground | block.low, block.height, models.objects, block.density, rn, nr
        )
    block.building, block.noise = found.building, found.noise
    block.labels[act[found.building]] = BUILDING
    block.labels[act[found.noise]] = NOISE
    core = block.core[act]
    block.stats["objects"] = {
        "building": int(np.count_nonzero(found.building & core)),
        "noise": int(np.count_nonzero(found.noise & core)),
    }


def _vegetation_halo(models: BlockModels, density: float) -> float:
    return VEGETATION_PAD * float(models.vegetation.cell)


@block_step("vegetation", order=40, halo=_vegetation_halo)
def vegetation_step(block: Block, models: BlockModels) -> None:
    """Vegetation bins on the core window, and classes 3/4/5 for the points in them."""
    block.check_cancel()
    xmin, ymin, xmax, ymax = block.grid.core_bounds(block.ix, block.iy)
    vparams = vegetation.with_support(models.vegetation, block.density)
    c = vparams.cell
    vgrid = Grid(xmin, ymin, c, int(round((xmax - xmin) / c)), int(round((ymax - ymin) / c)))
    pad = VEGETATION_PAD
    hgrid = Grid(xmin - pad * c, ymin - pad * c, c, vgrid.nx + 2 * pad, vgrid.ny + 2 * pad)
    sub, is_ground, surface = block.sub, block.ground, block.surface
    n = sub.shape[0]
    building = block.building if block.building is not None else np.zeros(n, bool)
    noise = block.noise if block.noise is not None else np.zeros(n, bool)
    # Bins are judged on the vegetation's points: a roof is not a tree.
    plant = ~building & ~noise & ~block.low
    with block.timer("vegetation"):
        veg = vegetation.classify_bins(
            sub[plant], is_ground[plant], hgrid, vparams, surface=surface
        ).crop(vgrid)
        veg = vegetation.mark_buildings(veg, sub[building])
        if surface is not None:
            flat = vgrid.index(sub[:, 0], sub[:, 1])
            in_veg = (flat >= 0) & (veg.bin_class[np.maximum(flat, 0)] >= vegetation.BUSH)
            pick = in_veg & ~is_ground & plant
            hag = sub[pick, 2] - surface(sub[pick, 0], sub[pick, 1])
            block.labels[block.act[pick]] = vegetation.height_classes(hag)
    block.stats["vegetation"] = veg.counts
    block.stats["vegetation_nogo"] = int(veg.nogo.sum())
    block.rasters["coverage"] = veg.raster()


@block_step("roughness", order=50)
def roughness_step(block: Block, models: BlockModels) -> None:
    """Roughness gauge over the core's bins (ground points, plane per accepted bin)."""
    xmin, ymin, xmax, ymax = block.grid.core_bounds(block.ix, block.iy)
    tparams = models.terrain
    rcell = terrain.roughness_cell(tparams, block.density)
    rgrid = Grid(xmin, ymin, rcell, int((xmax - xmin) // rcell), int((ymax - ymin) // rcell))
    with block.timer("roughness"):
        rough = terrain.roughness(block.sub[block.ground], rgrid, tparams)
    block.stats["roughness_sums"] = [
        rough.n_bins,
        rough.mean_sx,
        rough.mean_sy,
        rough.m2_sx,
        rough.m2_sy,
    ]
    block.stats["roughness_cell"] = rcell


@block_step("elevation", order=60)
def elevation_step(block: Block, models: BlockModels) -> None:
    """DTM and DSM on the core window; cells beyond the data's reach are nodata."""
    block.check_cancel()
    grid = block.grid
    xmin, _, _, ymax = grid.core_bounds(block.ix, block.iy)
    _, _, rows, cols = grid.core_window(block.ix, block.iy)
    window = dem.Window(xmin, ymax, grid.resolution, rows, cols)
    with block.timer("dtm"):
        # From the job's density: a block's own count over its nominal area
        # makes a half-empty edge block reach further into a lake than its
        # neighbour, and their nodata edges disagree.
        reach = dem.default_reach(block.density, grid.resolution)
        valid = dem.data_reach_mask(block.sub, window, reach)
        dtm = dem.sample_window(block.surface, window)
        dtm[~valid] = np.nan
        # noise (a bird, multipath) stays out of the surface model
        dsm = dem.dsm_window(block.sub[block.labels[block.act] != NOISE], window)
        dsm[~valid] = np.nan
        dsm = np.fmax(dsm, dtm)
    block.rasters["dtm"] = dtm
    block.rasters["dsm"] = dsm
    with block.timer("chm"):
        canopy = _chm(block, window)
        canopy[~valid] = np.nan
    block.rasters["chm"] = canopy


def _chm(block: Block, window: dem.Window) -> NDArray[np.float32]:
    """Pit-free CHM of the vegetation's first returns (layered TINs); every other
    point (ground, roofs, unclassified; one per cell) at 0, so a roof reads 0
    and no layer bridges over it."""
    if block.surface is None:
        return np.full((window.rows, window.cols), np.nan, np.float32)
    act, sub = block.act, block.sub
    labels = block.labels[act]
    first = np.ones(act.size, bool)
    if block.return_number is not None and block.number_of_returns is not None:
        first = (block.return_number[act] <= 1) | (block.number_of_returns[act] <= 1)
    is_plant = np.isin(labels, (LOW_VEG, MED_VEG, HIGH_VEG))
    plant = is_plant & first
    floor = dem.lowest_per_cell(sub[~is_plant & (labels != NOISE)], window.resolution)
    xy = np.concatenate([sub[plant, :2], floor[:, :2]])
    hag = sub[plant, 2] - block.surface(sub[plant, 0], sub[plant, 1])
    h = np.concatenate([hag, np.zeros(floor.shape[0])])
    return chm.layered_chm(xy, h, window, chm.max_edge_for(block.density, window.resolution))


@block_step("keep", order=90)
def keep_step(block: Block, models: BlockModels) -> None:
    """Input classes listed in ``objects.keep`` (water by default) stay as they were."""
    keep = models.objects.keep
    if keep and block.given is not None:
        kept = np.isin(block.given, keep)
        block.labels[kept] = block.given[kept]
