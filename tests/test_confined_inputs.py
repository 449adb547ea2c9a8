"""Inputs are re-checked against the input root on the opened file, in the task that reads it:
a file or folder swapped for a symbolic link after the job started is refused."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from terrasift import jobs
from terrasift.errors import InputError
from terrasift.tiling.lasfile import open_input
from terrasift.workers.executors import Future, InlineExecutor


def test_open_input_checks_the_opened_file(tmp_path: Path) -> None:
    root = tmp_path / "root"
    (root / "sub").mkdir(parents=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    for folder in (root, root / "sub", elsewhere):
        (folder / "a.las").write_bytes(b"LASF" + bytes(300))
    roots = [str(root.resolve())]
    with open_input(root / "a.las", roots) as fh:
        assert fh.read(4) == b"LASF"
    (root / "link.las").symlink_to(elsewhere / "a.las")
    with pytest.raises(InputError, match="symbolic link"):
        open_input(root / "link.las", roots)
    (root / "inner.las").symlink_to(root / "a.las")  # even one that stays inside: not followed
    with pytest.raises(InputError, match="symbolic link"):
        open_input(root / "inner.las", roots)
    shutil.rmtree(root / "sub")
    (root / "sub").symlink_to(elsewhere)  # a folder on the way swapped for a link
    with pytest.raises(InputError, match="outside the input root"):
        open_input(root / "sub" / "a.las", roots)
    (root / "same").symlink_to(root)  # a folder link that stays inside the root is fine
    with open_input(root / "same" / "a.las", roots) as fh:
        assert fh.read(4) == b"LASF"
    os.mkfifo(root / "fifo.las")  # opened without blocking, then refused
    with pytest.raises(InputError, match="regular file"):
        open_input(root / "fifo.las", roots)
    with open_input(root / "link.las") as fh:  # without roots (the CLI): any path
        assert fh.read(4) == b"LASF"


class _SwapAtFirstTask(InlineExecutor):
    """Runs tasks inline; before the first one, ``swap`` replaces the input."""

    def __init__(self, swap: Callable[[], None]):
        self.swap: Callable[[], None] | None = swap

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        if self.swap is not None:
            self.swap()
            self.swap = None
        return super().submit(fn, *args)


@pytest.mark.parametrize("what", ["file", "folder"])
def test_a_swap_after_the_job_started_fails_the_job(
    tmp_path: Path, small_tile: Path, what: str
) -> None:
    root = tmp_path / "root"
    (root / "survey").mkdir(parents=True)
    tile = root / "survey" / "tile.laz"
    shutil.copy(small_tile, tile)
    outside = tmp_path / "outside"
    outside.mkdir()
    shutil.copy(small_tile, outside / "tile.laz")  # a readable file: only the check stops it
    job = tmp_path / "job"
    jobs.prepare_job(job, [tile], jobs.validate_params({"block_size": 80, "buffer": 15}))
    jobs.set_input_roots(job, [root])

    def swap() -> None:
        if what == "file":
            tile.unlink()
            tile.symlink_to(outside / "tile.laz")
        else:
            shutil.rmtree(root / "survey")
            (root / "survey").symlink_to(outside)

    # the plan (job start) still sees the file inside; the shard task opens it after the swap
    with pytest.raises(InputError, match="symbolic link" if what == "file" else "outside"):
        jobs.run_job(job, _SwapAtFirstTask(swap))
    assert not (job / "shards").exists() or not any((job / "shards").iterdir())


def test_a_job_whose_input_left_the_root_before_planning_fails(
    tmp_path: Path, small_tile: Path
) -> None:
    root = tmp_path / "root"
    root.mkdir()
    tile = root / "tile.laz"
    shutil.copy(small_tile, tile)
    job = tmp_path / "job"
    jobs.prepare_job(job, [tile], jobs.validate_params({"block_size": 80, "buffer": 15}))
    jobs.set_input_roots(job, [root])
    tile.unlink()
    tile.symlink_to(small_tile)
    with pytest.raises(InputError, match="symbolic link"):
        jobs.run_job(job, InlineExecutor())
    assert not (job / "plan.json").exists()
