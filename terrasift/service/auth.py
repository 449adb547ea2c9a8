"""Bearer tokens map to tenants; a tenant sees only its own jobs and surveys.

The token file holds one ``token tenant`` pair per line (``#`` starts a
comment), or a JSON object mapping tokens to tenants. With auth off (a loopback bind without a token file, or
``TERRASIFT_AUTH=off``) every request belongs to the tenant ``local``.
"""

from __future__ import annotations

import hmac
import json
from pathlib import Path

from fastapi import Request

from terrasift.service.problems import Problem

LOCAL_TENANT = "local"


def load_tokens(path: Path) -> dict[str, str]:
    """token → tenant from a token file: ``token tenant`` lines, or a JSON object ``{"token": "tenant"}``.

    A missing or malformed file raises ValueError naming the file (and line), so
    the service refuses to start rather than run with auth silently broken.
    """
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"token file {path}: {exc.strerror}") from None
    if text.lstrip().startswith("{"):
        try:
            tokens = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(
                f"token file {path}: not valid JSON ({exc.msg}, line {exc.lineno})"
            ) from None
        if not all(
            isinstance(k, str) and isinstance(v, str) and k and v for k, v in tokens.items()
        ):
            raise ValueError(
                f"token file {path}: expected an object of token strings to tenant strings"
            )
        return tokens
    tokens = {}
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2:
            raise ValueError(f"token file {path}, line {number}: expected `token tenant`")
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


async def tenant(request: Request) -> str:
    """FastAPI dependency: the tenant of this request (async: no thread hop, it only compares)."""
    return request.app.state.auth.tenant(request)
