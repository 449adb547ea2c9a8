"""Hard synthetic scenes for ground filters, with exact truth (built on ``make_scene``).

- ``forest_on_slopes``: dense trees and bushes on hilly terrain with 15–30° slopes;
- ``buildings``: a built-up area with many large flat-roofed buildings on gentle terrain;
- ``steep_hillside``: bare ground whose slope varies between 35° and 45°, the
  case where level select/reject mistakes a slope for vegetation;
- ``ground_based``: a scan from a mast, its density falling with the square of
  the range (no occlusion modelled), for the concentric grid.

Every scene keeps ``make_scene``'s low and high outliers (class 7), so a
filter must also be robust to them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from terrasift.synthetic.terrain import Scene, Surface, make_scene


def forest_on_slopes(size: float = 200.0, density: float = 8.0, *, seed: int = 1) -> Scene:
    """Forest (0.02 trees and 0.01 bushes per m²) over hills with slopes up to ~30°."""
    surface = Surface(
        z0=300.0,
        gx=0.35,
        gy=0.1,
        waves=((6.0, 120.0, 20.0, 0.0), (2.5, 45.0, 110.0, 1.0)),
        hills=((0.3 * size, 0.6 * size, 15.0, 25.0),),
    )
    return make_scene(
        size,
        density,
        surface=surface,
        n_buildings=0,
        tree_density=0.02,
        bush_density=0.01,
        seed=seed,
    )


def buildings(size: float = 200.0, density: float = 8.0, *, seed: int = 2) -> Scene:
    """Town: 25 buildings of 10–45 m and 4–20 m height on gentle, undulating terrain."""
    return make_scene(
        size,
        density,
        n_buildings=25,
        building_size=(10.0, 45.0),
        building_height=(4.0, 20.0),
        tree_density=0.002,
        bush_density=0.002,
        seed=seed,
    )


def steep_hillside(
    size: float = 200.0,
    density: float = 8.0,
    *,
    angle_deg: float = 40.0,
    spread_deg: float = 5.0,
    seed: int = 3,
) -> Scene:
    """Bare hillside whose slope swings between ``angle ± spread`` degrees (35–45° by default)."""
    g = np.tan(np.radians(angle_deg))
    # A sinusoid along the fall line with amplitude A and wavelength L adds a
    # slope of up to A·2π/L; choose A so the slope spans the requested range.
    swing = 0.5 * (
        np.tan(np.radians(angle_deg + spread_deg)) - np.tan(np.radians(angle_deg - spread_deg))
    )
    wavelength = 60.0
    amp = swing * wavelength / (2 * np.pi)
    surface = Surface(z0=200.0, gx=g, gy=0.0, waves=((amp, wavelength, 0.0, 0.0),))
    return make_scene(
        size, density, surface=surface, n_buildings=0, tree_density=0.0, bush_density=0.0, seed=seed
    )


def ground_based(
    radius: float = 50.0, near_density: float = 100.0, *, near: float = 5.0, seed: int = 4
) -> tuple[Scene, NDArray[np.float64]]:
    """A ground-based scan of gently rolling terrain with bushes and trees, and
    its sensor origin (1.8 m above the ground at the centre).

    Density is ``near_density`` pts/m² out to ``near`` metres and falls as
    (near / r)² beyond (a scanner's fixed angular step), out to ``radius``.
    """
    size = 2 * radius
    dense = make_scene(
        size, near_density, n_buildings=0, tree_density=0.004, bush_density=0.01, seed=seed
    )
    xmin, ymin = dense.bounds[0], dense.bounds[1]
    cx, cy = xmin + radius, ymin + radius
    r = np.hypot(dense.xyz[:, 0] - cx, dense.xyz[:, 1] - cy)
    keep_prob = np.minimum(1.0, (near / np.maximum(r, 1e-9)) ** 2)
    keep = (r <= radius) & (np.random.default_rng(seed + 1).random(r.size) < keep_prob)
    scene = Scene(
        dense.xyz[keep],
        dense.truth[keep],
        dense.return_number[keep],
        dense.number_of_returns[keep],
        dense.surface,
        dense.bounds,
        {k: v[keep] for k, v in dense.extra.items()},
    )
    origin = np.array([cx, cy, float(dense.surface(np.array([cx]), np.array([cy]))[0]) + 1.8])
    return scene, origin


SCENES = {
    "forest_on_slopes": forest_on_slopes,
    "buildings": buildings,
    "steep_hillside": steep_hillside,
}
