"""The checked-in OpenAPI spec is exactly what the app serves."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]


def _exporter():
    spec = importlib.util.spec_from_file_location(
        "export_openapi", REPO / "scripts" / "export_openapi.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_openapi_yaml_matches_the_app() -> None:
    exporter = _exporter()
    checked_in = (REPO / "api-spec" / "openapi.yaml").read_text()
    generated = exporter.render()
    assert yaml.safe_load(checked_in) == yaml.safe_load(generated), (
        "api-spec/openapi.yaml is out of date: run `python scripts/export_openapi.py`"
    )


def test_spec_documents_the_contract() -> None:
    spec = yaml.safe_load((REPO / "api-spec" / "openapi.yaml").read_text())
    paths = spec["paths"]
    for path, methods in {
        "/": {"get"},
        "/conformance": {"get"},
        "/processes": {"get"},
        "/processes/{process_id}": {"get"},
        "/processes/{process_id}/execution": {"post"},
        "/jobs": {"get", "post"},
        "/jobs/{job_id}": {"get", "delete"},
        "/jobs/{job_id}/results": {"get"},
        "/jobs/{job_id}/outputs/{name}": {"get", "head"},
        "/surveys": {"post"},
        "/surveys/{survey_id}/runs": {"post"},
        "/surveys/{survey_id}/tiles/{name}": {"put", "delete"},
        "/surveys/{survey_id}/results": {"get"},
        "/surveys/{survey_id}/outputs/{path}": {"get", "head"},
    }.items():
        assert methods <= set(paths[path]), path
    upload = paths["/jobs"]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert set(upload["properties"]) == {"file", "params"}
    status = spec["components"]["schemas"]["StatusInfo"]
    assert set(status["required"]) == {"jobID", "status"}
    assert paths["/jobs/{job_id}"]["get"]["responses"]["404"]["content"]["application/problem+json"]
