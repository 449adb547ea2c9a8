"""Every point lands in exactly one block core, and in the halo of every block within the buffer."""

from __future__ import annotations

import laspy
import numpy as np
import pytest

from terrasift.tiling.blocks import (
    BlockGrid,
    assign_blocks,
    block_name,
    occupancy_cell,
    occupied_cells,
    occupied_density,
    read_block_points,
    shard_tile,
)


def _brute_force(grid: BlockGrid, x, y):
    pairs = set()
    cores = set()
    for iy in range(grid.ny):
        for ix in range(grid.nx):
            x0 = grid.x0 + ix * grid.block_size
            y0 = grid.y0 + iy * grid.block_size
            b = grid.buffer
            inside = (
                (x >= x0 - b)
                & (x < x0 + grid.block_size + b)
                & (y >= y0 - b)
                & (y < y0 + grid.block_size + b)
            )
            core = (x >= x0) & (x < x0 + grid.block_size) & (y >= y0) & (y < y0 + grid.block_size)
            for p in np.flatnonzero(inside):
                pairs.add((p, iy * grid.nx + ix))
            for p in np.flatnonzero(core):
                cores.add((p, iy * grid.nx + ix))
    return pairs, cores


def test_assignment_matches_definition_at_edges_and_corners():
    grid = BlockGrid.over((0.0, 0.0), (299.9, 199.9), resolution=0.5, block_size=100.0, buffer=10.0)
    assert (grid.nx, grid.ny) == (3, 2)
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 299.9, 3000)
    y = rng.uniform(0, 199.9, 3000)
    # points exactly on block edges, on corners, and exactly at the buffer distance
    special = np.array(
        [
            [100.0, 100.0],
            [90.0, 110.0],
            [110.0, 90.0],
            [100.0, 50.0],
            [50.0, 100.0],
            [89.999, 100.0],
            [110.0, 110.0],
            [200.0, 100.0],
            [0.0, 0.0],
            [190.0, 90.0],
        ]
    )
    x = np.r_[x, special[:, 0]]
    y = np.r_[y, special[:, 1]]
    p, b, core = assign_blocks(grid, x, y)
    expected_pairs, expected_cores = _brute_force(grid, x, y)
    assert set(zip(p.tolist(), b.tolist(), strict=True)) == expected_pairs
    assert set(zip(p[core].tolist(), b[core].tolist(), strict=True)) == expected_cores
    assert np.bincount(p[core], minlength=x.size).tolist() == [1] * x.size
    # the corner point (100, 100) is core of block (1, 1) and halo of the three others around it
    corner = x.size - special.shape[0]
    assert sorted(b[p == corner].tolist()) == [0, 1, 3, 4]


def test_core_windows_tile_the_raster_exactly():
    grid = BlockGrid.over((10.2, 20.7), (333.3, 250.1), resolution=0.5, block_size=64.0, buffer=8.0)
    cover = np.zeros((grid.height, grid.width), int)
    for iy in range(grid.ny):
        for ix in range(grid.nx):
            r, c, rows, cols = grid.core_window(ix, iy)
            cover[r : r + rows, c : c + cols] += 1
            xmin, ymin, xmax, ymax = grid.core_bounds(ix, iy)
            assert (
                xmin == grid.x0 + c * grid.resolution and ymax == grid.y_top - r * grid.resolution
            )
    assert (cover == 1).all()
    assert grid.x0 % 0.5 == 0 and grid.y0 % 0.5 == 0


def test_shards_hold_every_point_once_as_core(tmp_path, small_tile, small_scene):
    xyz = small_scene.xyz
    grid = BlockGrid.over(xyz[:, :2].min(0), xyz[:, :2].max(0), 0.5, 50.0, 5.0)
    counts = shard_tile(str(small_tile), 0, grid, tmp_path / "0", 7_000)
    assert not (tmp_path / "0.tmp").exists()
    seen = np.zeros(len(small_scene), int)
    total = 0
    for iy in range(grid.ny):
        for ix in range(grid.nx):
            pts = read_block_points([tmp_path / "0"], block_name(ix, iy))
            core = pts["core"] == 1
            np.add.at(seen, pts["index"][core], 1)
            total += pts.size
            assert counts.get(block_name(ix, iy), 0) == core.sum()
            np.testing.assert_allclose(pts["z"], xyz[pts["index"], 2], atol=0.006)
    assert (seen == 1).all()
    assert total > len(small_scene)  # halos duplicate points near block edges


