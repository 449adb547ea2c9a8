"""Subscriber callbacks of OGC execute requests: POSTs to the client's URLs as a job moves on.

``inProgressUri`` gets the statusInfo when the job starts and whenever its
progress changes (at most once per ``min_interval`` seconds), ``successUri``
the results document, ``failedUri`` the statusInfo of a failed or dismissed
job. Each POST is tried ``attempts`` times with doubling waits; a receiver
that never answers 2xx is logged and given up. Each job's callbacks go out
from their own thread, in order, so a dead receiver delays only its job's. Subscriptions are kept in the
job directory (``subscriber.json``), so a restarted service still calls back.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from terrasift.service import ogc
from terrasift.service.store import ACCEPTED, RUNNING, SUCCESSFUL, JobStore

log = logging.getLogger(__name__)
FILE = "subscriber.json"


@dataclass
class _Subscription:
    uris: dict[str, str]
    base: str
    last: tuple[str, int] | None = None
    sent_at: float = 0.0
    deliveries: list[str] = field(default_factory=list)
    worker: threading.Thread | None = None


class Notifier:
    """A thread that watches subscribed jobs in the store and calls their URLs."""

    def __init__(
        self,
        store: JobStore,
        job_dir: Callable[[str], Path],
        *,
        attempts: int = 4,
        first_wait: float = 0.5,
        poll: float = 0.25,
        min_interval: float = 1.0,
        timeout: float = 10.0,
    ):
        self.store, self.job_dir = store, job_dir
        self.attempts, self.first_wait, self.poll = attempts, first_wait, poll
        self.min_interval, self.timeout = min_interval, timeout
        self._subs: dict[str, _Subscription] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def subscribe(self, job_id: str, uris: dict[str, str], base: str) -> None:
        """Call ``uris`` back for job ``job_id``; links in the documents start with ``base``."""
        path = self.job_dir(job_id) / FILE
        path.write_text(json.dumps({"uris": uris, "base": base}))
        with self._lock:
            self._subs[job_id] = _Subscription(dict(uris), base)

    def start(self) -> None:
        """Pick up subscriptions of unfinished jobs, then watch."""
        for job in self.store.jobs_with_status(ACCEPTED, RUNNING):
            try:
                saved = json.loads((self.job_dir(job.id) / FILE).read_text())
            except (OSError, ValueError):
                continue
            self._subs[job.id] = _Subscription(saved["uris"], saved["base"])
        self._thread = threading.Thread(target=self._loop, name="terrasift-callbacks", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def _loop(self) -> None:
        while not self._stop.wait(self.poll):
            with self._lock:
                subs = list(self._subs.items())
            for job_id, sub in subs:
                # one delivery thread per job at a time: a job's callbacks stay in order,
                # and a slow or dead receiver (retries) does not hold up other jobs'
                if sub.worker is None or not sub.worker.is_alive():
                    sub.worker = threading.Thread(
                        target=self._deliver, args=(job_id, sub), daemon=True
                    )
                    sub.worker.start()

    def _deliver(self, job_id: str, sub: _Subscription) -> None:
        try:
            if self._check(job_id, sub):
                with self._lock:
                    self._subs.pop(job_id, None)
        except Exception:  # noqa: BLE001 - one bad job must not stop the others
            log.exception("callback for job %s failed", job_id)

    def _check(self, job_id: str, sub: _Subscription) -> bool:
        """Send what is due for one job; True once the job is final (and told)."""
        job = self.store.get_job(job_id)
        if job is None:
            return True
        if job.status == SUCCESSFUL:
            self._send(sub, "successUri", ogc.results(job, sub.base))
            return True
        if job.status not in (ACCEPTED, RUNNING):
            self._send(sub, "failedUri", ogc.status_info(job, sub.base))
            return True
        state = (job.status, job.progress)
        now = time.monotonic()
        if job.status == RUNNING and state != sub.last and now - sub.sent_at >= self.min_interval:
            sub.last, sub.sent_at = state, now
            self._send(sub, "inProgressUri", ogc.status_info(job, sub.base))
        return False

    def _send(self, sub: _Subscription, key: str, doc: dict[str, Any]) -> bool:
        url = sub.uris.get(key)
        if not url:
            return False
        wait = self.first_wait
        for attempt in range(1, self.attempts + 1):
            try:
                r = httpx.post(url, json=doc, timeout=self.timeout)
                if 200 <= r.status_code < 300:
                    sub.deliveries.append(key)
                    return True
                reason = f"HTTP {r.status_code}"
            except httpx.HTTPError as exc:
                reason = str(exc) or type(exc).__name__
            log.info("callback %s to %s, attempt %d: %s", key, url, attempt, reason)
            if attempt == self.attempts or self._stop.wait(wait):
                break
            wait *= 2
        log.warning("callback %s to %s given up after %d attempts", key, url, self.attempts)
        return False
