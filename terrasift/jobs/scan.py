"""The scan geometry of a ground-based job, measured once per scan position from all blocks.

The mixed-measurement filter takes its angles and distances from the scan's
geometry (angular steps, range noise, LAS scale, beam footprint). Measured in
each block, a block holding few points of a scan position (a block at the edge
of the scan, or one cut through a sparse far sector) measures a footprint from
few edges or nothing at all and falls back to assumed values, and neighbouring
blocks measure slightly different steps. Here every scan position is measured
once after sharding, on the same contiguous azimuth sector around its median
azimuth that the stage alone would take from the whole scan (``MAX_SAMPLE``
points), and its footprint on the same sectors spread over all azimuths the stage
takes (``ramp_sectors``), read from the core records of every shard; ``plan.json``
keeps the result and every block task passes it to the stage.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from terrasift.tiling.blocks import shard_dtype
from terrasift.workers.mixed import MixedParams
from terrasift.workers.scan_geometry import (
    MAX_SAMPLE,
    ScanGeometry,
    lenders,
    measure_scan_geometry,
    pool_footprints,
    ramp_sectors,
)

AZ_BINS = 1 << 16  # azimuth histogram bins over the circle (0.0055° each)


def _scan_records(files: Sequence[Path], n_scans: int):
    """Core records of every shard file, with each record's scan position."""
    for f in files:
        rec = np.fromfile(f, dtype=shard_dtype(f.parent))
        rec = rec[rec["core"] == 1]
        if rec.size == 0:
            continue
        ids = rec["scan_id"].astype(np.int64) if n_scans > 1 else np.zeros(rec.size, np.int64)
        yield rec, ids


def _az_bin(rec: NDArray, origin: NDArray[np.float64]) -> NDArray[np.int64]:
    az = np.arctan2(rec["y"] - origin[1], rec["x"] - origin[0])
    return np.minimum(((az + np.pi) / (2 * np.pi) * AZ_BINS).astype(np.int64), AZ_BINS - 1)


