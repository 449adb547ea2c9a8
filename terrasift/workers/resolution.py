"""Stage sizes that follow the job's resolution: vegetation bins, roughness bins, category tiles.

The vegetation bins and the category tiles are laid on the DTM grid's
origin, and the roughness bins on the block's, so each must be a whole
number of DTM cells. A size the job does not set follows the resolution:
its nominal value (the stage's default: 1 m bins, 2 m category tiles)
snapped to the nearest whole number of cells, with at least the cells the
stage needs (a category tile is fitted by planes through its boundary
points: two cells at least). A size the job sets is kept, and refused only
when it contradicts the resolution.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from terrasift.workers.registry import get_stage

#: (stage id, field, fewest DTM cells it may span)
RESOLUTION_FIELDS: tuple[tuple[str, str, int], ...] = (
    ("vegetation", "cell", 1),
    ("terrain", "cell", 1),
    ("categories", "tile_size", 2),
)


def snap(nominal: float, resolution: float, min_cells: int = 1) -> float:
    """``nominal`` metres as the nearest whole number (≥ ``min_cells``) of ``resolution`` cells."""
    cells = max(min_cells, int(round(nominal / resolution)))
    return round(cells * resolution, 9)


def follow_resolution(
    resolution: float, given: Mapping[str, Any]
) -> tuple[dict[str, float], list[str]]:
    """Values for the resolution-dependent keys the job leaves out, and one
    message per given key that contradicts ``resolution``.

    ``given`` holds the job's keys (``vegetation.cell`` …) with validated values.
    """
    derived: dict[str, float] = {}
    conflicts: list[str] = []
    for stage_id, field, min_cells in RESOLUTION_FIELDS:
        key = f"{stage_id}.{field}"
        if key in given:
            value = float(given[key])
            k = value / resolution
            if round(k) < min_cells or abs(k - round(k)) > 1e-6:
                conflicts.append(
                    f"{key} ({value:g}) must be a whole multiple of resolution ({resolution:g}), "
                    f"at least {min_cells} cell{'s' if min_cells > 1 else ''}: "
                    f"e.g. {snap(value, resolution, min_cells):g}, or leave it out to follow the resolution"
                )
            continue
        nominal = float(get_stage(stage_id).params.model_fields[field].default)
        derived[key] = snap(nominal, resolution, min_cells)
    return derived, conflicts
