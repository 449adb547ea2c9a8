"""The job's ``report.json``, ``steep_blocks.geojson`` and STAC ``item.json``."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pyproj

from terrasift.files import PARTIAL, write_json
from terrasift.jobs.params import effective_stage_params
from terrasift.tiling.blocks import BlockGrid, parse_block_name
from terrasift.tiling.stac import stac_item
from terrasift.workers import terrain, vegetation


def write_report_and_item(
    job_dir: Path,
    plan: Mapping[str, Any],
    params: Mapping[str, Any],
    block_stats: list[dict],
    timings: Mapping[str, float],
) -> list[str]:
    """Write ``report.json`` and ``item.json``; return every output name of the job."""
    job = Path(job_dir)
    out = job / "outputs"
    counts: dict[str, int] = {}
    stage_times: dict[str, float] = {}
    for s in block_stats:
        for c, v in s.get("counts", {}).items():
            counts[c] = counts.get(c, 0) + v
        for k, v in s.get("timings", {}).items():
            stage_times[k] = stage_times.get(k, 0.0) + v
    points = sum(int(t["point_count"]) for t in plan["tiles"])
    bins = {"empty": 0, "open": 0, "bush": 0, "tree": 0, "building": 0}
    for s in block_stats:
        for k in bins:
            bins[k] += s.get("vegetation", {}).get(k, 0)
    tree_cov, bush_cov = vegetation.coverage_from_counts(bins)
    rough = terrain.combine(
        terrain.Roughness(*s["roughness_sums"]) for s in block_stats if "roughness_sums" in s
    )
    steep = [s for s in block_stats if s.get("steep", {}).get("rotated")]
    mixed = [s["mixed"] for s in block_stats if "mixed" in s]
    report = {
        "job": job.name,
        "points": points,
        "tiles": [Path(t["path"]).name for t in plan["tiles"]],
        "crs": plan["crs"],
        "blocks": len(block_stats),
        "block_buffer": plan["grid"][
            "buffer"
        ],  # metres; resolved when the buffer parameter is auto
        "counts_per_class": dict(sorted(counts.items(), key=lambda kv: int(kv[0]))),
        "vegetation": {
            "tree_coverage": tree_cov,
            "bush_coverage": bush_cov,
            "bins": bins,
            "nogo_bins": sum(s.get("vegetation_nogo", 0) for s in block_stats),
        },
        "roughness": {
            **rough.to_dict(),
            "cell": max((s.get("roughness_cell", 0) for s in block_stats), default=None),
        },
        "roughness_per_block": {
            s["name"]: terrain.Roughness(*s["roughness_sums"]).to_dict()
            for s in block_stats
            if "roughness_sums" in s
        },
        "steep_blocks": {
            "tested": sum(1 for s in block_stats if s.get("steep")),
            "rotated": len(steep),
            "blocks": {s["name"]: s["steep"] for s in steep},
        },
        "mixed_measurements": (
            {
                "marked": sum(m["marked"] for m in mixed),
                "unclassified": sum(m["unclassified"] for m in mixed),
                "geometry": _scan_geometry(mixed),
            }
            if mixed
            else "not run: no sensor_origin given"
        ),
        "low_points": sum(s.get("low_points", 0) for s in block_stats),
        "parameters": dict(params),
        "stage_parameters": effective_stage_params(params),
        "timings_seconds": {
            "job": dict(timings),
            "stages_summed_over_blocks": stage_times,
        },
        "points_per_second": points / timings["total"] if timings.get("total") else None,
        "warnings": list(plan.get("warnings", [])),
    }
    write_json(out / "steep_blocks.geojson", steep_blocks_geojson(plan, steep))
    write_json(out / "report.json", report, indent=2)
    names = sorted(
        p.name
        for p in out.iterdir()
        if not p.name.endswith(PARTIAL) and not p.name.startswith(".") and p.name != "item.json"
    )
    write_json(out / "item.json", stac_item(job.name, out, plan, names), indent=2)
    return sorted([*names, "item.json"])


def steep_blocks_geojson(plan: Mapping[str, Any], steep_stats: list[dict]) -> dict[str, Any]:
    """Blocks that went through rotated classification, as RFC 7946 polygons (WGS 84 when the CRS is known)."""
    grid = BlockGrid(**plan["grid"])
    tf = None
    if plan.get("crs_wkt"):
        tf = pyproj.Transformer.from_crs(
            pyproj.CRS.from_wkt(plan["crs_wkt"]), "EPSG:4326", always_xy=True
        )
    feats = []
    for s in steep_stats:
        ix, iy = parse_block_name(s["name"])
        x0, y0, x1, y1 = grid.core_bounds(ix, iy)
        ring = [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]
        if tf is not None:
            ring = [tf.transform(x, y) for x, y in ring]
        feats.append(
            {
                "type": "Feature",
                "geometry": {"type": "Polygon", "coordinates": [[list(p) for p in ring]]},
                "properties": {
                    "block": s["name"],
                    "facet_share": s["steep"].get("facet_share"),
                    "points_added_per_rotation": s["steep"].get("added_per_rotation", []),
                    "points": s.get("points_core"),
                },
            }
        )
    return {"type": "FeatureCollection", "features": feats}


def _scan_geometry(mixed: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per scan position: the median over blocks of each measured or derived value."""
    per: dict[str, list[dict[str, Any]]] = {}
    for m in mixed:
        for g in m.get("geometry", []):
            per.setdefault(str(g["scan"]), []).append(g)
    out: dict[str, dict[str, Any]] = {}
    for scan, gs in sorted(per.items()):
        flat = [{**g, **g.get("measured", {})} for g in gs]
        vals: dict[str, list[float]] = {}
        for f in flat:
            for k, v in f.items():
                if isinstance(v, (int, float)) and not isinstance(v, bool) and k != "scan":
                    vals.setdefault(k, []).append(float(v))
        out[scan] = {"blocks": len(gs), **{k: float(np.median(v)) for k, v in vals.items()}}
        out[scan]["how"] = gs[0].get("measured", {}).get("how", "stated parameters")
        # how the returns were placed on the scan grid: blocks per way (GPS time or angles)
        placed = [g["grid_index"] for g in gs if "grid_index" in g]
        if placed:
            out[scan]["grid_index"] = {w: placed.count(w) for w in sorted(set(placed))}
    return out
