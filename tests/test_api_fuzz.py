"""Schemathesis over the OpenAPI document: whatever the generated requests hold, the
service never answers 5xx. The number of examples per operation is bounded."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error

from terrasift.service.app import create_app
from terrasift.service.settings import Settings
from terrasift.synthetic.terrain import make_scene, write_las

EXAMPLES = 6  # per operation (its coverage phase adds the boundary cases)
STATUSES: Counter[int] = Counter()


def _app():
    import tempfile

    tmp = Path(tempfile.mkdtemp(prefix="terrasift-fuzz-"))
    root = tmp / "root"
    root.mkdir()
    write_las(make_scene(size=40, density=2, seed=5), root / "tile.las")
    settings_ = Settings(
        _env_file=None, data_dir=tmp / "data", workers=1, input_root=root, sync_max_points=0
    )
    # jobs are recorded but never run: only the answers matter here
    app = create_app(settings_, executor_factory=lambda: pytest.fail("no job should run"))
    client = TestClient(app, raise_server_exceptions=False)
    client.__enter__()  # runs the lifespan: store and scheduler exist for every call
    app.state.svc.scheduler.stop()
    return app, client


APP, CLIENT = _app()
schema = schemathesis.openapi.from_asgi("/openapi.json", APP)


@schema.parametrize()
@settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=list(HealthCheck),
)
def test_no_request_gets_a_5xx(case: schemathesis.Case) -> None:
    response = case.call_and_validate(checks=[not_a_server_error])
    STATUSES[response.status_code] += 1


def teardown_module() -> None:
    print(
        f"schemathesis: {sum(STATUSES.values())} cases, statuses {dict(sorted(STATUSES.items()))}"
    )
    CLIENT.__exit__(None, None, None)
