"""Multipart uploads streamed straight to the job's input directory.

Starlette's form parser would spool every file to a temporary file first and
has no limit on file parts; here each ``file`` part goes to its final place in
chunks as it arrives, and the byte count is checked on every chunk, so an
oversized upload stops with 413 as soon as it crosses the limit.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, MultipartState, parse_options_header
from starlette.requests import ClientDisconnect, Request

from terrasift.service.problems import Problem

if TYPE_CHECKING:
    from python_multipart.multipart import MultipartCallbacks

MAX_FIELD_BYTES = 1024 * 1024
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")
MAX_NAME = 128  # characters of an uploaded file's name (ASCII after _UNSAFE)


@dataclass
class Upload:
    """What a multipart request carried: saved files (in order) and text fields."""

    files: list[Path] = field(default_factory=list)
    fields: dict[str, str] = field(default_factory=dict)
    bytes: int = 0


def safe_name(filename: str, index: int, taken: set[str]) -> str:
    """A file name for an upload: the client's base name made safe and unique."""
    base = (
        _UNSAFE.sub("_", Path(filename.replace("\\", "/")).name).strip("._")
        or f"upload-{index}.las"
    )
    if len(base) > MAX_NAME:  # a file system takes 255 bytes a name: keep the suffix
        stem, dot, suffix = base.rpartition(".")
        suffix = suffix[:16]
        base = f"{stem[: MAX_NAME - len(suffix) - 1]}.{suffix}" if dot and stem else base[:MAX_NAME]
    name, n = base, 1
    while name in taken:
        stem, dot, suffix = base.rpartition(".")
        name = f"{stem}-{n}.{suffix}" if dot and stem else f"{base}-{n}"
        n += 1
    taken.add(name)
    return name


class _Receiver:
    """Callbacks for python-multipart: routes part data to files or text fields."""

    def __init__(self, dest: Path, file_fields: set[str], text_fields: set[str], max_files: int):
        self.dest, self.file_fields, self.text_fields, self.max_files = (
            dest,
            file_fields,
            text_fields,
            max_files,
        )
        self.upload = Upload()
        self._taken: set[str] = set()
        self._header_field = b""
        self._header_value = b""
        self._headers: dict[bytes, bytes] = {}
        self._fh: IO[bytes] | None = None
        self._text: bytearray | None = None
        self._name = ""

    def callbacks(self) -> MultipartCallbacks:
        return {
            "on_part_begin": self.part_begin,
            "on_header_field": self.header_field,
            "on_header_value": self.header_value,
            "on_header_end": self.header_end,
            "on_headers_finished": self.headers_finished,
            "on_part_data": self.part_data,
            "on_part_end": self.part_end,
        }

    def part_begin(self) -> None:
        self._headers = {}

    def header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_field += data[start:end]

    def header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def header_end(self) -> None:
        self._headers[self._header_field.lower()] = self._header_value
        self._header_field, self._header_value = b"", b""

    def headers_finished(self) -> None:
        disposition, options = parse_options_header(self._headers.get(b"content-disposition", b""))
        if disposition != b"form-data" or b"name" not in options:
            raise Problem(
                "invalid-request",
                "a multipart part lacks `Content-Disposition: form-data; name=...`",
            )
        self._name = options[b"name"].decode("utf-8", "replace")
        if self._name in self.file_fields:
            if len(self.upload.files) >= self.max_files:
                raise Problem("invalid-request", f"more than {self.max_files} files in one request")
            filename = options.get(b"filename", b"").decode("utf-8", "replace")
            name = safe_name(filename, len(self.upload.files), self._taken)
            path = self.dest / name
            self._fh = path.open("wb")
            self.upload.files.append(path)
        elif self._name in self.text_fields:
            if self._name in self.upload.fields:
                raise Problem("invalid-request", f"field {self._name!r} given twice")
            self._text = bytearray()
        else:
            known = ", ".join(sorted(self.file_fields | self.text_fields))
            raise Problem("invalid-request", f"unknown form field {self._name!r} (known: {known})")

    def part_data(self, data: bytes, start: int, end: int) -> None:
        if self._fh is not None:
            self._fh.write(data[start:end])
        elif self._text is not None:
            self._text += data[start:end]
            if len(self._text) > MAX_FIELD_BYTES:
                raise Problem(
                    "payload-too-large",
                    f"field {self._name!r} is longer than {MAX_FIELD_BYTES} bytes",
                )

    def part_end(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None
        elif self._text is not None:
            try:
                self.upload.fields[self._name] = self._text.decode("utf-8")
            except UnicodeDecodeError:
                raise Problem(
                    "invalid-request", f"field {self._name!r} is not UTF-8 text"
                ) from None
            self._text = None

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


async def receive_multipart(
    request: Request,
    dest: Path,
    *,
    max_bytes: int,
    max_files: int,
    file_fields: frozenset[str] = frozenset({"file"}),
    text_fields: frozenset[str] = frozenset({"params"}),
) -> Upload:
    """Stream a ``multipart/form-data`` body: file parts into ``dest``, text fields in memory.

    Raises Problem: 415 when the body is not multipart, 413 past ``max_bytes``,
    400 on malformed multipart or unknown fields. The caller removes ``dest`` on error.
    """
    ctype, options = parse_options_header(request.headers.get("content-type", ""))
    if ctype != b"multipart/form-data" or b"boundary" not in options:
        raise Problem(
            "unsupported-media-type",
            "send the files as multipart/form-data (curl -F file=@tile.laz)",
        )
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > max_bytes:
        raise Problem(
            "payload-too-large", f"the request declares {declared} bytes; the limit is {max_bytes}"
        )
    dest.mkdir(parents=True, exist_ok=True)
    receiver = _Receiver(dest, set(file_fields), set(text_fields), max_files)
    parser = MultipartParser(options[b"boundary"], receiver.callbacks())
    try:
        async for chunk in request.stream():
            receiver.upload.bytes += len(chunk)
            if receiver.upload.bytes > max_bytes:
                raise Problem(
                    "payload-too-large", f"the upload exceeds the limit of {max_bytes} bytes"
                )
            parser.write(chunk)
        parser.finalize()
        if parser.state != MultipartState.END:
            raise Problem(
                "invalid-request",
                "the multipart body ends before its closing boundary (upload cut short?)",
            )
    except MultipartParseError as exc:
        raise Problem("invalid-request", f"malformed multipart body: {exc}") from None
    except ClientDisconnect:
        raise Problem("invalid-request", "the client disconnected during the upload") from None
    finally:
        receiver.close()
    return receiver.upload
