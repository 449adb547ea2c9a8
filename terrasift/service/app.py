"""The FastAPI application: a thin layer that validates, records and schedules.

``create_app(settings)`` builds the app; its lifespan opens the job store and
starts the scheduler (which resumes interrupted jobs). ``serve`` runs it with
uvicorn, which ``terrasift serve`` calls.
"""

from __future__ import annotations

import gc
import logging
import os
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from functools import partial
from typing import Any

import anyio
from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from terrasift import __version__
from terrasift.jobs.plan import header_reader, use_header_reader
from terrasift.jobs.warm import cache_dir_for
from terrasift.service import problems
from terrasift.service.auth import Auth, load_tokens
from terrasift.service.callbacks import Notifier
from terrasift.service.context import Service
from terrasift.service.guard import RequestGuard
from terrasift.service.inspector import HeaderInspector
from terrasift.service.routes import events, health, jobs, pages, path, processes, surveys, uploads
from terrasift.service.scheduler import Scheduler
from terrasift.service.schemas import add_problem_schema
from terrasift.service.settings import Settings
from terrasift.service.store import JobStore
from terrasift.tiling.lasfile import TileInfo, read_tile_info
from terrasift.workers.executors import Executor
from terrasift.workers.pool import reap_leftovers

log = logging.getLogger(__name__)


def create_app(
    settings: Settings | None = None,
    *,
    pipeline: Any | None = None,
    executor_factory: Callable[[], Executor] | None = None,
    freeze_heap: bool = False,
    read_header: Callable[..., TileInfo] | None = None,
) -> FastAPI:
    """The terrasift API; ``pipeline``/``executor_factory`` replace the real ones in tests.

    With the real pipeline, tile headers are read by ``settings.header_readers``
    subprocesses (``service.inspector``), which start with the app; ``read_header``
    replaces the function they run (tests: one that crashes).

    ``freeze_heap`` (``terrasift serve``): at startup, import what jobs need and move
    every object alive then out of the garbage collector's reach (see ``settle_heap``).
    """
    settings = settings or Settings()
    if executor_factory is None:

        def executor_factory() -> Executor:
            from terrasift.workers.executors import make_executor

            return make_executor(
                settings.workers,
                settings.dask_scheduler,
                settings.dask_no_workers_timeout,
                nice=settings.worker_nice,
                memory_limit=settings.worker_memory_limit(),
                pid_dir=settings.workers_dir,
            )

    auth = Auth(
        settings.auth_enabled, load_tokens(settings.token_file) if settings.token_file else {}
    )
    if auth.enabled and not auth.tokens:
        log.warning("auth is on but no tokens are configured: every job request will get 401")

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        settings.jobs_dir.mkdir(parents=True, exist_ok=True)
        settings.surveys_dir.mkdir(parents=True, exist_ok=True)
        reaped = reap_leftovers(settings.workers_dir)
        if reaped:
            log.warning("killed %d worker(s) left by an earlier run: %s", len(reaped), reaped)
        store = JobStore(settings.db_path, settings.jobs_dir, settings.surveys_dir)
        if store.recovered:
            log.error("job store: %s", store.recovered)
        scheduler = Scheduler(
            store,
            settings.jobs_dir,
            executor_factory,
            settings.max_concurrent_jobs,
            pipeline=pipeline,
            task_seconds=(settings.task_seconds, settings.task_seconds_per_mpoint),
            input_roots=[
                settings.jobs_dir,
                settings.surveys_dir,
                *([settings.input_root] if settings.input_root else []),
            ],
        )
        inspector = None
        if pipeline is None and settings.header_readers > 0:
            inspector = HeaderInspector(
                settings.header_readers,
                seconds=settings.header_seconds,
                memory=settings.header_memory,
                pid_dir=settings.workers_dir,
                read=read_header or read_tile_info,
            )
            inspector.start()
        previous_reader = use_header_reader(inspector) if inspector is not None else None
        if freeze_heap:
            log.info("%d objects frozen out of garbage collection", settle_heap())
        app.state.svc = Service(settings, store, scheduler, inspector)
        scheduler.on_success = partial(surveys.continue_batches, app.state.svc)
        app.state.notifier = Notifier(store, scheduler.job_dir, attempts=settings.callback_attempts)
        scheduler.start()
        app.state.notifier.start()
        try:
            yield
        finally:
            await anyio.to_thread.run_sync(app.state.notifier.stop)
            # running tasks get the grace period, then their workers are stopped; off the event loop
            await anyio.to_thread.run_sync(scheduler.stop, settings.shutdown_grace)
            if inspector is not None:
                if header_reader() is inspector:  # an app started meanwhile keeps its own
                    alive = not getattr(previous_reader, "closed", False)
                    use_header_reader(previous_reader if alive else None)
                await anyio.to_thread.run_sync(inspector.stop)
            store.close()

    app = FastAPI(
        title="terrasift",
        version=__version__,
        description="OGC API – Processes over LAS/LAZ tiles: ground classification, DTM/DSM, "
        "vegetation, terrain objects. Errors are RFC 9457 problem+json.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.auth = auth
    problems.install(app)
    app.add_middleware(RequestGuard)
    app.include_router(pages.router)  # first: matches only requests that want HTML
    app.include_router(processes.router)
    app.include_router(jobs.router)
    app.include_router(path.router)
    app.include_router(surveys.router)
    app.include_router(uploads.router)
    app.include_router(events.router)
    app.include_router(health.router)

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = add_problem_schema(
                get_openapi(
                    title=app.title,
                    version=app.version,
                    description=app.description,
                    routes=app.routes,
                )
            )
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    return app


def settle_heap() -> int:
    """Import what the job driver uses, collect once and freeze the survivors; how many.

    A full collection walks every object the collector tracks, and with numpy,
    numba, rasterio and Dask loaded that is ~140,000 objects: 50-130 ms holding the
    GIL, during which the event loop answers no request (0.3 s stalls of every
    status read at load ~15). Frozen objects are skipped by later collections;
    what the service allocates afterwards is collected as before.
    """
    import rasterio  # noqa: F401 - the job driver's last check reads the DTM with it

    import terrasift.jobs  # noqa: F401 - otherwise imported by the first job's thread

    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def serve(
    host: str | None = None, port: int | None = None, settings: Settings | None = None
) -> None:
    """Run the API with embedded workers (``terrasift serve``).

    uvicorn picks uvloop and httptools (dependencies) over asyncio and h11: they take
    less CPU per request, so a status read waits less for a CPU on a busy machine.
    """
    import uvicorn

    settings = settings or Settings()
    update = {k: v for k, v in (("host", host), ("port", port)) if v is not None}
    settings = settings.model_copy(update=update)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    cache = cache_dir_for(settings.data_dir)
    if cache is not None:  # read-only install: workers (spawned later) cache here
        os.environ["NUMBA_CACHE_DIR"] = str(cache)
    uvicorn.run(
        create_app(settings, freeze_heap=True),
        host=settings.host,
        port=settings.port,
        access_log=settings.access_log,
    )
