"""Task: a job's quicklook PNGs from its finished rasters, features and block stats.

``thumbnail.png`` (hillshade, 256 px) and, at most 1024 px on the long side,
``hillshade.png``, ``chm.png``, ``coverage.png``, ``categories.png``,
``features.png`` (objects over the hillshade) and ``steep_blocks.png`` (blocks
classified with rotations, over the hillshade). Each picture is made only when
its source exists, so a job that selected few outputs gets what fits. The
STAC item lists them as ``thumbnail`` and ``overview`` assets.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from terrasift.files import atomic_path, load_json
from terrasift.jobs.dirs import block_results
from terrasift.tiling import quicklook as ql

THUMBNAIL = "thumbnail.png"
OVERVIEWS = (
    "hillshade.png",
    "chm.png",
    "coverage.png",
    "categories.png",
    "features.png",
    "steep_blocks.png",
)
NAMES = (THUMBNAIL, *OVERVIEWS)
MAX_SIDE = 1024
THUMB_SIDE = 256


def _read(path: Path, max_side: int) -> tuple[NDArray, object, float] | None:
    """Band 1 (decimated to ``max_side``, nodata as NaN or kept for integer bands) and its transform."""
    if not path.exists():
        return None
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(path) as ds:
        k = max(1, int(np.ceil(max(ds.width, ds.height) / max_side)))
        shape = (max(1, ds.height // k), max(1, ds.width // k))
        integer = np.issubdtype(np.dtype(ds.dtypes[0]), np.integer)
        data = ds.read(
            1,
            out_shape=shape,
            masked=not integer,
            resampling=Resampling.nearest,
        )
        transform = ds.transform @ ds.transform.scale(ds.width / shape[1], ds.height / shape[0])
    if not integer:
        data = data.astype(np.float64).filled(np.nan)
    return data, transform, abs(transform.a)


def _save(out: Path, name: str, image: ql.RGBA) -> str:
    with atomic_path(out / name) as tmp:
        tmp.write_bytes(ql.png(image))
    return name


def write_quicklooks(job_dir: str) -> list[str]:
    """Task: every quicklook whose source exists; returns the names written."""
    job = Path(job_dir)
    out = job / "outputs"
    names: list[str] = []
    dtm = _read(out / "dtm.tif", MAX_SIDE)
    shade = None
    if dtm is not None:
        data, transform, cell = dtm
        shade = ql.hillshade(data, cell)
        names.append(_save(out, "hillshade.png", ql.grey(shade)))
        small = _read(out / "dtm.tif", THUMB_SIDE)
        if small is not None:
            names.append(_save(out, THUMBNAIL, ql.grey(ql.hillshade(small[0], small[2]))))
        names += _features(job, out, shade, transform)
        names += _steep(job, out, shade, transform)
    chm = _read(out / "chm.tif", MAX_SIDE)
    if chm is not None:
        values = chm[0]
        top = float(np.nanpercentile(values, 99)) if np.isfinite(values).any() else 1.0
        names.append(_save(out, "chm.png", ql.ramp(values, max(top, 2.0))))
    cov = _read(out / "coverage.tif", MAX_SIDE)
    if cov is not None:
        names.append(_save(out, "coverage.png", ql.classes(cov[0], ql.COVERAGE_CLASSES, 255)))
    cats = out / "categories.tif"
    if cats.exists():
        names.append(_save(out, "categories.png", _categories(cats)))
    return names


def _categories(path: Path) -> ql.RGBA:
    import rasterio

    with rasterio.open(path) as ds:
        k = max(1, int(np.ceil(max(ds.width, ds.height) / MAX_SIDE)))
        incl, state = ds.read(1)[::k, ::k], ds.read(3)[::k, ::k]
    image = ql.classes(incl, ql.INCLINATION_CLASSES, 255)
    return ql.over(image, ql.classes(state, ql.STATE_CLASSES, 255))


def _features(job: Path, out: Path, shade: NDArray, transform: object) -> list[str]:
    path = out / "features.native.geojson"
    if not path.exists():
        return []
    from rasterio.features import rasterize

    features = load_json(path).get("features", [])
    image = ql.grey(shade)
    kinds = sorted({f.get("properties", {}).get("kind", "") for f in features})
    for kind in kinds:
        shapes = [
            f["geometry"]
            for f in features
            if f.get("geometry") and f.get("properties", {}).get("kind", "") == kind
        ]
        if not shapes:
            continue
        mask = rasterize(
            shapes, out_shape=shade.shape, transform=transform, all_touched=True, dtype="uint8"
        )
        rgb = ql.FEATURE_COLOURS.get(kind, ql.OTHER_FEATURE)
        layer = np.zeros((*shade.shape, 4), np.uint8)
        layer[mask > 0] = (*rgb, 255)
        image = ql.over(image, layer, 0.75)
    return [_save(out, "features.png", image)]


def _steep(job: Path, out: Path, shade: NDArray, transform: object) -> list[str]:
    """Steep blocks (rotated classification) tinted red over the hillshade."""
    from rasterio.transform import rowcol

    from terrasift.tiling.blocks import BlockGrid, parse_block_name

    try:
        grid = BlockGrid(**load_json(job / "plan.json")["grid"])
    except (OSError, ValueError, KeyError):
        return []
    layer = np.zeros((*shade.shape, 4), np.uint8)
    for stats_path in (p.with_suffix(".json") for p in block_results(job)):
        try:
            stats = load_json(stats_path)
        except (OSError, ValueError):
            continue
        if not stats.get("steep", {}).get("rotated"):
            continue
        x0, y0, x1, y1 = grid.core_bounds(*parse_block_name(stats["name"]))
        r0, c0 = rowcol(transform, x0, y1)
        r1, c1 = rowcol(transform, x1, y0)
        layer[max(r0, 0) : max(r1, 0), max(c0, 0) : max(c1, 0)] = (220, 30, 30, 255)
    return [_save(out, "steep_blocks.png", ql.over(ql.grey(shade), layer, 0.45))]
