"""Atomic writes and JSON reads: the one way this package writes a result file.

Every task writes its result under a temporary sibling name and renames it
onto the final name when complete, so a crash or a repeated task never
leaves a half-written result and a file that exists is whole (DESIGN §1).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

#: suffix of a result still being written; listings of results skip these
PARTIAL = ".part"


def partial_path(path: Path, keep_suffix: bool = False) -> Path:
    """The temporary sibling ``path`` is written under: ``.<name>.part``, or
    ``.<stem>.part<suffix>`` for writers that choose a format by suffix (GDAL)."""
    if keep_suffix:
        return path.with_name(f".{path.stem}{PARTIAL}{path.suffix}")
    return path.with_name(f".{path.name}{PARTIAL}")


@contextmanager
def atomic_path(
    path: str | Path, *, keep_suffix: bool = False, make_parents: bool = True
) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` to write (a file or a folder) and
    rename it onto ``path`` when the block ends without an error.

    A stale temporary from an earlier crash is removed first; on an error the
    temporary is removed and ``path`` is left as it was. A folder replaces a
    folder already at ``path``. Missing parent folders are created unless
    ``make_parents`` is off (a folder that may have been removed on purpose,
    such as a dismissed job's, is then not brought back: OSError instead).
    """
    path = Path(path)
    if make_parents:
        path.parent.mkdir(parents=True, exist_ok=True)
    tmp = partial_path(path, keep_suffix)
    _remove(tmp)
    try:
        yield tmp
    except BaseException:
        _remove(tmp)
        raise
    if tmp.is_dir() and path.is_dir():
        shutil.rmtree(path)
    os.replace(tmp, path)


def write_json(path: str | Path, data: Any, *, indent: int | None = None) -> None:
    """Write ``data`` as JSON at ``path`` atomically (values JSON does not know as strings)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=indent, default=str))


def load_json(path: str | Path) -> Any:
    """The JSON document at ``path``."""
    return json.loads(Path(path).read_text())


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)
