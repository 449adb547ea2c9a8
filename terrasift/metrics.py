"""Accuracy of a ground filter against reference labels (Sithole & Vosselman 2004).

Type I: ground called object, over reference ground. Type II: object called
ground, over reference object. Total: all errors over all points. Kappa:
Cohen's agreement beyond chance.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class GroundScore:
    n: int
    type1: float  # fraction
    type2: float
    total: float
    kappa: float

    def as_percent(self) -> dict[str, float]:
        d = asdict(self)
        return {k: (round(100 * v, 2) if k != "n" else v) for k, v in d.items()}


def ground_score(
    truth_ground: NDArray[np.bool_], predicted_ground: NDArray[np.bool_]
) -> GroundScore:
    """Score ``predicted_ground`` against ``truth_ground`` (boolean per point)."""
    t = np.asarray(truth_ground, dtype=bool)
    p = np.asarray(predicted_ground, dtype=bool)
    if t.shape != p.shape:
        raise ValueError(f"shape mismatch: {t.shape} vs {p.shape}")
    n = t.size
    a = np.count_nonzero(t & p)  # ground as ground
    b = np.count_nonzero(t & ~p)  # ground as object (Type I)
    c = np.count_nonzero(~t & p)  # object as ground (Type II)
    d = np.count_nonzero(~t & ~p)
    type1 = b / (a + b) if a + b else 0.0
    type2 = c / (c + d) if c + d else 0.0
    total = (b + c) / n if n else 0.0
    observed = (a + d) / n if n else 1.0
    expected = ((a + b) * (a + c) + (c + d) * (b + d)) / (n * n) if n else 1.0
    kappa = (observed - expected) / (1 - expected) if expected < 1 else 1.0
    return GroundScore(n, type1, type2, total, kappa)
