"""Run one piece of code in fresh processes of this tree and of another checkout.

The label- and mark-identity benchmarks (``ground_labels.py``, ``mixed_marks.py``)
and the ground speed row share it: each run gets a fresh interpreter whose import
path starts at the checkout under test, so two commits never share a module, and
runs of the two trees alternate so that load on a shared machine falls on both.
"""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np


def run_code(code: Path, script: str, *args: str) -> float:
    """Run ``script`` with ``sys.argv[1]`` = ``code`` and the last printed number returned."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(code))
    res = subprocess.run(
        [sys.executable, "-c", script, str(code), *args],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        cwd=code,
    )
    return float(res.stdout.strip().splitlines()[-1])


@dataclass
class Pair:
    """Outputs of the first run of each tree and median CPU seconds over all runs."""

    ours: np.ndarray
    theirs: np.ndarray
    cpu_ours: float
    cpu_theirs: float

    @property
    def same(self) -> bool:
        return bool(np.array_equal(self.ours, self.theirs))

    @property
    def verdict(self) -> str:
        return "identical" if self.same else f"{np.count_nonzero(self.ours != self.theirs)} differ"

    @property
    def ratio(self) -> float:
        """Baseline CPU over ours: above 1 when this tree is faster."""
        return self.cpu_theirs / self.cpu_ours


def alternate(script: str, ours: Path, base: Path, out: Path, runs: int, *args: str) -> Pair:
    """``runs`` alternated runs of ``script`` on both trees, compared.

    The script reads its tree from ``sys.argv[1]``, saves its output array to the
    ``.npy`` path in ``sys.argv[2]``, takes ``args`` after that and prints its CPU seconds.
    """
    t_ours, t_base = [], []
    for _ in range(runs):
        t_ours.append(run_code(ours, script, str(out / "ours.npy"), *args))
        t_base.append(run_code(base, script, str(out / "base.npy"), *args))
        if len(t_ours) == 1:
            first = np.load(out / "ours.npy"), np.load(out / "base.npy")
    return Pair(first[0], first[1], float(np.median(t_ours)), float(np.median(t_base)))
