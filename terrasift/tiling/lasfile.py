"""LAS/LAZ headers checked before any point is read, and points read in chunks.

Every check names the problem in words a survey engineer recognises, because
the message goes straight into a 4xx problem body or a failed job.
"""

from __future__ import annotations

import errno
import os
import stat
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import laspy
import numpy as np
from numpy.typing import NDArray

from terrasift.errors import InputError

LAS_HEADER_MIN = 227
LAS14_HEADER = 375
MAX_ABS_COORD = 1e9  # metres (or feet): beyond anything on Earth in any projected CRS
MAX_EXTENT = 200_000.0  # one tile wider than 200 km is a broken header, not a survey
# Exceptions a decoder must let through: everything else it raises (lazrs panics
# surface as pyo3's PanicException, a BaseException) is a verdict on the input.
PASS_THROUGH = (KeyboardInterrupt, SystemExit, GeneratorExit)


def _decoder_failure(exc: BaseException) -> str:
    """What a failed decoder said, with its type when that is not a plain error."""
    text = str(exc).strip() or "no message"
    kind = type(exc).__name__
    if not isinstance(exc, Exception):  # a panic in lazrs, not an error it reports
        return f"the LAZ decoder crashed ({kind}: {text})"
    return text


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
    crs_label: str | None = None
    """``EPSG:<code>`` or the CRS's name, found where the header was read (a reader
    process in the service), so the API process need not parse the CRS again."""

    @property
    def area(self) -> float:
        return max(self.maxs[0] - self.mins[0], 0.0) * max(self.maxs[1] - self.mins[1], 0.0)


def open_input(path: str | Path, roots: Sequence[str] | None = None) -> BinaryIO:
    """Open a tile for reading; with ``roots``, only a regular file inside one of them.

    The check is made on the opened file itself, not on its name: the last
    component may not be a symbolic link (``O_NOFOLLOW``), and the path the
    kernel reports for the open descriptor must lie under a root. A file or
    folder swapped for a link to somewhere else between submission and this
    open is refused, whenever the swap happened. ``roots`` are resolved paths.
    """
    path = Path(path)
    name = path.name
    if roots is None:
        return open(path, "rb")
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(path, flags | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputError(
                f"{name}: is now a symbolic link; inputs are read only from inside the input root"
            ) from None
        raise InputError(f"{name}: cannot open for reading ({exc.strerror})") from None
    fh = os.fdopen(fd, "rb")
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise InputError(f"{name}: is no longer a regular file")
        real = _real_path(fd, path)
        if real is None or not any(real.is_relative_to(r) for r in roots):
            raise InputError(f"{name}: now lies outside the input root")
    except BaseException:
        fh.close()
        raise
    return fh


def _real_path(fd: int, path: Path) -> Path | None:
    """Where the open descriptor ``fd`` really is (None when that cannot be told)."""
    try:
        return Path(os.readlink(f"/proc/self/fd/{fd}"))
    except OSError:  # no /proc: the resolved name must still be this very file
        real = Path(os.path.realpath(path))
        try:
            return real if os.path.samestat(os.fstat(fd), os.stat(real)) else None
        except OSError:
            return None


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
        head = fh.read(LAS14_HEADER)
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
    # Every count and offset is checked against the file's size before laspy
    # reads anything, so a header cannot make it allocate or loop beyond that.
    laszip = _check_structure(path, name, size, head, minor, point_format)
    try:
        with laspy.open(str(path)) as reader:
            header = reader.header
    except PASS_THROUGH:
        raise
    except BaseException as exc:  # laspy raises several types for corrupt headers and VLRs
        raise InputError(
            f"{name}: unreadable LAS header or VLRs: {_decoder_failure(exc)}"
        ) from None

    count = int(header.point_count)
    if count == 0:
        raise InputError(f"{name}: the header says the file holds no points")
    if max_points is not None and count > max_points:
        raise InputError(f"{name}: {count} points exceeds the configured limit of {max_points}")
    offset = int(header.offset_to_point_data)
    record = int(header.point_format.size)
    if not header.are_points_compressed:
        end = _point_data_end(head, minor, size, offset)
        room = (end - offset) // record if end > offset else 0
        if room < count:
            raise InputError(
                f"{name}: header claims {count} points but the file holds only {max(room, 0)} "
                f"({size} bytes; the file is truncated or the header is wrong)"
            )
        if room > count:
            raise InputError(
                f"{name}: header claims {count} points but the file holds {room} "
                "(the header's point count is wrong)"
            )
    else:
        if laszip is None:
            raise InputError(f"{name}: compressed points but no laszip VLR to decode them")
        _check_laz_chunk_table(path, name, offset, size, count, laszip)
    # Writers get the per-return counts slightly wrong (one point off in lidR's
    # Topography.laz): a small gap is a warning, a large one a wrong count.
    by_return = _points_by_return(head, minor)
    count_warning = None
    if by_return and by_return != count:
        text = (
            f"{name}: header claims {count} points but its counts per return add up to {by_return}"
        )
        if abs(by_return - count) > max(1, 0.01 * count):
            raise InputError(text + " (the header is wrong)")
        count_warning = text + f"; {count} points are read"

    scales = tuple(float(s) for s in header.scales)
    for axis, s in zip("xyz", scales, strict=True):
        if not np.isfinite(s) or s <= 0 or s < 1e-9 or s > 10:
            raise InputError(f"{name}: absurd {axis} scale factor {s} in the header")
    for axis, o in zip("xyz", (float(v) for v in header.offsets), strict=True):
        if not np.isfinite(o) or abs(o) > MAX_ABS_COORD:
            raise InputError(f"{name}: absurd {axis} offset {o} in the header")
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

    warnings: list[str] = [count_warning] if count_warning else []
    crs_wkt = crs_label = None
    try:
        crs = header.parse_crs()
        if crs is not None:
            crs_wkt, crs_label = crs.to_wkt(), crs_name(crs)
    except PASS_THROUGH:
        raise
    except BaseException as exc:  # a malformed CRS record should not sink the tile
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
        crs_label=crs_label,
    )


