"""OGC API – Processes documents: landing page, conformance, process description, statusInfo.

Only documents are built here; routes decide what to answer. statusInfo follows
the Part 1 schema exactly: optional members are left out rather than null.
"""

from __future__ import annotations

from typing import Any

from terrasift.service.outputs import media_type
from terrasift.service.store import SUCCESSFUL, Job

PROCESS_ID = "terrain"
PROCESS_VERSION = "1.0.0"
REL_PROCESSES = "http://www.opengis.net/def/rel/ogc/1.0/processes"
REL_JOB_LIST = "http://www.opengis.net/def/rel/ogc/1.0/job-list"
REL_EXECUTE = "http://www.opengis.net/def/rel/ogc/1.0/execute"
REL_RESULTS = "http://www.opengis.net/def/rel/ogc/1.0/results"
REL_CONFORMANCE = "http://www.opengis.net/def/rel/ogc/1.0/conformance"

CONFORMANCE = [
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/core",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/ogc-process-description",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/json",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/html",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/job-list",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/callback",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/dismiss",
]
# Not claimed: conf/oas30 (the API definition served at /openapi.json is OpenAPI 3.1).

OUTPUTS: dict[str, str] = {
    "classified.laz": "every input point, original order and dimensions, ASPRS classes "
    "1/2/3/4/5/6/7 and the kept input classes (objects.keep, 9 water by default)",
    "dtm.tif": "bare-earth elevation, float32 COG",
    "dsm.tif": "surface elevation, float32 COG",
    "chm.tif": "vegetation height above ground (pit-free; buildings 0), float32 COG",
    "slope.tif": "slope in degrees, COG",
    "coverage.tif": "bins: 0 empty, 1 open, 2 bush, 3 tree, 4 building",
    "categories.tif": "inclination, orientation, state, height×10 on the category tile grid",
    "features.geojson": "terrain objects, WGS 84",
    "features.native.geojson": "terrain objects in the tile CRS (crs member)",
    "features.gpkg": "terrain objects in the tile CRS, GeoPackage",
    "steep_blocks.geojson": "blocks classified with rotations",
    "report.json": "counts per class, coverage, roughness, parameters, stage timings, warnings",
    "item.json": "STAC Item whose assets are the outputs",
    "thumbnail.png": "quicklook: DTM hillshade, 256 px",
    "hillshade.png": "quicklook: DTM hillshade",
    "chm.png": "quicklook: canopy height",
    "coverage.png": "quicklook: vegetation bins (legend in the job page)",
    "categories.png": "quicklook: terrain categories (inclination, edges)",
    "features.png": "quicklook: terrain objects over the hillshade",
    "steep_blocks.png": "quicklook: blocks classified with rotations, over the hillshade",
}


def parameter_inputs() -> dict[str, dict[str, Any]]:
    """Every job parameter as a process input: the §8 keys, then ``<stage>.<field>`` per registered stage."""
    from terrasift.jobs.params import JobParams
    from terrasift.workers.registry import stages

    out: dict[str, dict[str, Any]] = {}

    def add(key: str, prop: dict[str, Any], defs: dict[str, Any], prefix: str = "") -> None:
        prop = dict(prop)
        prop.pop("title", None)
        description = prefix + prop.pop("description", "")
        if defs:
            prop["$defs"] = defs
        out[key] = {"description": description.strip(), "schema": prop}

    schema = JobParams.model_json_schema(by_alias=True)
    for key, prop in schema["properties"].items():
        add(key, prop, schema.get("$defs", {}))
    for stage in stages():
        schema = stage.params.model_json_schema(by_alias=True)
        for field, prop in schema.get("properties", {}).items():
            add(
                f"{stage.id}.{field}",
                prop,
                schema.get("$defs", {}),
                f"{stage.id} ({stage.description}): ",
            )
    return out


def link(
    href: str, rel: str, type_: str = "application/json", title: str | None = None
) -> dict[str, str]:
    out = {"href": href, "rel": rel, "type": type_}
    if title:
        out["title"] = title
    return out


