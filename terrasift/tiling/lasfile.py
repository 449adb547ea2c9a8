"""LAS/LAZ headers checked before any point is read, and points read in chunks.

Every check names the problem in words a survey engineer recognises, because
the message goes straight into a 4xx problem body or a failed job.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import laspy
import numpy as np
from numpy.typing import NDArray

from terrasift.errors import InputError

LAS_HEADER_MIN = 227
MAX_ABS_COORD = 1e9  # metres (or feet): beyond anything on Earth in any projected CRS
MAX_EXTENT = 200_000.0  # one tile wider than 200 km is a broken header, not a survey


@dataclass(frozen=True)
class TileInfo:
    """What the planner needs from one tile's header."""

    path: str
    point_count: int
    point_format: int
    version: str
    compressed: bool
    mins: tuple[float, float, float]
    maxs: tuple[float, float, float]
    scales: tuple[float, float, float]
    crs_wkt: str | None
    extra_dims: tuple[str, ...] = ()
    warnings: tuple[str, ...] = field(default=())

    @property
    def area(self) -> float:
        return max(self.maxs[0] - self.mins[0], 0.0) * max(self.maxs[1] - self.mins[1], 0.0)


def read_tile_info(path: str | Path, *, max_points: int | None = None) -> TileInfo:
    """Validate ``path``'s header (no points read) and describe the tile.

    Raises InputError naming the problem: not a LAS file, unsupported version
    or point format, no points, a point count the file cannot hold, absurd
    scales or bounds, a truncated LAZ chunk table.
    """
    path = Path(path)
    name = path.name
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(f"{name}: cannot read file ({exc.strerror})") from None
    with open(path, "rb") as fh:
        head = fh.read(LAS_HEADER_MIN)
    if len(head) < 4 or head[:4] != b"LASF":
        raise InputError(
            f"{name}: not a LAS/LAZ file (signature is {head[:4]!r}, expected b'LASF')"
        )
    if len(head) < LAS_HEADER_MIN:
        raise InputError(f"{name}: file is truncated inside the LAS header ({size} bytes)")
    major, minor = head[24], head[25]
    if major != 1 or minor > 4:
        raise InputError(f"{name}: unsupported LAS version {major}.{minor} (1.0 to 1.4 are read)")
    raw_format = head[104]
    point_format = raw_format & 0x3F
    compressed = bool(raw_format & 0xC0)
    if point_format > 10:
        raise InputError(f"{name}: unsupported point data format {point_format} (0 to 10 are read)")
    try:
        with laspy.open(str(path)) as reader:
            header = reader.header
    except Exception as exc:  # laspy raises several types for corrupt headers and VLRs
        raise InputError(f"{name}: unreadable LAS header or VLRs: {exc}") from None

    count = int(header.point_count)
    if count == 0:
        raise InputError(f"{name}: the header says the file holds no points")
    if max_points is not None and count > max_points:
        raise InputError(f"{name}: {count} points exceeds the configured limit of {max_points}")
    offset = int(header.offset_to_point_data)
    record = int(header.point_format.size)
    if not header.are_points_compressed:
        room = (size - offset) // record if size > offset else 0
        if room < count:
            raise InputError(
                f"{name}: header claims {count} points but the file holds only {max(room, 0)} "
                f"({size} bytes; the file is truncated or the header is wrong)"
            )
    else:
        _check_laz_chunk_table(path, name, offset, size)

    scales = tuple(float(s) for s in header.scales)
    for axis, s in zip("xyz", scales, strict=True):
        if not np.isfinite(s) or s <= 0 or s < 1e-9 or s > 10:
            raise InputError(f"{name}: absurd {axis} scale factor {s} in the header")
    mins = tuple(float(v) for v in header.mins)
    maxs = tuple(float(v) for v in header.maxs)
    for axis, lo, hi in zip("xyz", mins, maxs, strict=True):
        if (
            not (np.isfinite(lo) and np.isfinite(hi))
            or abs(lo) > MAX_ABS_COORD
            or abs(hi) > MAX_ABS_COORD
        ):
            raise InputError(f"{name}: absurd {axis} bounds in the header ({lo} to {hi})")
        if lo > hi:
            raise InputError(f"{name}: header {axis} minimum {lo} is above its maximum {hi}")
    if maxs[0] - mins[0] > MAX_EXTENT or maxs[1] - mins[1] > MAX_EXTENT:
        raise InputError(
            f"{name}: header bounds span {maxs[0] - mins[0]:.0f} × {maxs[1] - mins[1]:.0f}, "
            f"more than {MAX_EXTENT:.0f} for one tile"
        )

    warnings: list[str] = []
    crs_wkt = None
    try:
        crs = header.parse_crs()
        crs_wkt = crs.to_wkt() if crs is not None else None
    except Exception as exc:  # a malformed CRS record should not sink the tile
        warnings.append(f"{name}: CRS record could not be parsed ({exc})")
    if crs_wkt is None:
        warnings.append(f"{name}: no CRS in the file")
    extra = tuple(header.point_format.extra_dimension_names)
    return TileInfo(
        path=str(path),
        point_count=count,
        point_format=point_format,
        version=f"{major}.{minor}",
        compressed=compressed,
        mins=mins,  # type: ignore[arg-type]
        maxs=maxs,  # type: ignore[arg-type]
        scales=scales,  # type: ignore[arg-type]
        crs_wkt=crs_wkt,
        extra_dims=extra,
        warnings=tuple(warnings),
    )


