"""Files posted to ``/uploads``, kept until their href expires, for execute requests to name.

An upload is a directory ``uploads/<id>/`` with the files and a ``meta.json``
(tenant, expiry). Its hrefs are ``<base>/uploads/<id>/<name>``; a job that names
one gets a hard link (or a copy) of the file in its own input directory, so the
job does not depend on the upload living on. Expired uploads are removed
whenever a new upload arrives or an href is resolved.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote, urlsplit

from terrasift.files import write_json
from terrasift.service.problems import Problem

META = "meta.json"
PREFIX = "/uploads/"


@dataclass(frozen=True)
class StoredUpload:
    """One upload request: its id, files, owner and expiry (epoch seconds)."""

    id: str
    files: list[str]
    tenant: str
    expires: float


class UploadStore:
    """Uploads under ``root``, each valid for ``lifetime`` seconds."""

    def __init__(self, root: Path, lifetime: float):
        self.root = root
        self.lifetime = lifetime

    def directory(self, upload_id: str) -> Path:
        return self.root / upload_id

    def record(self, upload_id: str, files: list[Path], tenant: str) -> StoredUpload:
        """Write the metadata of files already received into ``directory(upload_id)``."""
        stored = StoredUpload(
            upload_id, [p.name for p in files], tenant, time.time() + self.lifetime
        )
        write_json(self.directory(upload_id) / META, stored.__dict__)
        return stored

    def get(self, upload_id: str, tenant: str) -> StoredUpload | None:
        """The upload, or None when unknown, expired or another tenant's."""
        if not upload_id.isalnum():
            return None
        try:
            meta = json.loads((self.directory(upload_id) / META).read_text())
        except (OSError, ValueError):
            return None
        stored = StoredUpload(**meta)
        if stored.tenant != tenant or stored.expires <= time.time():
            return None
        return stored

    def file(self, upload_id: str, name: str, tenant: str) -> Path:
        """The stored file, or a 404 problem saying the href is unknown or expired."""
        stored = self.get(upload_id, tenant)
        if stored is None or name not in stored.files:
            raise Problem(
                "not-found",
                f"no upload {upload_id}/{name}: unknown, or its href expired "
                f"(hrefs live {self.lifetime:.0f} s); POST the file to /uploads again",
            )
        return self.directory(upload_id) / name

    def resolve(self, href: str, tenant: str) -> Path | None:
        """The file an ``/uploads/<id>/<name>`` href names (absolute or relative), None if not such an href."""
        parts_of = urlsplit(href)
        path = unquote(parts_of.path)
        at = path.rfind(PREFIX)
        if parts_of.scheme in ("http", "https"):
            if at < 0:
                return None
        elif parts_of.scheme or not path.startswith(PREFIX):
            return None
        parts = path[at + len(PREFIX) :].split("/")
        if len(parts) != 2:
            return None
        self.purge_expired()
        return self.file(parts[0], parts[1], tenant)

    def purge_expired(self) -> int:
        """Remove expired uploads (and ones without metadata older than a lifetime); how many."""
        if not self.root.is_dir():
            return 0
        now = time.time()
        removed = 0
        for d in self.root.iterdir():
            try:
                expires = json.loads((d / META).read_text())["expires"]
            except (OSError, ValueError, KeyError):
                expires = d.stat().st_mtime + self.lifetime  # an upload still arriving, or broken
            if expires <= now:
                shutil.rmtree(d, ignore_errors=True)
                removed += 1
        return removed


def link_or_copy(src: Path, dest: Path) -> Path:
    """Put ``src`` at ``dest`` without copying bytes when the file system allows."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dest)
    except OSError:
        shutil.copyfile(src, dest)
    return dest
