"""Bearer tokens map to tenants; a tenant sees only its own jobs and surveys.

The token file holds one ``token tenant`` pair per line (``#`` starts a
comment). With auth off (a loopback bind without a token file, or
``TERRASIFT_AUTH=off``) every request belongs to the tenant ``local``.
"""

from __future__ import annotations

import hmac
from pathlib import Path

from fastapi import Request

from terrasift.service.problems import Problem

LOCAL_TENANT = "local"


def load_tokens(path: Path) -> dict[str, str]:
    """token → tenant from a token file; malformed lines raise ValueError naming the line."""
    tokens: dict[str, str] = {}
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2:
            raise ValueError(f"{path.name}, line {number}: expected `token tenant`")
        tokens[parts[0]] = parts[1]
    return tokens


class Auth:
    """Resolves the tenant of a request, or refuses it with 401."""

    def __init__(self, enabled: bool, tokens: dict[str, str] | None = None):
        self.enabled = enabled
        self.tokens = tokens or {}

    def tenant(self, request: Request) -> str:
        if not self.enabled:
            return LOCAL_TENANT
        scheme, _, token = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() == "bearer" and token:
            for known, tenant in self.tokens.items():
                if hmac.compare_digest(known.encode(), token.strip().encode()):
                    return tenant
        raise Problem(
            "unauthorized",
            "send `Authorization: Bearer <token>` with a token from the service's token file",
            headers={"WWW-Authenticate": 'Bearer realm="terrasift"'},
        )


def tenant(request: Request) -> str:
    """FastAPI dependency: the tenant of this request."""
    return request.app.state.auth.tenant(request)
