"""`terrasift survey DIR --server URL` against a live service: state, lock, resume, product."""

from __future__ import annotations

import fcntl
import json
import os
from pathlib import Path

import httpx
import laspy
import numpy as np
import pytest
import rasterio
from live_server import live_server

from terrasift.service.settings import Settings
from terrasift.survey import LOCK_FILE, OUT_DIR, STATE_FILE, run_survey
from terrasift.synthetic.terrain import make_scene, write_tiles

PARAMS = {"block_size": 20, "resolution": 0.5, "features": "hill"}


def _runs(server: str, sid: str) -> list[dict]:
    return httpx.get(f"{server}/surveys/{sid}").json()["jobs"]


def _summary(server: str, job_id: str) -> dict:
    return httpx.get(f"{server}/jobs/{job_id}/outputs/survey.json").json()


def test_survey_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "area"
    paths = write_tiles(make_scene(40.0, 3.0, n_buildings=0, seed=9), folder, 20.0)
    settings = Settings(_env_file=None, data_dir=tmp_path / "data", workers=1)
    with live_server(settings) as server:
        assert run_survey(folder, server, PARAMS, poll=0.1) == 0
        state = json.loads((folder / STATE_FILE).read_text())
        sid = state["survey"]
        assert sorted(state["tiles"]) == [p.name for p in paths] and "run" not in state
        out = folder / OUT_DIR
        assert (out / "dtm.vrt").exists() and (out / "tiles/t0_0/classified.laz").exists()
        assert len(_runs(server, sid)) == 1
        # the mosaic reads in place over HTTP: GDAL resolves the VRT's relative tile paths
        url = f"/vsicurl/{server}/surveys/{sid}/outputs/dtm.vrt"
        with rasterio.Env(GDAL_DISABLE_READDIR_ON_OPEN="EMPTY_DIR"), rasterio.open(url) as ds:
            remote = ds.read(1)
        with rasterio.open(out / "dtm.vrt") as ds:
            assert np.array_equal(remote, ds.read(1)) and (remote != ds.nodata).mean() > 0.9

        # touch changes nothing: no upload, no run
        os.utime(paths[0])
        capsys.readouterr()
        assert run_survey(folder, server, PARAMS, poll=0.1) == 0
        assert "nothing changed" in capsys.readouterr().out
        assert len(_runs(server, sid)) == 1

        # an overlapping call (cron) exits at once
        with open(folder / LOCK_FILE, "a") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            assert run_survey(folder, server, PARAMS, poll=0.1) == 3
            fcntl.flock(fh, fcntl.LOCK_UN)

        # a call stopped right after submitting: the next call waits for that run
        las = laspy.read(paths[1])
        las.z = np.asarray(las.z) + 0.3
        las.write(paths[1])
        r = httpx.put(
            f"{server}/surveys/{sid}/tiles/{paths[1].name}",
            content=paths[1].read_bytes(),
            headers={"content-type": "application/octet-stream"},
        )
        assert r.status_code == 200, r.text
        started = httpx.post(f"{server}/surveys/{sid}/runs", json={"params": PARAMS})
        assert started.status_code == 201, started.text
        capsys.readouterr()
        assert run_survey(folder, server, PARAMS, poll=0.1) == 0
        assert f"resuming run {started.json()['jobID']}" in capsys.readouterr().out
        runs = _runs(server, sid)
        assert len(runs) == 2 and runs[-1]["status"] == "successful"  # nothing resubmitted
        assert paths[1].name in _summary(server, runs[-1]["jobID"])["outputs"]

        # a changed parameter redoes every tile
        assert run_survey(folder, server, {**PARAMS, "resolution": 1.0}, poll=0.1) == 0
        runs = _runs(server, sid)
        assert len(runs) == 3
        summary = _summary(server, runs[-1]["jobID"])
        assert summary["mode"] == "parameters changed" and len(summary["outputs"]) == 4

        # a removed tile leaves the survey and the downloaded product
        paths[3].unlink()
        assert run_survey(folder, server, {**PARAMS, "resolution": 1.0}, poll=0.1) == 0
        assert not (out / "tiles" / paths[3].stem).exists()
        assert (out / "dtm.vrt").exists()