def test_canonical_order_is_the_lexsort_order():
    from terrasift.workers.block import canonical_order

    rng = np.random.default_rng(5)
    # LAS-like coordinates on a 1 cm lattice, with exact duplicates and ties in x and y.
    xyz = np.round(rng.uniform([5e5, 5.4e6, 100], [5e5 + 240, 5.4e6 + 240, 180], (20_000, 3)), 2)
    xyz[100:200] = xyz[:100]
    xyz[300:400, 0] = xyz[0, 0]
    xyz[500:530] = xyz[499]  # a run of 31 equal points, split by others below
    xyz[rng.permutation(20_000)[:50]] = xyz[499]
    for pts in (xyz, xyz + rng.uniform(0, 1e-4, xyz.shape)):  # on and off the millimetre lattice
        x, y, z = pts.T.copy()
        assert np.array_equal(canonical_order(x, y, z), np.lexsort((z, y, x)))


def test_tile_parts_shard_to_the_same_points(tmp_path, small_tile, small_scene):
    from terrasift.tiling.blocks import shard_parts

    grid = BlockGrid.over(small_scene.xyz[:, :2].min(0), small_scene.xyz[:, :2].max(0), 0.5, 80, 15)
    n = len(small_scene)
    parts = shard_parts([n, 10], part_points=n // 3)
    assert [(p.tile, p.start) for p in parts][:3] == [(0, 0), (0, n // 3), (0, 2 * n // 3)]
    assert parts[2].stop == n and parts[3] == type(parts[3])(1, 0, 10)
    shard_tile(str(small_tile), 0, grid, tmp_path / "whole")
    for p in parts[:3]:
        shard_tile(str(small_tile), 0, grid, tmp_path / p.name, start=p.start, stop=p.stop)
    for name in sorted(q.stem for q in (tmp_path / "whole").glob("*.bin")):
        whole = read_block_points([tmp_path / "whole"], name)
        split = read_block_points([tmp_path / p.name for p in parts[:3]], name)
        assert np.array_equal(np.sort(whole, order="index"), np.sort(split, order="index"))


def test_the_block_task_runs_the_registered_steps_in_order():
    from terrasift.workers.registry import block_steps

    ids = [s.id for s in block_steps()]
    assert ids == [
        "mixed",
        "ground",
        "surface",
        "objects",
        "vegetation",
        "roughness",
        "elevation",
        "keep",
    ]


def test_occupied_density_leaves_voids_out_and_unions_parts(tmp_path, small_tile, small_scene):
    # A 100 x 100 m square at 2 pts/m² with a 50 x 100 m void: the header area is
    # twice the occupied area, the occupied-area density is the true one.
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 100, (20000, 2))
    xy = xy[xy[:, 0] < 50]
    cell = occupancy_cell(xy.shape[0] / 1e4)
    d = occupied_density(xy.shape[0], [occupied_cells(xy[:, 0], xy[:, 1], cell)], cell)
    assert 1.85 < d < 2.0  # cells cut by the void's edge count as occupied
    # Parts sharing cells (overlapping strips) count each cell once.
    halves = [occupied_cells(xy[i::2, 0], xy[i::2, 1], cell) for i in (0, 1)]
    assert occupied_density(xy.shape[0], halves, cell) == d
    # Sharding records the same cells as the whole tile's points occupy.
    grid = BlockGrid.over(small_scene.xyz[:, :2].min(0), small_scene.xyz[:, :2].max(0), 0.5, 80, 15)
    shard_tile(str(small_tile), 0, grid, tmp_path / "s", 7_000, occupancy=1.3)
    las = laspy.read(small_tile)  # the file's coordinates: on the LAS scale's lattice
    want = occupied_cells(np.asarray(las.x), np.asarray(las.y), 1.3)
    got = np.load(tmp_path / "s" / "occupancy.npy")
    assert np.array_equal(got, want)


def test_shadow_copies_a_return_to_the_blocks_behind_it():
    # a sensor at (5, 5) in a row of four 50 m blocks (10 m halo): a return east of it
    # reaches, along its ray, the blocks it lies in front of (not those it is core or
    # halo of), and a return whose ray leaves the grid at once reaches none
    from terrasift.tiling.blocks import assign_shadow

    grid = BlockGrid.over((0.0, 0.0), (199.0, 49.0), 0.5, 50.0, 10.0)
    assert (grid.nx, grid.ny) == (4, 1)
    x, y = np.array([45.0, 20.0]), np.array([5.0, 5.0])
    ox, oy = np.array([5.0, 5.0]), np.array([5.0, 5.0])
    own = assign_blocks(grid, x, y)[:2]
    p, b = assign_shadow(grid, x, y, ox, oy, own)
    # x = 45 is core of block 0 and halo of block 1; x = 20 is in block 0 only
    assert set(zip(p.tolist(), b.tolist(), strict=True)) == {(0, 2), (0, 3), (1, 1), (1, 2), (1, 3)}
    west = assign_shadow(
        grid, np.array([2.0]), np.array([5.0]), ox[:1], oy[:1], (np.array([0]), np.array([0]))
    )
    assert west[0].size == 0
    # bounded by the farthest return of the position (60 m from the sensor): the rays
    # stop at x = 65, inside block 1's halo
    p, b = assign_shadow(grid, x, y, ox, oy, own, np.array([60.0, 60.0]))
    assert set(zip(p.tolist(), b.tolist(), strict=True)) == {(1, 1)}


def test_scan_reach_is_the_farthest_return_of_each_position(small_tile):
    from terrasift.tiling.blocks import scan_reach

    las = laspy.read(small_tile)
    o = (float(np.mean(las.x)), float(np.mean(las.y)), 0.0)
    want = float(np.max(np.hypot(np.asarray(las.x) - o[0], np.asarray(las.y) - o[1])))
    assert scan_reach(str(small_tile), [o]) == pytest.approx([want])
    n = len(las.x)
    parts = [
        scan_reach(str(small_tile), [o], start=a, stop=b) for a, b in ((0, n // 2), (n // 2, n))
    ]
    assert max(v[0] for v in parts) == pytest.approx(want)


def test_the_ground_step_tells_the_method_the_box_its_block_was_cut_to():
    """Core ± buffer: where the block's data meets that box it goes on beyond it."""
    import dataclasses

    from terrasift import jobs
    from terrasift.jobs.params import block_models
    from terrasift.workers import steps
    from terrasift.workers.block import Block
    from terrasift.workers.registry import Stage

    seen: dict = {}

    def method(xyz, params, *, sensor_origin=None, window=None):
        seen["window"] = window
        return np.zeros(xyz.shape[0], dtype=bool)

    models = block_models(jobs.validate_params({"rotation": "off"}))
    models = dataclasses.replace(
        models, ground=Stage("ground.box", type(models.ground_params), method, "records its box")
    )
    grid = BlockGrid.over((0.0, 0.0), (299.9, 199.9), resolution=0.5, block_size=100.0, buffer=10.0)
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(90, 210, 500), rng.uniform(0, 110, 500), np.zeros(500)])
    core = (xyz[:, 0] >= 100) & (xyz[:, 0] < 200) & (xyz[:, 1] < 100)
    block = Block(xyz, np.zeros(500, np.uint16), core, grid, 1, 0, 1.0, lambda: None)
    steps.ground_step(block, models)
    assert seen["window"] == (90.0, -10.0, 210.0, 110.0)
