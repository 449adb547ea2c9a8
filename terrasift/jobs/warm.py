"""Where numba keeps the compiled kernels, and how an install compiles them once.

Every stage's loops are numba kernels cached on disk (``cache=True``). On a fresh
install, or after an edit to a kernel module, the cache is empty and each worker
process compiles every kernel it meets, the workers at once (README, *Measured*:
the first job's cost). Numba keys each kernel's cache on its source file's modification time
and size, so an edited kernel module is compiled again and never taken stale (the
kernels live in ``*_kernels.py`` modules for that reason: an edit elsewhere
compiles nothing).

Numba caches beside the modules (``__pycache__``) when the package folder is
writable, else in ``NUMBA_CACHE_DIR``, else in the user's cache folder, which a
service account may lack: then every new worker compiles again. ``cache_dir_for``
gives the service a folder under its data folder in that case; it takes effect in
worker processes started afterwards (numba reads it when a kernel is defined).
``python -m terrasift.warmup`` compiles everything once (an install step; the
Docker image runs it, so its first job starts compiled; numba's cache is also keyed
on the CPU, so a machine of another kind compiles again).
"""

from __future__ import annotations

import os
from pathlib import Path

import terrasift


def cache_dir_for(data_dir: Path) -> Path | None:
    """``data_dir/numba-cache`` when the package folder is read-only and no
    ``NUMBA_CACHE_DIR`` is given, else None (numba's own choice works)."""
    if os.environ.get("NUMBA_CACHE_DIR") or os.access(Path(terrasift.__file__).parent, os.W_OK):
        return None
    return Path(data_dir) / "numba-cache"
