"""Write api-spec/openapi.yaml from the app, so the checked-in spec is what the code serves.

Run it after changing a route: ``python scripts/export_openapi.py`` (``make openapi``).
``tests/test_api_spec.py`` fails when the file and the app disagree.
"""

from __future__ import annotations

import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
SPEC = REPO / "api-spec" / "openapi.yaml"


def render() -> str:
    """The app's OpenAPI document as YAML (keys in the app's order)."""
    sys.path.insert(0, str(REPO))
    from terrasift.service.app import create_app
    from terrasift.service.settings import Settings

    spec = create_app(Settings(_env_file=None)).openapi()
    return yaml.safe_dump(spec, sort_keys=False, allow_unicode=True, width=100)


def main() -> None:
    SPEC.parent.mkdir(parents=True, exist_ok=True)
    SPEC.write_text(render())
    print(f"wrote {SPEC.relative_to(REPO)}")


if __name__ == "__main__":
    main()
