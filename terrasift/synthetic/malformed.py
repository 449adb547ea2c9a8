"""A corpus of malformed LAS/LAZ files made from one good tile, for tests and benchmarks:
truncations, header fields set to extremes, NaN/inf, lying counts, LAZ chunk tables, corrupt
payloads, VLR bombs."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

# (name, byte offset, struct format) of every field of the LAS 1.2 public header block
HEADER_12 = [
    ("signature", 0, "4s"),
    ("file_source_id", 4, "H"),
    ("global_encoding", 6, "H"),
    ("guid_1", 8, "I"),
    ("guid_2", 12, "H"),
    ("guid_3", 14, "H"),
    ("guid_4", 16, "8s"),
    ("version_major", 24, "B"),
    ("version_minor", 25, "B"),
    ("system_identifier", 26, "32s"),
    ("generating_software", 58, "32s"),
    ("creation_day", 90, "H"),
    ("creation_year", 92, "H"),
    ("header_size", 94, "H"),
    ("offset_to_points", 96, "I"),
    ("number_of_vlrs", 100, "I"),
    ("point_format", 104, "B"),
    ("record_length", 105, "H"),
    ("point_count", 107, "I"),
    *[(f"points_by_return_{i + 1}", 111 + 4 * i, "I") for i in range(5)],
    ("x_scale", 131, "d"),
    ("y_scale", 139, "d"),
    ("z_scale", 147, "d"),
    ("x_offset", 155, "d"),
    ("y_offset", 163, "d"),
    ("z_offset", 171, "d"),
    ("max_x", 179, "d"),
    ("min_x", 187, "d"),
    ("max_y", 195, "d"),
    ("min_y", 203, "d"),
    ("max_z", 211, "d"),
    ("min_z", 219, "d"),
]
# the fields LAS 1.3 and 1.4 add after it
HEADER_14 = [
    ("start_of_waveform", 227, "Q"),
    ("start_of_first_evlr", 235, "Q"),
    ("number_of_evlrs", 243, "I"),
    ("point_count_64", 247, "Q"),
    *[(f"points_by_return_64_{i + 1}", 255 + 8 * i, "Q") for i in range(15)],
]
# the fields the short corpus (the test suite's) sets to every extreme
FIELDS = [
    f
    for f in HEADER_12
    if f[0]
    in (
        "version_major",
        "version_minor",
        "header_size",
        "offset_to_points",
        "number_of_vlrs",
        "point_format",
        "record_length",
        "point_count",
        "x_scale",
        "z_scale",
        "x_offset",
        "z_offset",
        "max_x",
        "min_x",
        "min_z",
    )
]
EXTREMES: dict[str, list[int | float]] = {
    "B": [0, 0xFF],
    "H": [0, 0xFFFF],
    "I": [0, 0xFFFFFFFF],
    "Q": [0, 0xFFFFFFFFFFFFFFFF],
    "d": [0.0, -1.0, float("nan"), float("inf"), 1e300, 4e9],
}


def _field_variants(good: bytes, at: int, fmt: str) -> Iterator[tuple[str, bytes]]:
    """(label, file) for one header field: every bit flipped, then its extremes (bytes
    fields: all zero and all 0xFF)."""
    size = struct.calcsize("<" + fmt)
    flipped = bytes(b ^ 0xFF for b in good[at : at + size])
    yield "flipped", good[:at] + flipped + good[at + size :]
    if fmt.endswith("s"):
        for label, byte in (("zeros", 0), ("0xff", 0xFF)):
            yield label, good[:at] + bytes([byte]) * size + good[at + size :]
        return
    for value in EXTREMES[fmt]:
        yield str(value), _put(good, at, fmt, value)


def _put(data: bytes, offset: int, fmt: str, value: object) -> bytes:
    out = bytearray(data)
    struct.pack_into("<" + fmt, out, offset, value)
    return bytes(out)


def corpus(
    las: bytes, laz: bytes, seed: int = 0, v14: tuple[bytes, bytes] | None = None
) -> Iterator[tuple[str, str, bytes]]:
    """(case name, file suffix, bytes) for every malformed variant of the two good files
    (LAS 1.2). With ``v14`` (a LAS 1.4 pair, from ``write_pair(..., version="1.4")``) also
    every field of both headers flipped and set to its extremes (``full_corpus``)."""
    if v14 is not None:
        for version, pair in (("1.2", (las, laz)), ("1.4", v14)):
            fields = HEADER_12 if version == "1.2" else HEADER_12 + HEADER_14
            for suffix, good in zip(("las", "laz"), pair, strict=True):
                for name, at, fmt in fields:
                    for label, data in _field_variants(good, at, fmt):
                        yield f"{suffix}{version}-{name}-{label}", suffix, data
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
        as_14 = _put(good, 25, "B", 4)
        yield f"{suffix}-evlr-count-huge", suffix, as_14
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


def write_pair(
    directory: Path, size: float = 40.0, density: float = 2.0, version: str = "1.2"
) -> tuple[bytes, bytes]:
    """A small good tile as LAS and LAZ with a CRS: LAS 1.2 point format 1, or 1.4 format 6."""
    from terrasift.synthetic.terrain import make_scene, write_las

    scene = make_scene(size=size, density=density, seed=11)
    fmt = 1 if version == "1.2" else 6
    files = [
        write_las(
            scene,
            directory / f"good-{version}.{suffix}",
            crs="EPSG:32632",
            point_format=fmt,
            version=version,
        )
        for suffix in ("las", "laz")
    ]
    return files[0].read_bytes(), files[1].read_bytes()


def full_corpus(directory: Path, seed: int = 0) -> list[tuple[str, str, bytes]]:
    """The corpus of ``corpus`` with every header field of LAS 1.2 and 1.4 files (LAS and
    LAZ) flipped and set to its extremes."""
    return list(corpus(*write_pair(directory), seed=seed, v14=write_pair(directory, version="1.4")))


def run_through_app(
    client: Any,
    cases: list[tuple[str, str, bytes]] | list[tuple[str, str, bytes, str]],
    params: dict,
    timeout: float = 180.0,
) -> dict[str, tuple[str, str]]:
    """Upload every case to ``POST /jobs`` of a running app (a TestClient or httpx client)
    and wait for the accepted ones; case -> (outcome, message). A case may carry its own
    ``params`` text as a fourth item (sent as is: it may be hostile JSON).

    Outcomes: ``refused-4xx``, ``http-5xx`` (must never happen), ``failed``, ``successful``,
    ``dismissed``, ``stuck`` (must never happen: a job running for more than ``timeout`` s,
    or no job ending for ``timeout`` s while some wait).
    """
    import json
    import time

    out: dict[str, tuple[str, str]] = {}
    jobs: dict[str, str] = {}
    default = json.dumps(params)
    for name, suffix, data, *own in cases:
        form = {"params": own[0] if own else default}
        r = client.post("/jobs", files=[("file", (f"t.{suffix}", data))], data=form)
        if r.status_code == 201:
            jobs[name] = r.json()["jobID"]
        elif r.status_code >= 500:
            out[name] = ("http-5xx", f"{r.status_code} {r.text[:200]}")
        else:
            out[name] = ("refused-4xx", r.json().get("detail", ""))
    started: dict[str, float] = {}
    last_end = time.monotonic()
    while jobs:
        for name, job_id in list(jobs.items()):
            info = client.get(f"/jobs/{job_id}").json()
            now = time.monotonic()
            if info["status"] not in ("accepted", "running"):
                out[name] = (info["status"], info.get("message", ""))
                del jobs[name]
                last_end = now
                continue
            if info["status"] == "running":
                started.setdefault(name, now)
            if now - started.get(name, now) > timeout or now - last_end > timeout:
                out[name] = ("stuck", f"{info['status']} at {info['progress']} %")
                del jobs[name]
        time.sleep(0.1)
    return out


# JSON texts of values no parameter should take, tried on every fixed job parameter
BAD_VALUES = [
    "null",
    "true",
    "[]",
    "{}",
    '""',
    '"x"',
    "-1",
    "0",
    "1e308",
    "-1e308",
    "5e-324",
    "NaN",
    "Infinity",
    "-Infinity",
    "1" + "0" * 400,
    '"\\u0000"',
    "[[[[[1]]]]]",
    '"' + "a" * 100_000 + '"',
]


def hostile_params(job_params: Any) -> list[tuple[str, str]]:
    """(case name, ``params`` JSON text) of hostile parameter sets for the job parameter
    model ``job_params`` (``jobs.params.JobParams``; this room may not import it): every
    fixed parameter given every value of ``BAD_VALUES``, lists of names far beyond their bound, filters and
    CRSs built to be costly, odd keys, and every stage field just outside its bounds, NaN,
    and each stage's fields all at their smallest and all at their largest allowed values.

    Each must be refused with a 4xx or give a job that ends (failed naming why, or
    successful) within the task limits."""
    import json
    import math
    from typing import get_args

    from annotated_types import Ge, Gt, Le, Lt

    from terrasift.workers.registry import stages

    cases: list[tuple[str, str]] = []
    for name, field in job_params.model_fields.items():
        key = field.alias or name
        for i, value in enumerate(BAD_VALUES):
            cases.append((f"{key}=bad-{i}", f'{{"{key}": {value}}}'))
    names = [f"filter{i}" for i in range(80_000)]
    many = {
        "features-80000-names": {"features": ",".join(names)},
        "features-80000-same-name": {"features": ",".join(["ditch"] * 80_000)},
        "features-unknown": {"features": "no-such-filter"},
        "features-all-and-none": {"features": "all,none"},
        "filters-65": {"filters": {f"f{i}": "slope > 10" for i in range(65)}},
        "filters-long-text": {"filters": {"f": "slope > 10 and " * 20_000 + "slope > 10"}},
        "filters-deep-parentheses": {"filters": {"f": "(" * 5_000 + "slope > 10" + ")" * 5_000}},
        "filters-bad-text": {"filters": {"f": "}{)(*&^%"}},
        "filters-empty-name": {"filters": {"": "slope > 10"}},
        "sensor-origin-10000": {"sensor_origin": ";".join(["1,2,3"] * 10_000)},
        "sensor-origin-nan": {"sensor_origin": "nan,nan,nan"},
        "sensor-origin-huge": {"sensor_origin": "1e308,1e308,1e308"},
        "sensor-origin-two-numbers": {"sensor_origin": "1,2"},
        "crs-epsg-0": {"crs": "EPSG:0"},
        "crs-geographic": {"crs": "EPSG:4326"},
        "crs-zero-ellipsoid": {"crs": "+proj=longlat +a=0 +b=0"},
        "crs-long-text": {"crs": "EPSG:" + "9" * 10_000},
        "crs-wkt-garbage": {"crs": 'PROJCS["x",' * 2_000},
        "smallest-blocks-finest-cells": {"block_size": 20, "buffer": 0, "resolution": 0.05},
        "largest-blocks-halo": {"block_size": 5000, "buffer": 500, "resolution": 100},
        "buffer-half-block": {"block_size": 20, "buffer": 10},
        "unknown-key": {"no_such_parameter": 1},
        "10000-unknown-keys": {f"k{i}": i for i in range(10_000)},
        "stage-key-empty-field": {"ground.nist.": 1},
        "stage-key-dunder": {"ground.nist.__class__": 1},
        "stage-key-traversal": {"../../etc.passwd": 1},
        "stage-unknown": {"nosuchstage.field": 1},
        "workers-256": {"workers": 256},
        "scan-dimension-unknown": {"scan_dimension": "no_such_dimension"},
        "ground-preset-unknown": {"ground.preset": "reckless"},
    }
    cases += [(name, json.dumps(value)) for name, value in many.items()]
    for stage in stages():
        low: dict[str, object] = {}
        high: dict[str, object] = {}
        for field_name, field in stage.params.model_fields.items():
            key = f"{stage.id}.{field_name}"
            integer = field.annotation is int or int in get_args(field.annotation)
            lo: Any = None  # smallest and largest allowed value, and the nearest refused
            hi: Any = None
            out_lo: Any = None
            out_hi: Any = None
            for m in field.metadata:
                bound: Any = getattr(m, type(m).__name__.lower(), None)
                if isinstance(m, Ge):
                    lo, out_lo = bound, bound - (1 if integer else 1e-9)
                elif isinstance(m, Gt):
                    lo = bound + 1 if integer else math.nextafter(float(bound), math.inf)
                    out_lo = bound
                elif isinstance(m, Le):
                    hi, out_hi = bound, bound + (1 if integer else 1e-9 * max(1, abs(bound)))
                elif isinstance(m, Lt):
                    hi = bound - 1 if integer else math.nextafter(float(bound), -math.inf)
                    out_hi = bound
            cases.append((f"{key}=nan", f'{{"{key}": NaN}}'))
            cases.append((f"{key}=string", json.dumps({key: "x" * 1000})))
            if lo is not None:
                low[field_name] = lo
                cases.append((f"{key}=below-{lo}", json.dumps({key: out_lo})))
            if hi is not None:
                high[field_name] = hi
                cases.append((f"{key}=above-{hi}", json.dumps({key: out_hi})))
        for label, values in (("smallest", low), ("largest", high)):
            if values:
                body = {f"{stage.id}.{k}": v for k, v in values.items()}
                if stage.role == "ground":
                    body["ground"] = stage.id.split(".", 1)[1]
                cases.append((f"{stage.id}-all-{label}", json.dumps(body)))
    return cases