def measure_job_geometry(
    shard_dirs: Sequence[Path], origins: Sequence[Sequence[float]], params: MixedParams
) -> list[dict[str, Any] | None]:
    """Per scan position, its measured geometry (``ScanGeometry.to_dict``) or None when
    it has too few points. Two passes over the shards: azimuth histograms, then the
    points of the sector of ``MAX_SAMPLE`` points around each position's median azimuth."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    k = o.shape[0]
    files = [f for d in shard_dirs if d.is_dir() for f in sorted(d.glob("*.bin"))]
    hist = np.zeros((k, AZ_BINS), dtype=np.int64)
    for rec, ids in _scan_records(files, k):
        for s in np.unique(ids[ids < k]):
            sel = rec[ids == s]
            hist[s] += np.bincount(_az_bin(sel, o[s]), minlength=AZ_BINS)
    # rank ranges (by azimuth) of the points taken: the middle sector of MAX_SAMPLE (steps,
    # noise) and the sectors the footprint is measured on, as the stage alone takes them
    ranges: list[list[tuple[int, int]]] = []
    bins: list[list[tuple[int, int]]] = []
    for s in range(k):
        total = int(hist[s].sum())
        mid = (total // 2 - MAX_SAMPLE // 2, total // 2 - MAX_SAMPLE // 2 + 2 * (MAX_SAMPLE // 2))
        want = [(0, total) if total <= MAX_SAMPLE else mid, *ramp_sectors(total)]
        cum = np.cumsum(hist[s])
        ranges.append(want)
        bins.append(
            [
                (
                    int(np.searchsorted(cum, a, side="right")),
                    int(np.searchsorted(cum, max(b - 1, a), side="right")),
                )
                for a, b in want
            ]
        )
    # the field of view: azimuths counted from inside the widest empty arc of bins, so
    # its first and last return are those the stage alone finds on the whole scan
    outside = np.array([_empty_arc(hist[s]) for s in range(k)])
    to_first = np.full(k, np.inf)  # (azimuth - outside) mod 2π of the first / last return
    to_last = np.full(k, -np.inf)
    fov = np.zeros((k, 4))
    fov[:, 2], fov[:, 3] = np.inf, -np.inf
    pts: list[list[list[NDArray[np.float64]]]] = [[[] for _ in ranges[s]] for s in range(k)]
    # GPS time beside the points (NaN where the shards carry none): the steps from the
    # firing order where the angles show no grid
    tms: list[list[list[NDArray[np.float64]]]] = [[[] for _ in ranges[s]] for s in range(k)]
    for rec, ids in _scan_records(files, k):
        for s in np.unique(ids[ids < k]):
            sel = rec[ids == s]
            rel = np.column_stack([sel["x"], sel["y"], sel["z"]]) - o[s]
            az = np.arctan2(rel[:, 1], rel[:, 0])
            r = np.linalg.norm(rel, axis=1)
            el = np.arcsin(np.clip(rel[:, 2] / np.maximum(r, 1e-12), -1.0, 1.0))
            from_c = (az - outside[s]) % (2 * np.pi)
            i, j = int(np.argmin(from_c)), int(np.argmax(from_c))
            if from_c[i] < to_first[s]:
                to_first[s], fov[s, 0] = from_c[i], az[i]
            if from_c[j] > to_last[s]:
                to_last[s], fov[s, 1] = from_c[j], az[j]
            fov[s, 2] = np.minimum(fov[s, 2], el.min())
            fov[s, 3] = np.maximum(fov[s, 3], el.max())
            b = _az_bin(sel, o[s])
            for q, (lo, hi) in enumerate(bins[s]):
                part = sel[(b >= lo) & (b <= hi)]
                pts[s][q].append(np.column_stack([part["x"], part["y"], part["z"]]))
                timed = part.dtype.names is not None and "gps_time" in part.dtype.names
                tms[s][q].append(
                    np.asarray(part["gps_time"], np.float64)
                    if timed
                    else np.full(part.size, np.nan)
                )
    taken: list[tuple[list[NDArray[np.float64]], list[NDArray[np.float64]]]] = []
    for s in range(k):
        # each range's points: those in its bins sorted by azimuth, cut at its ranks
        # (the points before its first bin are counted in the histogram)
        cut, cut_t = [], []
        for q, (start, stop) in enumerate(ranges[s]):
            xyz = np.concatenate(pts[s][q]) if pts[s][q] else np.zeros((0, 3))
            tq = np.concatenate(tms[s][q]) if tms[s][q] else np.zeros(0)
            rel = xyz - o[s]
            order = np.argsort(np.arctan2(rel[:, 1], rel[:, 0]), kind="stable")
            first = start - int(hist[s][: bins[s][q][0]].sum())
            take = order[max(first, 0) : max(first, 0) + (stop - start)]
            cut.append(xyz[take])
            cut_t.append(tq[take])
        taken.append((cut, cut_t))
    geos: list[ScanGeometry | None] = [None] * k
    for lend in (False, True):
        # a position whose angles show no grid takes the steps of another (``lent_steps``)
        others = lenders(geos) if lend else []
        if lend and not others:
            break
        for s in range(k):
            if geos[s] is not None:
                continue
            cut, cut_t = taken[s]
            xyz = cut[0]
            geo = measure_scan_geometry(
                xyz - o[s],
                footprint=params.footprint,
                absolute=xyz,
                sectors=[c - o[s] for c in cut[1:]],
                gps_time=cut_t[0] if cut_t[0].size and np.isfinite(cut_t[0]).all() else None,
                lenders=others,
            )
            a0, a1, e0, e1 = (float(v) for v in fov[s])
            geos[s] = None if geo is None else replace(geo, field_of_view=(a0, a1, e0, e1))
    out: list[dict[str, Any] | None] = []
    for s, geo in enumerate(pool_footprints(geos)):
        if geo is None:
            out.append(None)
            continue
        d = geo.to_dict()
        d["how"] = {
            **geo.how,
            "scope": f"once per job and scan position, from {int(hist[s].sum())} points of all "
            "blocks (a contiguous azimuth sector around the median azimuth)",
        }
        out.append(d)
    return out


def _empty_arc(hist: NDArray[np.int64]) -> float:
    """Azimuth (radians) in the middle of the widest circular run of empty bins."""
    full = np.flatnonzero(hist > 0)
    if full.size == 0:
        return float(np.pi)
    gaps = np.diff(np.append(full, full[0] + AZ_BINS))  # bins from one full bin to the next
    i = int(np.argmax(gaps))
    mid = full[i] + 0.5 * gaps[i] + 0.5  # bin units, centre of the empty run
    return float(mid / AZ_BINS * 2 * np.pi - np.pi)


def job_geometry(
    found: Sequence[dict[str, Any] | None] | None,
) -> tuple[ScanGeometry | None, ...] | None:
    """``plan.json``'s per-position geometry back as ``ScanGeometry`` values."""
    if not found:
        return None
    return tuple(None if g is None else ScanGeometry.from_dict(g) for g in found)
