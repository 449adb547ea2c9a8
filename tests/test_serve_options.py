"""`terrasift serve` runs with the faster event loop and HTTP parser and no access log."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from terrasift.service import app as app_module
from terrasift.service.settings import Settings


def test_serve_has_no_access_log_by_default_and_uses_uvloop_and_httptools(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import uvicorn
    from uvicorn.config import Config

    calls: list[dict[str, Any]] = []
    monkeypatch.setattr(uvicorn, "run", lambda app, **kw: calls.append(kw))
    app_module.serve(settings=Settings(_env_file=None, data_dir=tmp_path / "data"))
    monkeypatch.setenv("TERRASIFT_ACCESS_LOG", "true")
    app_module.serve(settings=Settings(_env_file=None, data_dir=tmp_path / "data"))
    assert [c["access_log"] for c in calls] == [False, True]
    # uvicorn's "auto" choices take them when they can be imported
    config = Config(app=lambda *a: None, loop="auto", http="auto")
    config.load()
    assert config.http_protocol_class.__module__.endswith("httptools_impl")
    import uvloop  # noqa: F401 - a dependency where uvicorn's auto loop looks for it
