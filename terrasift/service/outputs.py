"""Serving job outputs the way GDAL and QGIS read them over HTTP: Range, ETag, HEAD.

A COG is read in place by ``/vsicurl/``: HEAD for the size, then single byte
ranges. Outputs never change once a job has finished, so a strong ETag from
size and modification time is enough and costs no hashing.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import anyio
from starlette.requests import Request
from starlette.responses import Response
from starlette.types import Receive, Scope, Send

from terrasift.service.problems import Problem
from terrasift.tiling import stac

#: the outputs' media types, as their STAC assets name them, and the pages served beside them
MEDIA_TYPES = {
    **stac.MEDIA_TYPES,
    ".html": "text/html; charset=utf-8",
    ".vrt": "application/xml",
}
# a STAC Item is a GeoJSON Feature
MEDIA_TYPE_BY_NAME = {"item.json": "application/geo+json"}

CHUNK = 256 * 1024


def media_type(name: str) -> str:
    """The media type of an output file, by name, then by suffix."""
    if name in MEDIA_TYPE_BY_NAME:
        return MEDIA_TYPE_BY_NAME[name]
    return MEDIA_TYPES.get(Path(name).suffix.lower(), "application/octet-stream")


def etag_for(stat: os.stat_result) -> str:
    """Strong ETag from size and modification time (outputs are immutable once written)."""
    return f'"{stat.st_size:x}-{stat.st_mtime_ns:x}"'


@dataclass(frozen=True)
class ByteRange:
    """An inclusive byte range ``first..last`` of a file of ``size`` bytes."""

    first: int
    last: int
    size: int

    @property
    def length(self) -> int:
        return self.last - self.first + 1

    @property
    def content_range(self) -> str:
        return f"bytes {self.first}-{self.last}/{self.size}"


class RangeNotSatisfiable(Exception):
    """The Range header is valid syntax but selects nothing of the file."""


def parse_range(header: str | None, size: int) -> ByteRange | None:
    """The single range a ``Range`` header asks for, or None for the whole file.

    Follows RFC 9110 §14: ``bytes=a-b``, ``bytes=a-``, ``bytes=-n``; a last
    position past the end is clipped. Headers we do not understand (other units,
    several ranges, bad syntax) are ignored, which the RFC allows: the client
    gets the whole file with 200. A well-formed range that starts past the end,
    or a zero suffix, raises RangeNotSatisfiable (416).
    """
    if not header:
        return None
    unit, _, spec = header.strip().partition("=")
    if unit.strip().lower() != "bytes" or "," in spec:
        return None
    first_s, dash, last_s = spec.strip().partition("-")
    first_s, last_s = first_s.strip(), last_s.strip()
    if (
        not dash
        or not (first_s.isdigit() or first_s == "")
        or not (last_s.isdigit() or last_s == "")
    ):
        return None
    if first_s == "":
        if last_s == "":
            return None
        suffix = int(last_s)
        if suffix == 0 or size == 0:
            raise RangeNotSatisfiable(header)
        return ByteRange(max(0, size - suffix), size - 1, size)
    first = int(first_s)
    if last_s and int(last_s) < first:
        return None  # syntactically invalid per RFC 9110: ignore the header
    if first >= size:
        raise RangeNotSatisfiable(header)
    last = min(int(last_s), size - 1) if last_s else size - 1
    return ByteRange(first, last, size)


def _etag_matches(header: str, etag: str) -> bool:
    tags = [t.strip() for t in header.split(",")]
    # If-None-Match uses weak comparison
    return "*" in tags or any(t.removeprefix("W/") == etag for t in tags)


class FileSliceResponse(Response):
    """Sends ``path`` (or one byte range of it) in chunks read off the event loop."""

    def __init__(
        self,
        path: Path,
        headers: dict[str, str],
        status_code: int,
        rng: ByteRange | None,
        head: bool,
    ):
        super().__init__(status_code=status_code, headers=headers)
        self.path, self.rng, self.head = path, rng, head

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        await send(
            {"type": "http.response.start", "status": self.status_code, "headers": self.raw_headers}
        )
        if self.head:
            await send({"type": "http.response.body", "body": b"", "more_body": False})
            return
        first = self.rng.first if self.rng else 0
        remaining = self.rng.length if self.rng else int(self.headers["content-length"])
        async with await anyio.open_file(self.path, "rb") as fh:
            await fh.seek(first)
            while remaining > 0:
                chunk = await fh.read(min(CHUNK, remaining))
                if not chunk:  # file shrank under us: end the body short rather than hang
                    break
                remaining -= len(chunk)
                await send({"type": "http.response.body", "body": chunk, "more_body": True})
        await send({"type": "http.response.body", "body": b"", "more_body": False})


def file_response(request: Request, path: Path, name: str) -> Response:
    """200/206/304/416 for GET or HEAD of an output file, with ETag and Content-Length."""
    try:
        stat = path.stat()
    except FileNotFoundError:
        raise Problem("no-such-output", f"output {name!r} does not exist") from None
    etag = etag_for(stat)
    headers = {
        "ETag": etag,
        "Accept-Ranges": "bytes",
        "Cache-Control": "private, max-age=0, must-revalidate",
    }
    inm = request.headers.get("if-none-match")
    if inm is not None and _etag_matches(inm, etag):
        return Response(status_code=304, headers=headers)
    rng = None
    if_range = request.headers.get("if-range")
    if if_range is None or if_range.strip() == etag:
        try:
            rng = parse_range(request.headers.get("range"), stat.st_size)
        except RangeNotSatisfiable:
            raise Problem(
                "range-not-satisfiable",
                f"range {request.headers.get('range')!r} lies outside the {stat.st_size} bytes of {name!r}",
                headers={"Content-Range": f"bytes */{stat.st_size}", **headers},
            ) from None
    headers["Content-Type"] = media_type(name)
    head = request.method == "HEAD"
    if rng is None:
        headers["Content-Length"] = str(stat.st_size)
        return FileSliceResponse(path, headers, 200, None, head)
    headers["Content-Length"] = str(rng.length)
    headers["Content-Range"] = rng.content_range
    return FileSliceResponse(path, headers, 206, rng, head)
