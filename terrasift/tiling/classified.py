"""A classified copy of a LAS/LAZ file: every point in order, every dimension kept, new classes."""

from __future__ import annotations

import copy
from collections.abc import Sequence
from pathlib import Path

import laspy
import numpy as np
import pyproj
from numpy.typing import NDArray

from terrasift.files import atomic_path
from terrasift.tiling.lasfile import open_input


def write_classified_copy(
    src: str | Path,
    dst: str | Path,
    classes: NDArray[np.uint8],
    *,
    crs: str | None = None,
    chunk_size: int = 1_000_000,
    roots: Sequence[str] | None = None,
) -> Path:
    """Copy ``src`` to ``dst`` (LAZ) with ``classes[i]`` as point i's classification.

    The source is streamed in chunks, so memory follows the chunk and the
    labels, not the file. ``crs`` (any pyproj string) is written into the
    header when given. LAS 1.0 input is written as 1.2, which shares its
    header and point records of formats 0 and 1. With ``roots`` the source
    must lie inside one of them when it is opened (``open_input``).
    """
    dst = Path(dst)
    with atomic_path(dst) as tmp, laspy.open(open_input(src, roots), closefd=True) as reader:
        header = copy.deepcopy(reader.header)
        if str(header.version) == "1.0":
            # laspy writes from 1.1 on
            header.version = laspy.header.Version(1, 2)
        if crs:
            header.add_crs(pyproj.CRS.from_user_input(crs))
        # the header's text fields (system identifier, software, VLR descriptions) are
        # copied as the file holds them, ASCII or not (strict checking failed the job)
        with laspy.open(
            str(tmp), mode="w", header=header, do_compress=True, encoding_errors="replace"
        ) as writer:
            start = 0
            for pts in reader.chunk_iterator(chunk_size):
                pts.classification = classes[start : start + len(pts)]
                writer.write_points(pts)
                start += len(pts)
    return dst
