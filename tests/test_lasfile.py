"""Header checks name the problem; chunked reading returns every point in order."""

from __future__ import annotations

import struct

import laspy
import numpy as np
import pytest

from terrasift.errors import InputError
from terrasift.synthetic.terrain import make_scene, write_las
from terrasift.tiling.lasfile import iter_chunks, read_tile_info


@pytest.fixture(scope="module")
def las_file(tmp_path_factory):
    scene = make_scene(size=40, density=4, seed=1, n_buildings=1)
    path = tmp_path_factory.mktemp("las") / "tile.las"
    write_las(scene, path, point_format=1, version="1.2")
    return path, scene


def _patched(tmp_path, src, offset, fmt, value, name="patched.las"):
    data = bytearray(src.read_bytes())
    struct.pack_into(fmt, data, offset, value)
    out = tmp_path / name
    out.write_bytes(bytes(data))
    return out


def test_reads_header_of_good_tile(small_tile, small_scene):
    info = read_tile_info(small_tile)
    assert info.point_count == len(small_scene)
    assert info.compressed and info.point_format == 6 and info.version == "1.4"
    assert "32632" in info.crs_wkt
    assert info.extra_dims == ("truth",)


def test_not_a_las_file(tmp_path):
    p = tmp_path / "notes.laz"
    p.write_text("x,y,z\n1,2,3\n" * 50)
    with pytest.raises(InputError, match="not a LAS/LAZ file"):
        read_tile_info(p)


def test_empty_file(tmp_path):
    p = tmp_path / "empty.las"
    p.write_bytes(b"")
    with pytest.raises(InputError, match="not a LAS/LAZ file"):
        read_tile_info(p)


def test_truncated_laz(tmp_path, small_tile):
    data = small_tile.read_bytes()
    p = tmp_path / "cut.laz"
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated"):
        read_tile_info(p)


def test_header_claims_more_points_than_file_holds(tmp_path, las_file):
    src, scene = las_file
    data = src.read_bytes()
    p = tmp_path / "short.las"
    p.write_bytes(data[: len(data) - 28 * 100])  # 100 records of format 1 gone
    with pytest.raises(
        InputError, match=f"claims {len(scene)} points but the file holds only {len(scene) - 100}"
    ):
        read_tile_info(p)


def test_zero_points(tmp_path):
    header = laspy.LasHeader(point_format=3, version="1.2")
    las = laspy.LasData(header)
    p = tmp_path / "zero.las"
    las.write(str(p))
    with pytest.raises(InputError, match="no points"):
        read_tile_info(p)


@pytest.mark.parametrize("value", [0.0, -0.01, 1e6])
def test_absurd_scale(tmp_path, las_file, value):
    p = _patched(tmp_path, las_file[0], 131, "<d", value)  # x scale factor
    with pytest.raises(InputError, match="absurd x scale"):
        read_tile_info(p)


def test_absurd_bounds(tmp_path, las_file):
    p = _patched(tmp_path, las_file[0], 179, "<d", 1e15)  # max x
    with pytest.raises(InputError, match="absurd x bounds"):
        read_tile_info(p)


def test_unsupported_version(tmp_path, las_file):
    p = _patched(tmp_path, las_file[0], 24, "<B", 2)
    with pytest.raises(InputError, match="unsupported LAS version 2.2"):
        read_tile_info(p)


def test_point_limit(small_tile):
    with pytest.raises(InputError, match="exceeds the configured limit"):
        read_tile_info(small_tile, max_points=10)


def test_missing_crs_is_a_warning(las_file, tmp_path):
    scene = make_scene(size=20, density=2, seed=2, n_buildings=0)
    p = write_las(scene, tmp_path / "nocrs.las", crs=None)
    info = read_tile_info(p)
    assert info.crs_wkt is None
    assert any("no CRS" in w for w in info.warnings)


def test_chunks_cover_every_point_in_order(small_tile, small_scene):
    chunks = list(iter_chunks(small_tile, chunk_size=10_000))
    assert len(chunks) > 2
    assert [c.start for c in chunks] == list(range(0, len(small_scene), 10_000))
    xyz = np.concatenate([c.xyz for c in chunks])
    np.testing.assert_allclose(xyz, small_scene.xyz, atol=0.006)
    rn = np.concatenate([c.return_number for c in chunks])
    assert (rn == small_scene.return_number).all()
