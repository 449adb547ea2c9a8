"""The rooms import one way (DESIGN §2): service/cli -> jobs -> workers -> tiling.

Every import counts, those inside functions too: the test reads the source
with ``ast`` rather than importing it.
"""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "terrasift"

#: room of a module by its first part under terrasift/; the rest (errors, files,
#: metrics) is the base every room may import
ROOMS = {
    "tiling": "tiling",
    "workers": "workers",
    "jobs": "jobs",
    "service": "service",
    "cli": "cli",
    "__main__": "cli",
    "survey": "cli",
    "warmup": "cli",
    "synthetic": "synthetic",  # scenes with exact truth, for tests and benchmarks
}

#: rooms a room must never import
FORBIDDEN = {
    "base": {"tiling", "workers", "jobs", "service", "cli", "synthetic"},
    "tiling": {"workers", "jobs", "service", "cli", "synthetic"},
    "workers": {"jobs", "service", "cli", "synthetic"},
    "jobs": {"service", "cli", "synthetic"},
    "service": {"cli", "synthetic"},
    "synthetic": {"jobs", "service", "cli"},
}


def _room(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] != "terrasift" or len(parts) < 2:
        return None
    return ROOMS.get(parts[1], "base")


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in ``path``, at any depth."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = ".".join(("terrasift", *path.relative_to(PACKAGE).with_suffix("").parts[:-1]))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            if module == "terrasift":  # from terrasift import jobs
                found += [(node.lineno, f"terrasift.{alias.name}") for alias in node.names]
            else:
                found.append((node.lineno, module))
    return found


@cache
def _edges() -> tuple[tuple[str, str, str], ...]:
    """(importing room, imported room, where) over every module of the package; read once
    for all the tests below."""
    edges = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).with_suffix("")
        src = _room("terrasift." + ".".join(rel.parts))
        for line, module in _imports(path):
            dst = _room(module)
            if src and dst and src != dst:
                edges.append(
                    (src, dst, f"{path.relative_to(PACKAGE.parent)}:{line} imports {module}")
                )
    return tuple(edges)


def test_the_walk_sees_function_level_imports():
    where = [w for _, _, w in _edges() if w.startswith("terrasift/cli.py")]
    assert any("terrasift.jobs" in w for w in where), where


@pytest.mark.parametrize("room", sorted(FORBIDDEN))
def test_rooms_import_only_downwards(room):
    bad = [w for src, dst, w in _edges() if src == room and dst in FORBIDDEN[room]]
    assert not bad, "\n".join(bad)


def test_no_cycle_between_rooms():
    graph: dict[str, set[str]] = {}
    for src, dst, _ in _edges():
        graph.setdefault(src, set()).add(dst)
    done: set[str] = set()

    def visit(room: str, path: list[str]) -> None:
        if room in path:
            raise AssertionError("import cycle between rooms: " + " -> ".join([*path, room]))
        if room in done:
            return
        for nxt in sorted(graph.get(room, ())):
            visit(nxt, [*path, room])
        done.add(room)

    for room in sorted(graph):
        visit(room, [])
