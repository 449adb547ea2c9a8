"""The command line runs the same pipeline: process, classify, path."""

from __future__ import annotations

import json

import laspy
import numpy as np
import pytest
import rasterio

from terrasift.cli import WORK_DIR, main
from terrasift.synthetic.terrain import Surface, make_scene, write_las


@pytest.fixture(scope="module")
def tile(tmp_path_factory):
    scene = make_scene(size=90, density=4, seed=5, n_buildings=1)
    return write_las(scene, tmp_path_factory.mktemp("cli") / "tile.laz"), scene


def test_process_writes_outputs_and_cleans_up(tmp_path, tile, capsys):
    path, scene = tile
    out = tmp_path / "out"
    code = main(
        [
            "process",
            str(path),
            "--out",
            str(out),
            "--quiet",
            "--param",
            "block_size=60",
            "--param",
            "workers=1",
        ]
    )
    assert code == 0
    listed = capsys.readouterr().out.split()
    for name in ["classified.laz", "dtm.tif", "coverage.tif", "categories.tif", "report.json"]:
        assert (out / name).exists() and str(out / name) in listed
    assert not (out / WORK_DIR).exists()
    assert len(laspy.read(out / "classified.laz").points) == len(scene)


def test_classify_writes_only_the_point_cloud(tmp_path, tile):
    path, scene = tile
    dst = tmp_path / "classified.laz"
    assert main(["classify", str(path), str(dst), "--quiet", "--param", "workers=1"]) == 0
    out = laspy.read(dst)
    assert len(out.points) == len(scene)
    assert np.mean((np.asarray(out.classification) == 2) == scene.is_ground) > 0.85
    assert sorted(p.name for p in tmp_path.iterdir()) == ["classified.laz"]


def test_bad_parameter_exits_2_with_a_message(tmp_path, tile, capsys):
    path, _ = tile
    assert main(["process", str(path), "--out", str(tmp_path), "--param", "resolution=-3"]) == 2
    assert "resolution" in capsys.readouterr().err


def test_path_profile_on_a_tilted_plane(tmp_path, capsys):
    """A plane rising 10 % to the east: pitch atan(0.1) going east, roll 0; going north, roll ±atan(0.1)."""
    surface = Surface(z0=50.0, gx=0.1, gy=0.0, waves=())
    scene = make_scene(
        size=80,
        density=3,
        seed=2,
        surface=surface,
        n_buildings=0,
        tree_density=0,
        bush_density=0,
        outlier_rate=0,
        noise_sigma=0.0,
    )
    src = write_las(scene, tmp_path / "plane.laz")
    out = tmp_path / "out"
    assert (
        main(
            [
                "process",
                str(src),
                "--out",
                str(out),
                "--quiet",
                "--param",
                "workers=1",
                "--param",
                "features=none",
            ]
        )
        == 0
    )
    x0, y0, _, _ = scene.bounds
    line = {
        "type": "LineString",
        "coordinates": [[x0 + 20, y0 + 40], [x0 + 60, y0 + 40], [x0 + 60, y0 + 70]],
    }
    (tmp_path / "line.geojson").write_text(json.dumps(line))
    capsys.readouterr()
    assert (
        main(
            [
                "path",
                str(out / "dtm.tif"),
                str(tmp_path / "line.geojson"),
                "--crs",
                "native",
                "--format",
                "json",
                "--spacing",
                "5",
            ]
        )
        == 0
    )
    answer = json.loads(capsys.readouterr().out)
    assert answer["crs"] == "EPSG:32632"
    records = answer["samples"]
    east = [r for r in records if r["distance"] < 39]
    north = [r for r in records if 41 < r["distance"] < 69]
    expected = np.degrees(np.arctan(0.1))
    assert all(abs(r["pitch_deg"] - expected) < 0.5 and abs(r["roll_deg"]) < 0.5 for r in east)
    assert all(
        abs(r["pitch_deg"]) < 0.5 and abs(abs(r["roll_deg"]) - expected) < 0.5 for r in north
    )
    with rasterio.open(out / "slope.tif") as ds:
        slope = ds.read(1, masked=True)
        assert abs(float(np.ma.median(slope)) - expected) < 0.5
