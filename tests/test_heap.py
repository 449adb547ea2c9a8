"""The serving process freezes its start-up heap: full garbage collections stay short."""

from __future__ import annotations

import gc
import sys
from pathlib import Path

from fastapi.testclient import TestClient

from terrasift.service.app import create_app
from terrasift.service.settings import Settings


def test_serve_freezes_the_heap_after_importing_what_jobs_need(tmp_path: Path) -> None:
    gc.unfreeze()
    app = create_app(Settings(data_dir=tmp_path, auth="off"), freeze_heap=True)
    try:
        with TestClient(app) as client:
            frozen = gc.get_freeze_count()
            tracked = len(gc.get_objects())
            assert client.get("/jobs").status_code == 200
        assert "terrasift.jobs" in sys.modules  # the job driver's imports came first
        # a full collection now walks only what was allocated after start-up
        assert frozen > 50_000 and tracked < frozen / 5
    finally:
        gc.unfreeze()


def test_the_heap_is_left_alone_without_the_flag(tmp_path: Path) -> None:
    gc.unfreeze()
    with TestClient(create_app(Settings(data_dir=tmp_path, auth="off"))):
        assert gc.get_freeze_count() == 0