def crs_name(crs: Any) -> str:
    """``EPSG:<code>`` of a pyproj CRS, else its name."""
    code = crs.to_epsg()
    return f"EPSG:{code}" if code else str(crs.name)


# Smallest point record of each format (LAS 1.4 R15 table 7 onwards)
POINT_RECORD_MIN = (20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67)
VLR_HEADER = 54
EVLR_HEADER = 60
MAX_VLR_BYTES = 64 * 1024**2  # CRS, laszip and extra-bytes records are kilobytes
LASZIP_USER = b"laszip encoded"
LASZIP_RECORD = 22204
LASZIP_PREAMBLE = 34  # bytes before the laszip record's item list
VARIABLE_CHUNKS = 0xFFFFFFFF


def _check_structure(
    path: Path, name: str, size: int, head: bytes, minor: int, point_format: int
) -> int | None:
    """Header size, point offset, record length, VLRs and EVLRs against the file's size.

    Returns the laszip chunk size (None without a laszip record). Reads at most
    the header and the VLR headers (bounded by MAX_VLR_BYTES).
    """
    header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
    (record,) = struct.unpack_from("<H", head, 105)
    minimum = {0: 227, 1: 227, 2: 227, 3: 235}.get(minor, 375)
    if header_size < minimum or header_size > size:
        raise InputError(
            f"{name}: header size {header_size} is impossible for LAS 1.{minor} in a "
            f"{size}-byte file (at least {minimum})"
        )
    if offset < header_size or offset > size:
        raise InputError(
            f"{name}: point data offset {offset} lies outside the file ({header_size} to {size})"
        )
    if record < POINT_RECORD_MIN[point_format]:
        raise InputError(
            f"{name}: point record length {record} is shorter than format {point_format} "
            f"needs ({POINT_RECORD_MIN[point_format]})"
        )
    if offset - header_size > MAX_VLR_BYTES:
        raise InputError(f"{name}: {offset - header_size} bytes of VLRs; at most {MAX_VLR_BYTES}")
    if n_vlrs * VLR_HEADER > offset - header_size:
        raise InputError(
            f"{name}: header claims {n_vlrs} VLRs, but only {offset - header_size} bytes "
            "lie between header and points"
        )
    chunk_size = None
    with open(path, "rb") as fh:
        fh.seek(header_size)
        vlrs = fh.read(offset - header_size)
        pos = 0
        for i in range(n_vlrs):
            if pos + VLR_HEADER > len(vlrs):
                raise InputError(f"{name}: VLR {i + 1} of {n_vlrs} runs past the point data")
            user = vlrs[pos + 2 : pos + 18].rstrip(b"\0")
            record_id, length = struct.unpack_from("<HH", vlrs, pos + 18)
            body = pos + VLR_HEADER
            if body + length > len(vlrs):
                raise InputError(
                    f"{name}: VLR {i + 1} of {n_vlrs} claims {length} bytes, past the point data"
                )
            if user == LASZIP_USER and record_id == LASZIP_RECORD:
                chunk_size = _check_laszip_vlr(name, vlrs[body : body + length], record)
            pos = body + length
        if minor >= 4:
            start, n_evlrs = struct.unpack_from("<QI", head, 235)
            _check_evlrs(fh, name, size, offset, start, n_evlrs)
    return chunk_size


