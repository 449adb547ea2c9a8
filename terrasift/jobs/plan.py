"""Submission and planning: input headers and CRS checked, ``job.json`` and ``plan.json`` written.

Planning reads headers only: the tiles, their CRS, the mean point density
(which the density-derived defaults of the stages use, one value per job)
and the block grid laid over the union of the tiles. The ground stage's
density is measured later, while sharding, over the area the points occupy
(``run.py``): header areas count voids and no-data corners as covered.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import pyproj

from terrasift.errors import InputError
from terrasift.files import load_json, write_json
from terrasift.jobs.params import grid_alignment, resolve_buffer
from terrasift.tiling.blocks import BlockGrid, occupancy_cell
from terrasift.tiling.lasfile import TileInfo, crs_name, open_input, read_tile_info

#: reads the headers of tiles (paths, max_points) -> one TileInfo per path, in order
HeaderReader = Callable[[Sequence[str | Path], int | None], list[TileInfo]]

_reader_lock = threading.Lock()
_header_reader: HeaderReader | None = None


def use_header_reader(reader: HeaderReader | None) -> HeaderReader | None:
    """Read every tile header of this process with ``reader`` (None: here, in-process);
    returns the reader it replaces.

    The service reads them in disposable subprocesses with a time and memory
    budget, so that a decoder that aborts or runs away on a hostile header takes
    down a reader process, not the API.
    """
    global _header_reader
    with _reader_lock:
        old, _header_reader = _header_reader, reader
    return old


def header_reader() -> HeaderReader | None:
    """The reader ``use_header_reader`` installed (None: headers are read in-process)."""
    return _header_reader


def read_headers(paths: Sequence[str | Path], max_points: int | None = None) -> list[TileInfo]:
    """``read_tile_info`` of every path, through the installed header reader if any."""
    reader = _header_reader
    if reader is None:
        return [read_tile_info(p, max_points=max_points) for p in paths]
    return reader(list(paths), max_points)


def inspect_inputs(
    paths: list[Path], params: Mapping[str, Any], *, max_points: int | None = None
) -> dict[str, Any]:
    """Check every input's header (no points read) and the job's CRS.

    Raises InputError naming the problem. Returns a summary for the job record.
    """
    if not paths:
        raise InputError("no input files")
    infos = read_headers(paths, max_points)
    crs_wkt, warnings = resolve_crs(infos, params.get("crs"))
    mins = [min(i.mins[k] for i in infos) for k in range(3)]
    maxs = [max(i.maxs[k] for i in infos) for k in range(3)]
    return {
        "tiles": len(infos),
        "points": sum(i.point_count for i in infos),
        "bounds": [*mins, *maxs],
        "crs": crs_label(crs_wkt, infos),
        "warnings": warnings,
    }


def resolve_crs(infos: list[TileInfo], override: str | None) -> tuple[str | None, list[str]]:
    """The job's CRS as WKT: the ``crs`` parameter, else the tiles' common CRS."""
    warnings = [w for i in infos for w in i.warnings]
    if override:
        crs = pyproj.CRS.from_user_input(override)
        return crs.to_wkt(), [w for w in warnings if "no CRS" not in w]
    with_crs = [i for i in infos if i.crs_wkt]
    if not with_crs:
        warnings.append(
            "no CRS known: rasters and features.gpkg carry none, features are written in the tiles' own coordinates only (features.native.geojson, features.gpkg; no WGS 84 features.geojson); pass crs=EPSG:..."
        )
        return None, warnings
    # the readers wrote each CRS as pyproj's WKT: the same text is the same CRS, and only
    # tiles whose text differs need parsing (here, in this process) to compare them
    first_wkt = str(with_crs[0].crs_wkt)
    first = None
    for info in with_crs[1:]:
        if info.crs_wkt == first_wkt:
            continue
        first = first or pyproj.CRS.from_wkt(first_wkt)
        other = pyproj.CRS.from_wkt(str(info.crs_wkt))
        if not first.equals(other, ignore_axis_order=True):
            raise InputError(
                f"tiles of one job must share a CRS: {Path(info.path).name} is "
                f"{crs_label(info.crs_wkt, infos)}, the first tile is {crs_label(first_wkt, infos)}"
            )
    if len(with_crs) < len(infos):
        warnings.append("some tiles have no CRS; the others' CRS is used for all")
    return first_wkt, warnings


def crs_label(wkt: str | None, infos: Sequence[TileInfo] = ()) -> str | None:
    """``EPSG:<code>`` or the name of the CRS ``wkt``: the label a tile's reader found for
    that text when one did, else from parsing it here."""
    if not wkt:
        return None
    for info in infos:
        if info.crs_wkt == wkt and info.crs_label:
            return info.crs_label
    return crs_name(pyproj.CRS.from_wkt(wkt))


_crs_label = crs_label


def prepare_job(
    job_dir: Path,
    inputs: list[Path],
    params: Mapping[str, Any],
    outputs: list[str] | None = None,
) -> None:
    """Write the job's ``job.json`` (inputs as absolute paths, validated parameters,
    the selected outputs when not all)."""
    job_dir = Path(job_dir)
    job_dir.mkdir(parents=True, exist_ok=True)
    job: dict[str, Any] = {
        "inputs": [str(Path(p).resolve()) for p in inputs],
        "params": dict(params),
    }
    if outputs is not None:
        job["outputs"] = list(outputs)
    write_json(job_dir / "job.json", job, indent=2)


def set_input_roots(job_dir: Path, roots: Sequence[str | Path]) -> None:
    """Confine the job's inputs to ``roots``: every task that opens an input
    checks, on the opened file, that it still lies inside one of them."""
    path = Path(job_dir) / "job.json"
    job = load_json(path)
    job["input_roots"] = [str(Path(r).resolve()) for r in roots]
    write_json(path, job, indent=2)


def plan_job(job_dir: Path, job: Mapping[str, Any]) -> dict[str, Any]:
    """The job's ``plan.json`` (tiles, CRS, density, block grid), made from the tiles' headers once."""
    path = job_dir / "plan.json"
    if path.exists():
        return load_json(path)
    if job.get("survey"):  # a survey run: the survey's grid and density, not the run's
        from terrasift.jobs.survey import survey_plan

        plan = survey_plan(job_dir, job)
        write_json(path, plan, indent=2)
        return plan
    params = job["params"]
    roots = job.get("input_roots")
    for p in job["inputs"]:
        open_input(p, roots).close()  # still inside the input root (see set_input_roots)
    infos = read_headers(job["inputs"])
    crs_wkt, warnings = resolve_crs(infos, params.get("crs"))
    mins = (min(i.mins[0] for i in infos), min(i.mins[1] for i in infos))
    maxs = (max(i.maxs[0] for i in infos), max(i.maxs[1] for i in infos))
    area = sum(max(i.area, 1.0) for i in infos)
    density = sum(i.point_count for i in infos) / area
    buffer, warning = resolve_buffer(params, density)
    if warning:
        warnings.append(warning)
    grid = BlockGrid.over(
        mins, maxs, params["resolution"], params["block_size"], buffer, grid_alignment(params)
    )
    plan = {
        "tiles": [dict(i.__dict__) for i in infos],
        "density": density,
        "occupancy_cell": occupancy_cell(density),
        "crs_wkt": crs_wkt,
        "crs": crs_label(crs_wkt, infos),
        "grid": grid.to_dict(),
        "warnings": warnings,
    }
    if roots is not None:
        plan["input_roots"] = list(roots)
    write_json(path, plan, indent=2)
    return plan
