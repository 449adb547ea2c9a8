"""Quicklook pictures of rasters: hillshade, colour ramps, class colours, PNG encoding.

Pure functions from numpy arrays to RGBA arrays and PNG bytes; no files, no
jobs. Nodata (NaN, or a mask) is transparent, so a quicklook over a tile's
irregular footprint shows the footprint. PNGs are written here with zlib
(one IDAT, filter type 0): no imaging library is needed.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

RGBA = NDArray[np.uint8]

#: vegetation bins of coverage.tif: value -> (label, colour)
COVERAGE_CLASSES: dict[int, tuple[str, tuple[int, int, int]]] = {
    0: ("empty", (235, 235, 235)),
    1: ("open", (237, 222, 160)),
    2: ("bush", (134, 190, 90)),
    3: ("tree", (26, 110, 46)),
    4: ("building", (200, 60, 60)),
}

#: categories.tif band 1 (inclination: the direction the tile rises toward) -> (label, colour)
INCLINATION_CLASSES: dict[int, tuple[str, tuple[int, int, int]]] = {
    0: ("level", (220, 220, 220)),
    1: ("rises E", (230, 97, 1)),
    2: ("rises NE", (253, 184, 99)),
    3: ("rises N", (255, 237, 111)),
    4: ("rises NW", (166, 217, 106)),
    5: ("rises W", (26, 152, 80)),
    6: ("rises SW", (102, 194, 165)),
    7: ("rises S", (50, 136, 189)),
    8: ("rises SE", (94, 79, 162)),
}

#: categories.tif band 3 (state) drawn over the inclination colours
STATE_CLASSES: dict[int, tuple[str, tuple[int, int, int]]] = {
    1: ("convex edge (ridge-like)", (255, 255, 255)),
    2: ("concave edge (ditch-like)", (20, 20, 90)),
}

#: colour stops of the canopy-height ramp (fraction of the top height -> colour)
CHM_RAMP: tuple[tuple[float, tuple[int, int, int]], ...] = (
    (0.0, (247, 252, 185)),
    (0.25, (173, 221, 142)),
    (0.5, (65, 171, 93)),
    (0.75, (0, 104, 55)),
    (1.0, (0, 50, 30)),
)

#: feature kinds -> colour over the hillshade
FEATURE_COLOURS: dict[str, tuple[int, int, int]] = {
    "ditch": (31, 120, 180),
    "pond": (166, 206, 227),
    "ridge": (227, 26, 28),
    "hill": (255, 127, 0),
    "road": (106, 61, 154),
    "flat-area": (255, 255, 51),
    "flat": (255, 255, 153),
}
OTHER_FEATURE = (255, 0, 255)


def hillshade(
    dem: NDArray, cell: float, azimuth: float = 315.0, altitude: float = 45.0, z: float = 1.0
) -> NDArray[np.float64]:
    """Shade 0-1 of a DEM lit from ``azimuth`` (degrees clockwise from north) at ``altitude``; NaN stays NaN."""
    dem = np.asarray(dem, dtype=np.float64)
    filled = np.where(np.isnan(dem), np.nanmean(dem) if np.isfinite(dem).any() else 0.0, dem)
    d_row, d_col = np.gradient(filled * z, cell)
    east, north = d_col, -d_row  # rows run south
    az, alt = np.radians(azimuth), np.radians(altitude)
    light = (np.sin(az) * np.cos(alt), np.cos(az) * np.cos(alt), np.sin(alt))
    # the surface normal (-east, -north, 1), normalised, dotted with the light direction
    shade = (-east * light[0] - north * light[1] + light[2]) / np.sqrt(1 + east**2 + north**2)
    shade = np.clip(shade, 0.0, 1.0)
    shade[np.isnan(dem)] = np.nan
    return shade


def grey(values: NDArray) -> RGBA:
    """0-1 values as opaque grey; NaN transparent."""
    v = np.nan_to_num(np.asarray(values, dtype=np.float64), nan=0.0)
    g = (np.clip(v, 0, 1) * 255).astype(np.uint8)
    alpha = np.where(np.isnan(values), 0, 255).astype(np.uint8)
    return np.dstack([g, g, g, alpha])


def ramp(
    values: NDArray, top: float, stops: Sequence[tuple[float, tuple[int, int, int]]] = CHM_RAMP
) -> RGBA:
    """Values 0..``top`` through the colour ``stops``; NaN transparent."""
    v = np.asarray(values, dtype=np.float64)
    f = np.clip(np.nan_to_num(v, nan=0.0) / (top if top > 0 else 1.0), 0.0, 1.0)
    xs = [s for s, _ in stops]
    channels = [np.interp(f, xs, [c[i] for _, c in stops]) for i in range(3)]
    alpha = np.where(np.isnan(v), 0, 255)
    return np.dstack([*channels, alpha]).astype(np.uint8)


def classes(
    values: NDArray,
    colours: Mapping[int, tuple[str, tuple[int, int, int]]],
    nodata: int | None = None,
) -> RGBA:
    """A class raster in its class colours; ``nodata`` and values without a colour transparent."""
    v = np.asarray(values)
    lut = np.zeros((256, 4), np.uint8)
    for value, (_, rgb) in colours.items():
        lut[value] = (*rgb, 255)
    if nodata is not None:
        lut[nodata] = 0
    return lut[v.astype(np.uint8)]


def over(base: RGBA, top: RGBA, opacity: float = 1.0) -> RGBA:
    """``top`` drawn over ``base`` (alpha compositing; the base's footprint is kept)."""
    a = top[..., 3:4].astype(np.float64) / 255.0 * opacity
    rgb = base[..., :3] * (1 - a) + top[..., :3] * a
    alpha = np.maximum(base[..., 3], (a[..., 0] * 255).astype(np.uint8))
    return np.dstack([rgb.astype(np.uint8), alpha])


def png(image: RGBA) -> bytes:
    """PNG bytes of an (rows, cols, 4) uint8 image (or (rows, cols) grey)."""
    img = np.asarray(image, dtype=np.uint8)
    if img.ndim == 2:
        img = np.dstack([img, img, img, np.full_like(img, 255)])
    rows, cols, channels = img.shape
    colour_type = {3: 2, 4: 6}[channels]
    raw = np.zeros((rows, 1 + cols * channels), np.uint8)  # filter byte 0 per row
    raw[:, 1:] = img.reshape(rows, cols * channels)

    def chunk(tag: bytes, data: bytes) -> bytes:
        body = tag + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    header = struct.pack(">IIBBBBB", cols, rows, 8, colour_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
        + chunk(b"IEND", b"")
    )


def legend(colours: Mapping[int, tuple[str, tuple[int, int, int]]]) -> list[dict[str, object]]:
    """Class values, labels and colours (``#rrggbb``), for pages and STAC ``classification:classes``."""
    return [
        {"value": v, "description": label, "color_hint": "".join(f"{c:02x}" for c in rgb)}
        for v, (label, rgb) in colours.items()
    ]
