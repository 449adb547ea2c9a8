"""A tile header reader that misbehaves on request, for the header readers' tests.

A module of its own with light imports: a reader process imports it (by name) to
run it, and the import counts against the reader's CPU budget.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from terrasift.tiling.lasfile import TileInfo, read_tile_info


def misbehaving_read(path: str, *, max_points: int | None = None) -> TileInfo:
    """``read_tile_info``, except for files whose name asks the reader to misbehave."""
    name = Path(path).name
    if name.startswith("abort"):
        os.abort()  # what a Rust decoder does when an allocation fails
    if name.startswith("greedy"):
        held = bytearray(2 * 1024**3)  # beyond the reader's address-space budget
        held[-1] = 1
    if name.startswith("spin"):
        while True:
            pass
    if name.startswith("sleepy"):
        time.sleep(60)  # a reader that gets no CPU (a stalled disk, a starved machine)
    if name.startswith("slow"):
        # record which reader read it and when, beside the file: two readers at once?
        started = time.time()
        time.sleep(0.5)
        with open(f"{path}.read", "w") as fh:
            fh.write(f"{os.getpid()} {started} {time.time()}")
    if name.startswith("killed"):
        os.kill(os.getpid(), signal.SIGKILL)  # as the OOM killer would
    return read_tile_info(path, max_points=max_points)