def landing(base: str) -> dict[str, Any]:
    return {
        "title": "terrasift",
        "description": "LAS/LAZ tiles in; ground classification, DTM/DSM, vegetation and terrain objects out.",
        "links": [
            link(f"{base}/", "self", title="this document"),
            link(
                f"{base}/openapi.json",
                "service-desc",
                "application/vnd.oai.openapi+json;version=3.1",
                "the API definition",
            ),
            link(f"{base}/docs", "service-doc", "text/html", "the API documentation"),
            link(f"{base}/conformance", REL_CONFORMANCE, title="conformance classes"),
            link(f"{base}/processes", REL_PROCESSES, title="processes"),
            link(f"{base}/jobs", REL_JOB_LIST, title="jobs"),
        ],
    }


def process_summary(base: str) -> dict[str, Any]:
    return {
        "id": PROCESS_ID,
        "title": "Terrain from LAS/LAZ tiles",
        "description": "Classify ground (and vegetation, noise), grid DTM/DSM and derived rasters, find terrain objects.",
        "version": PROCESS_VERSION,
        "jobControlOptions": ["sync-execute", "async-execute", "dismiss"],
        "outputTransmission": ["reference"],
        "links": [
            link(f"{base}/processes/{PROCESS_ID}", "self", title="process description"),
            link(f"{base}/processes/{PROCESS_ID}/execution", REL_EXECUTE, title="execute"),
        ],
    }


def process_description(base: str, parameters: dict[str, dict[str, Any]]) -> dict[str, Any]:
    inputs: dict[str, Any] = {
        "files": {
            "title": "tiles",
            "description": 'LAS/LAZ files: `{"href": ...}` as answered by POST /uploads, '
            '`{"value": <base64>, "encoding": "base64"}`, or paths under the service\'s '
            "input root (a directory stands for the .las/.laz files in it).",
            "schema": {
                "oneOf": [
                    {"type": "string", "contentMediaType": "application/vnd.laszip"},
                    {"type": "string", "format": "uri"},
                ]
            },
            "minOccurs": 1,
            "maxOccurs": "unbounded",
        },
        "params": {
            "title": "parameters",
            "description": "the parameters below as one object; they may also be given as inputs of their own",
            "schema": {"type": "object"},
            "minOccurs": 0,
            "maxOccurs": 1,
        },
    }
    for key, spec in parameters.items():
        inputs[key] = {"title": key, "minOccurs": 0, "maxOccurs": 1, **spec}
    outputs = {
        name: {
            "title": name,
            "description": text,
            "schema": {"type": "string", "contentMediaType": media_type(name)},
        }
        for name, text in OUTPUTS.items()
    }
    return {**process_summary(base), "inputs": inputs, "outputs": outputs}


def status_info(job: Job, base: str, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """statusInfo of OGC API – Processes Part 1, optional members only when known;
    ``extra`` adds terrasift's own members (stage, warnings, queuePosition)."""
    doc: dict[str, Any] = {
        "processID": job.process_id,
        "type": "process",
        "jobID": job.id,
        "status": job.status,
        "progress": int(job.progress),
        "created": job.created,
        "updated": job.updated,
    }
    if job.message:
        doc["message"] = job.message
    if job.started:
        doc["started"] = job.started
    if job.finished:
        doc["finished"] = job.finished
    doc.update(extra or {})
    doc["links"] = [
        link(f"{base}/jobs/{job.id}", "self", title="job status"),
        link(f"{base}/jobs/{job.id}/results", REL_RESULTS, title="job results"),
    ]
    return doc


def results(job: Job, base: str) -> dict[str, Any]:
    """Results document: each output by reference, with its media type."""
    assert job.status == SUCCESSFUL
    return {
        name: {"href": f"{base}/jobs/{job.id}/outputs/{name}", "type": media_type(name)}
        for name in job.outputs
    }
