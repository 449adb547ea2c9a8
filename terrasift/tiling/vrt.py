"""GDAL VRT mosaics over per-tile rasters, written as XML (no GDAL binding needed).

Source paths are relative to the VRT, so a product directory can be moved or
served as is and read in place (``/vsicurl/`` resolves them against the VRT's URL).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import escape

from terrasift.files import atomic_path

_GDAL_TYPES = {"float32": "Float32", "float64": "Float64", "uint8": "Byte", "uint16": "UInt16"}


@dataclass(frozen=True)
class VrtSource:
    """A raster file at ``href`` (relative to the VRT) placed at a cell offset of the mosaic."""

    href: str
    col_off: int
    row_off: int
    cols: int
    rows: int


def write_vrt(
    path: Path,
    sources: list[VrtSource],
    *,
    width: int,
    height: int,
    geotransform: tuple[float, float, float, float, float, float],
    crs_wkt: str | None,
    dtype: str,
    nodata: float | int,
    count: int = 1,
    descriptions: tuple[str, ...] | None = None,
) -> Path:
    """Write a VRT of ``count`` bands over ``sources`` (same dtype and cell size), atomically."""
    gdal_type = _GDAL_TYPES[dtype]
    lines = [f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}">']
    if crs_wkt:
        lines.append(f"  <SRS>{escape(crs_wkt)}</SRS>")
    lines.append(
        "  <GeoTransform>" + ", ".join(repr(float(v)) for v in geotransform) + "</GeoTransform>"
    )
    for band in range(1, count + 1):
        lines.append(f'  <VRTRasterBand dataType="{gdal_type}" band="{band}">')
        if descriptions and band <= len(descriptions):
            lines.append(f"    <Description>{escape(descriptions[band - 1])}</Description>")
        lines.append(f"    <NoDataValue>{nodata}</NoDataValue>")
        for s in sources:
            lines += [
                "    <ComplexSource>",
                f'      <SourceFilename relativeToVRT="1">{escape(s.href)}</SourceFilename>',
                f"      <SourceBand>{band}</SourceBand>",
                f'      <SourceProperties RasterXSize="{s.cols}" RasterYSize="{s.rows}" '
                f'DataType="{gdal_type}" BlockXSize="256" BlockYSize="256"/>',
                f'      <SrcRect xOff="0" yOff="0" xSize="{s.cols}" ySize="{s.rows}"/>',
                f'      <DstRect xOff="{s.col_off}" yOff="{s.row_off}" xSize="{s.cols}" '
                f'ySize="{s.rows}"/>',
                f"      <NODATA>{nodata}</NODATA>",
                "    </ComplexSource>",
            ]
        lines.append("  </VRTRasterBand>")
    lines.append("</VRTDataset>")
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
    return Path(path)