def _check_laszip_vlr(name: str, body: bytes, record: int) -> int:
    """The laszip record's item list against the header's point record length; its chunk size.

    The record lists the compressed items of a point (type, size, version, six
    bytes each, after a 34-byte preamble); their sizes add up to the point record.
    lazrs divides by that sum, so an empty list makes it panic rather than fail.
    """
    if len(body) < LASZIP_PREAMBLE:
        raise InputError(f"{name}: the laszip VLR is cut short ({len(body)} bytes)")
    (chunk_size,) = struct.unpack_from("<I", body, 12)
    (n_items,) = struct.unpack_from("<H", body, 32)
    if n_items == 0 or LASZIP_PREAMBLE + 6 * n_items > len(body):
        raise InputError(
            f"{name}: the laszip VLR lists {n_items} compressed items in {len(body)} bytes "
            "(the file is corrupt)"
        )
    sizes = [struct.unpack_from("<H", body, LASZIP_PREAMBLE + 6 * i + 2)[0] for i in range(n_items)]
    if sum(sizes) != record:
        raise InputError(
            f"{name}: the laszip VLR describes points of {sum(sizes)} bytes, the header "
            f"{record} bytes (the file is corrupt)"
        )
    return int(chunk_size)


def _check_evlrs(fh: BinaryIO, name: str, size: int, offset: int, start: int, count: int) -> None:
    if count == 0:
        return
    if start < offset or start + count * EVLR_HEADER > size:
        raise InputError(
            f"{name}: header claims {count} extended VLRs from byte {start}; "
            f"the file has {size} bytes"
        )
    pos = start
    for i in range(count):
        fh.seek(pos)
        raw = fh.read(EVLR_HEADER)
        if len(raw) < EVLR_HEADER:
            raise InputError(f"{name}: extended VLR {i + 1} of {count} runs past the file's end")
        (length,) = struct.unpack_from("<Q", raw, 20)
        pos += EVLR_HEADER + length
        if pos > size:
            raise InputError(
                f"{name}: extended VLR {i + 1} of {count} claims {length} bytes, past the file's end"
            )


def _points_by_return(head: bytes, minor: int) -> int:
    """Sum of the header's points-by-return counts (0 when the writer left them empty)."""
    legacy = sum(struct.unpack_from("<5I", head, 111))
    if minor >= 4:
        extended = sum(struct.unpack_from("<15Q", head, 255))
        return extended or legacy
    return legacy


def _point_data_end(head: bytes, minor: int, size: int, offset: int) -> int:
    """Where uncompressed point records end: the first EVLR (or waveform data) after them."""
    ends = [size]
    if minor >= 4:
        start, n_evlrs = struct.unpack_from("<QI", head, 235)
        if n_evlrs and start >= offset:
            ends.append(start)
    if minor >= 3:
        (waveform,) = struct.unpack_from("<Q", head, 227)
        if waveform >= offset and head[6] & 0x02:  # global encoding: waveform data internal
            ends.append(waveform)
    return min(ends)


