"""What every route needs, kept on ``app.state.svc`` for the lifetime of the app."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from starlette.requests import Request

from terrasift.service.scheduler import Scheduler
from terrasift.service.settings import Settings
from terrasift.service.store import JobStore


@dataclass
class Service:
    settings: Settings
    store: JobStore
    scheduler: Scheduler
    #: the subprocesses reading tile headers (``service.inspector``; None: read in-process)
    inspector: Any | None = None


def service(request: Request) -> Service:
    """The running service of this app."""
    return request.app.state.svc


def base_url(request: Request) -> str:
    """Absolute base URL for links: the configured public URL, else the request's own."""
    configured = request.app.state.settings.public_url
    return (configured or str(request.base_url)).rstrip("/")