def _check_laz_chunk_table(path: Path, name: str, offset: int, size: int) -> None:
    # A LAZ file starts its point data with the 8-byte offset of the chunk
    # table, which laszip writes at the end: an offset past the end of the
    # file means the file was cut short.
    with open(path, "rb") as fh:
        fh.seek(offset)
        raw = fh.read(8)
    if len(raw) < 8:
        raise InputError(f"{name}: LAZ file is truncated before its point data")
    (table_offset,) = struct.unpack("<q", raw)
    if table_offset != -1 and (table_offset < offset or table_offset + 8 > size):
        raise InputError(
            f"{name}: LAZ file is truncated (chunk table expected at byte {table_offset}, file has {size} bytes)"
        )


@dataclass(frozen=True)
class PointChunk:
    """Coordinates and the attributes the science needs, for a run of points."""

    start: int  # index of the first point in the tile
    xyz: NDArray[np.float64]
    return_number: NDArray[np.uint8]
    number_of_returns: NDArray[np.uint8]
    scan_id: NDArray[np.uint16]
    classification: NDArray[np.uint8] | None = None  # the input's classes (kept classes)


def iter_chunks(
    path: str | Path,
    chunk_size: int = 1_000_000,
    scan_dim: str | None = None,
    start: int = 0,
    stop: int | None = None,
) -> Iterator[PointChunk]:
    """Yield the tile's points ``start``..``stop`` (default: all) in file order,
    ``chunk_size`` at a time.

    Only the dimensions the science uses are decompressed. ``scan_dim`` names a
    dimension holding a scan-position id (default: point_source_id, 0 if absent).
    A LAZ reader seeks to ``start`` through the chunk table.
    """
    try:
        sel = laspy.DecompressionSelection
        wanted = (
            sel.XY_RETURNS_CHANNEL
            | sel.Z
            | sel.POINT_SOURCE_ID
            | sel.CLASSIFICATION
            | (sel.ALL_EXTRA_BYTES if scan_dim else 0)
        )
        reader = laspy.open(str(path), decompression_selection=wanted)
    except Exception as exc:
        raise InputError(f"{Path(path).name}: cannot open for reading: {exc}") from None
    with reader:
        total = int(reader.header.point_count)
        stop = total if stop is None else min(stop, total)
        names = set(reader.header.point_format.dimension_names)
        dim = scan_dim or "point_source_id"
        if scan_dim and scan_dim not in names:
            raise InputError(f"{Path(path).name}: no dimension {scan_dim!r} for scan ids")
        pos = start
        try:
            if start:
                reader.seek(start)
            while pos < stop:
                pts = reader.read_points(min(chunk_size, stop - pos))
                n = len(pts)
                if n == 0:
                    break
                xyz = np.empty((n, 3))
                xyz[:, 0] = pts.x
                xyz[:, 1] = pts.y
                xyz[:, 2] = pts.z
                scan = (
                    np.asarray(pts[dim], dtype=np.uint16)
                    if dim in names
                    else np.zeros(n, np.uint16)
                )
                yield PointChunk(
                    start=pos,
                    xyz=xyz,
                    return_number=np.asarray(pts.return_number, dtype=np.uint8),
                    number_of_returns=np.asarray(pts.number_of_returns, dtype=np.uint8),
                    scan_id=scan,
                    classification=np.asarray(pts.classification, dtype=np.uint8),
                )
                pos += n
        except InputError:
            raise
        except Exception as exc:  # lazrs / laspy errors on corrupt or cut data
            raise InputError(
                f"{Path(path).name}: point data unreadable after {pos} points: {exc}"
            ) from None
        if pos != stop:
            raise InputError(
                f"{Path(path).name}: header claims {total} points but only {pos} could be read"
            )
