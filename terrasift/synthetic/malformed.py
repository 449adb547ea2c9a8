"""A corpus of malformed LAS/LAZ files made from one good tile, for tests and benchmarks:
truncations, header fields set to extremes, NaN/inf, lying counts, LAZ chunk tables, corrupt
payloads, VLR bombs."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

# (name, byte offset, struct format) of the LAS 1.2 header fields that steer a reader
FIELDS = [
    ("version_major", 24, "B"),
    ("version_minor", 25, "B"),
    ("header_size", 94, "H"),
    ("offset_to_points", 96, "I"),
    ("number_of_vlrs", 100, "I"),
    ("point_format", 104, "B"),
    ("record_length", 105, "H"),
    ("point_count", 107, "I"),
    ("x_scale", 131, "d"),
    ("z_scale", 147, "d"),
    ("x_offset", 155, "d"),
    ("z_offset", 171, "d"),
    ("max_x", 179, "d"),
    ("min_x", 187, "d"),
    ("min_z", 219, "d"),
]
EXTREMES: dict[str, list[int | float]] = {
    "B": [0, 0xFF],
    "H": [0, 0xFFFF],
    "I": [0, 0xFFFFFFFF],
    "d": [0.0, -1.0, float("nan"), float("inf"), 1e300, 4e9],
}


def _put(data: bytes, offset: int, fmt: str, value: object) -> bytes:
    out = bytearray(data)
    struct.pack_into("<" + fmt, out, offset, value)
    return bytes(out)


def corpus(las: bytes, laz: bytes, seed: int = 0) -> Iterator[tuple[str, str, bytes]]:
    """(case name, file suffix, bytes) for every malformed variant of the two good files."""
    rng = np.random.default_rng(seed)
    for suffix, good in (("las", las), ("laz", laz)):
        offset = struct.unpack_from("<I", good, 96)[0]
        for cut in (0, 3, 100, 226, 300, offset, offset + 4, len(good) // 2, len(good) - 1):
            yield f"{suffix}-truncated-at-{cut}", suffix, good[:cut]
        for name, at, fmt in FIELDS:
            for value in EXTREMES[fmt]:
                yield f"{suffix}-{name}={value}", suffix, _put(good, at, fmt, value)
        count = struct.unpack_from("<I", good, 107)[0]
        for lie in (count // 2, count - 1, count + 1, count * 3):
            yield f"{suffix}-point-count-{lie}-of-{count}", suffix, _put(good, 107, "I", lie)
        # a VLR that claims more bytes than lie before the points
        yield f"{suffix}-vlr-length-65535", suffix, _put(good, 227 + 20, "H", 0xFFFF)
        yield f"{suffix}-vlrs-0xffffffff", suffix, _put(good, 100, "I", 0xFFFFFFFF)
        # a 1.4 header whose extended VLRs lie
        v14 = _put(good, 25, "B", 4)
        yield f"{suffix}-evlr-count-huge", suffix, v14
    # LAZ: the chunk table's place and count
    offset = struct.unpack_from("<I", laz, 96)[0]
    table = struct.unpack_from("<q", laz, offset)[0]
    for name, value in (("past-end", len(laz) + 100), ("zero", 0), ("into-header", 10)):
        yield f"laz-chunk-table-offset-{name}", "laz", _put(laz, offset, "q", value)
    for chunks in (0, 2, 0x7FFFFFFF, 0xFFFFFFFF):
        yield f"laz-chunk-count-{chunks}", "laz", _put(laz, table + 4, "I", chunks)
    # the laszip record's item list: none (lazrs panics on it), or items of no size
    items = laszip_items_at(laz)
    yield "laz-laszip-items-0", "laz", _put(laz, items - 2, "H", 0)
    yield "laz-laszip-item-sizes-0", "laz", _put(_put(laz, items + 2, "H", 0), items + 8, "H", 0)
    # corrupt compressed payloads: zeroed and random bytes inside the point data
    for i, (start, length) in enumerate([(offset + 8, 64), (offset + 200, 16), (table - 400, 300)]):
        body = bytearray(laz)
        body[start : start + length] = bytes(length)
        yield f"laz-payload-zeroed-{i}", "laz", bytes(body)
        body[start : start + length] = rng.integers(0, 256, length, dtype=np.uint8).tobytes()
        yield f"laz-payload-random-{i}", "laz", bytes(body)
    # LAS: coordinates far outside the header bounds
    body = bytearray(las)
    start, record = struct.unpack_from("<I", las, 96)[0], struct.unpack_from("<H", las, 105)[0]
    struct.pack_into("<i", body, start + 5 * record, 2**31 - 1)
    yield "las-point-outside-bounds", "las", bytes(body)


def laszip_items_at(laz: bytes) -> int:
    """Byte offset of the laszip VLR's item list (after its 34-byte preamble) in ``laz``."""
    header_size, _, n_vlrs = struct.unpack_from("<HII", laz, 94)
    pos = header_size
    for _ in range(n_vlrs):
        user = laz[pos + 2 : pos + 18].rstrip(b"\0")
        record_id, length = struct.unpack_from("<HH", laz, pos + 18)
        if user == b"laszip encoded" and record_id == 22204:
            return pos + 54 + 34
        pos += 54 + length
    raise ValueError("no laszip VLR")


def write_pair(directory: Path, size: float = 40.0, density: float = 2.0) -> tuple[bytes, bytes]:
    """A small good tile as LAS 1.2 (format 1) and LAZ, with a CRS."""
    from terrasift.synthetic.terrain import make_scene, write_las

    scene = make_scene(size=size, density=density, seed=11)
    las = write_las(scene, directory / "good.las", crs="EPSG:32632", point_format=1, version="1.2")
    laz = write_las(scene, directory / "good.laz", crs="EPSG:32632", point_format=1, version="1.2")
    return las.read_bytes(), laz.read_bytes()


def run_through_app(
    client: Any, cases: list[tuple[str, str, bytes]], params: dict, timeout: float = 180.0
) -> dict[str, tuple[str, str]]:
    """Upload every case to ``POST /jobs`` of a running app (a TestClient or httpx client)
    and wait for the accepted ones; case -> (outcome, message).

    Outcomes: ``refused-4xx``, ``http-5xx`` (must never happen), ``failed``, ``successful``,
    ``stuck`` (not final after ``timeout`` s: must never happen).
    """
    import json
    import time

    out: dict[str, tuple[str, str]] = {}
    jobs: dict[str, str] = {}
    form = {"params": json.dumps(params)}
    for name, suffix, data in cases:
        r = client.post("/jobs", files=[("file", (f"t.{suffix}", data))], data=form)
        if r.status_code == 201:
            jobs[name] = r.json()["jobID"]
        elif r.status_code >= 500:
            out[name] = ("http-5xx", r.text[:200])
        else:
            out[name] = ("refused-4xx", r.json().get("detail", ""))
    end = time.monotonic() + timeout
    for name, job_id in jobs.items():
        while True:
            info = client.get(f"/jobs/{job_id}").json()
            if info["status"] not in ("accepted", "running"):
                out[name] = (info["status"], info.get("message", ""))
                break
            if time.monotonic() > end:
                out[name] = ("stuck", f"{info['status']} at {info['progress']} %")
                break
            time.sleep(0.1)
    return out
