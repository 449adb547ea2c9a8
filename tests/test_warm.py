"""Numba's cache folder: the service's own for read-only installs, numba's choice otherwise."""

from __future__ import annotations

from pathlib import Path

from terrasift.jobs import warm


def test_a_read_only_install_caches_under_the_data_folder(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setattr(warm.os, "access", lambda path, mode: False)
    assert warm.cache_dir_for(tmp_path) == tmp_path / "numba-cache"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "given"))
    assert warm.cache_dir_for(tmp_path) is None  # the operator's choice stands


def test_a_writable_install_keeps_numba_s_choice(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setattr(warm.os, "access", lambda path, mode: True)
    assert warm.cache_dir_for(tmp_path) is None
