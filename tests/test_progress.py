"""Progress as work done: the meter itself, a whole job's trace, warnings in
statusInfo and in the CLI's summary."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from terrasift import jobs as pipeline
from terrasift.cli import main
from terrasift.progress import COST, JobProgress
from terrasift.service.app import create_app
from terrasift.service.settings import Settings
from terrasift.synthetic.terrain import make_scene, write_las
from terrasift.workers.executors import InlineExecutor

PARAMS = {"block_size": 30, "buffer": 5, "resolution": 1.0}


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_meter_weighs_points_by_cost_and_never_goes_back() -> None:
    calls: list[tuple[int, int, dict]] = []
    clock = Clock()
    meter = JobProgress(lambda d, t, i: calls.append((d, t, dict(i))), 1_000_000, clock=clock)
    meter.add("shard", "a", "shard", 1_000_000)
    meter.add("finish", 0, "raster", 1_000_000)
    meter.reserve("blocks", "block")
    meter.enter("shard")
    clock.t = 0.5
    meter.done("shard", "a")
    meter.split("blocks", {"b1": 3.0, "b2": 1.0}, "block")
    meter.enter("blocks")
    total = COST["shard"] + COST["block"] + COST["raster"]
    assert meter.total == pytest.approx(total)
    meter.done("blocks", "b2")  # the small block: a quarter of the block stage
    expected = (COST["shard"] + COST["block"] / 4) / total
    assert calls[-1][0] / calls[-1][1] == pytest.approx(expected, abs=1e-3)
    assert "1 of 2 blocks" in calls[-1][2]["message"]
    assert "0.25 of 1.00 M points" in calls[-1][2]["message"]
    # between completions the estimate moves on at the observed rate, capped below the running work
    clock.t = 1.0
    before = meter.percent()
    clock.t = 2.0
    meter.report()
    assert meter.percent() > before
    clock.t = 1e6
    assert meter.percent() < 100 * (meter.done_work + meter._stages["blocks"].work) / total
    high = meter.percent()
    meter.done("blocks", "b1")  # the real completion lands below the estimate: no step back
    assert meter.percent() >= high
    pcts = [d / t for d, t, _ in calls]
    assert pcts == sorted(pcts)


def test_job_trace_is_monotonic_with_stages_and_counts(tmp_path: Path) -> None:
    scene = make_scene(size=60, density=4, seed=3)
    tile = write_las(scene, tmp_path / "t.laz", crs=None)
    job = tmp_path / "job"
    params = pipeline.validate_params(PARAMS)
    pipeline.prepare_job(job, [tile], params)
    calls: list[tuple[float, dict]] = []
    pipeline.run_job(job, InlineExecutor(), lambda d, t, i: calls.append((d / t, dict(i))))
    fractions = [f for f, _ in calls]
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(1.0)
    stages = list(dict.fromkeys(i["stage"] for _, i in calls))
    assert stages == ["shard", "blocks", "finish", "report"]
    blocks = [i["message"] for _, i in calls if i["stage"] == "blocks"]
    last = re.search(r"(\d+) of (\d+) blocks, ([\d,]+) of ([\d,]+) points", blocks[-1])
    assert last and last[1] == last[2] and last[3] == last[4] == f"{len(scene):,}", blocks[-1]
    assert any("no CRS" in w for w in calls[-1][1]["warnings"])
    # quicklooks are outputs, listed in the STAC item as thumbnail and overviews
    item = json.loads((job / "outputs" / "item.json").read_text())
    roles = {name: a["roles"] for name, a in item["assets"].items() if name.endswith(".png")}
    assert roles["thumbnail.png"] == ["thumbnail"] and roles["hillshade.png"] == ["overview"]
    assert {"chm.png", "coverage.png", "categories.png", "steep_blocks.png"} <= set(roles)
    assert item["assets"]["chm.png"]["type"] == "image/png"
    # the block stage weighs what it costs, not what its task count says
    share = {s: max(f for f, i in calls if i["stage"] == s) for s in stages}
    assert share["blocks"] - share["shard"] > 0.5


def test_status_carries_warnings_and_stage(tmp_path: Path) -> None:
    tile = write_las(make_scene(size=40, density=4, seed=5), tmp_path / "t.laz", crs=None)
    app = create_app(Settings(_env_file=None, data_dir=tmp_path / "data", workers=1))
    with TestClient(app) as c:
        r = c.post(
            "/jobs",
            files=[("file", ("t.laz", tile.read_bytes()))],
            data={"params": json.dumps(PARAMS)},
        )
        job_id = r.json()["jobID"]
        seen: list[dict[str, Any]] = []
        end = time.monotonic() + 120
        while time.monotonic() < end:
            seen.append(c.get(f"/jobs/{job_id}").json())
            if seen[-1]["status"] not in ("accepted", "running"):
                break
            time.sleep(0.1)
        final = seen[-1]
        assert final["status"] == "successful", final
        assert any("no CRS" in w for w in final["warnings"])
        progress = [s["progress"] for s in seen]
        assert progress == sorted(progress)
        running = [s for s in seen if s["status"] == "running" and "stage" in s]
        assert all(s["message"].startswith(("reading", "classifying", "writing")) for s in running)


def test_cli_prints_warnings_and_summary(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    tile = write_las(make_scene(size=40, density=4, seed=5), tmp_path / "t.laz", crs=None)
    args = [f"--param={k}={v}" for k, v in {**PARAMS, "workers": 1}.items()]
    code = main(["process", str(tile), "--out", str(tmp_path / "out"), "--quiet", *args])
    assert code == 0
    err = capsys.readouterr().err
    assert "terrasift: warning: no CRS known" in err
    summary = [ln for ln in err.splitlines() if " points of 1 tile(s)" in ln]
    assert summary and "points/s" in summary[0] and "class 2:" in summary[0]