def _check_laz_chunk_table(
    path: Path, name: str, offset: int, size: int, count: int, chunk_size: int | None
) -> None:
    """The chunk table's place and chunk count against the file and the point count.

    A LAZ file starts its point data with the 8-byte offset of the chunk
    table, which laszip writes at the end; the table starts with its version
    and number of chunks. A decoder allocates per chunk, so a count the file
    cannot hold is refused here (every chunk holds at least one byte).
    """
    with open(path, "rb") as fh:
        fh.seek(offset)
        raw = fh.read(8)
        if len(raw) < 8:
            raise InputError(f"{name}: LAZ file is truncated before its point data")
        (table_offset,) = struct.unpack("<q", raw)
        if table_offset == -1:
            return  # no table (a stream): chunks are found by reading them
        if table_offset < offset + 8 or table_offset + 8 > size:
            raise InputError(
                f"{name}: LAZ file is truncated (chunk table expected at byte {table_offset}, "
                f"file has {size} bytes)"
            )
        fh.seek(table_offset)
        _version, chunks = struct.unpack("<II", fh.read(8))
    if chunks > table_offset - offset - 8:
        raise InputError(
            f"{name}: LAZ chunk table claims {chunks} chunks in {table_offset - offset - 8} "
            "bytes of point data"
        )
    if chunk_size and chunk_size != VARIABLE_CHUNKS:
        expected = -(-count // chunk_size)
        if chunks != expected:
            raise InputError(
                f"{name}: header claims {count} points, which fill {expected} chunks of "
                f"{chunk_size}, but the LAZ chunk table lists {chunks} (the point count "
                "or the file is wrong)"
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
    gps_time: NDArray[np.float64] | None = None  # when asked for and the format has it


def iter_chunks(
    path: str | Path,
    chunk_size: int = 1_000_000,
    scan_dim: str | None = None,
    start: int = 0,
    stop: int | None = None,
    roots: Sequence[str] | None = None,
    gps_time: bool = False,
) -> Iterator[PointChunk]:
    """Yield the tile's points ``start``..``stop`` (default: all) in file order,
    ``chunk_size`` at a time; with ``roots`` the file is opened by ``open_input``.
    With ``gps_time`` each chunk carries the points' GPS time (None when the point
    format has none).

    Only the dimensions the science uses are decompressed. ``scan_dim`` names a
    dimension holding a scan-position id (default: point_source_id, 0 if absent).
    A LAZ reader seeks to ``start`` through the chunk table.
    """
    sel = laspy.DecompressionSelection
    wanted = (
        sel.XY_RETURNS_CHANNEL
        | sel.Z
        | sel.POINT_SOURCE_ID
        | sel.CLASSIFICATION
        | (sel.ALL_EXTRA_BYTES if scan_dim else 0)
        | (sel.GPS_TIME if gps_time else 0)
    )
    try:
        source = open_input(path, roots)
    except OSError as exc:
        raise InputError(f"{Path(path).name}: cannot open for reading ({exc.strerror})") from None
    try:
        reader = laspy.open(source, closefd=True, decompression_selection=wanted)
    except PASS_THROUGH:
        source.close()
        raise
    except BaseException as exc:
        source.close()
        raise InputError(
            f"{Path(path).name}: cannot open for reading: {_decoder_failure(exc)}"
        ) from None
    with reader:
        total = int(reader.header.point_count)
        stop = total if stop is None else min(stop, total)
        names = set(reader.header.point_format.dimension_names)
        dim = scan_dim or "point_source_id"
        if scan_dim and scan_dim not in names:
            raise InputError(f"{Path(path).name}: no dimension {scan_dim!r} for scan ids")
        pos = start
        # a point beyond the header's bounds (by more than rounding) means a
        # corrupt payload or a wrong header: its coordinates are not to be trusted
        tol = 2 * np.asarray(reader.header.scales, float) + 0.01
        lo = np.asarray(reader.header.mins, float) - tol
        hi = np.asarray(reader.header.maxs, float) + tol
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
                outside = int(np.count_nonzero(~((xyz >= lo) & (xyz <= hi)).all(axis=1)))
                if outside:
                    raise InputError(
                        f"{Path(path).name}: {outside} of points {pos} to {pos + n} lie outside "
                        "the header's bounds (or are not finite); the point data is corrupt "
                        "or the header is wrong"
                    )
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
                    gps_time=(
                        np.asarray(pts.gps_time, dtype=np.float64)
                        if gps_time and "gps_time" in names
                        else None
                    ),
                )
                pos += n
        except (InputError, *PASS_THROUGH):
            raise
        except BaseException as exc:  # lazrs / laspy errors (and lazrs panics) on corrupt data
            raise InputError(
                f"{Path(path).name}: point data unreadable after {pos} points: "
                f"{_decoder_failure(exc)}"
            ) from None
        if pos != stop:
            raise InputError(
                f"{Path(path).name}: header claims {total} points but only {pos} could be read"
            )
