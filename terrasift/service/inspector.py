"""Tile headers read in disposable subprocesses, each with a CPU, wall-time and memory budget.

Reading a header means letting laspy and the lazrs decoder parse bytes a client
chose (VLRs, the laszip record, the LAZ chunk table, a CRS). The structural
checks in ``tiling.lasfile`` refuse what they know to be impossible, but a
decoder that *aborts* (a failed allocation in Rust, a crash in C) cannot be
caught: in the API process it would take the service down. Here every header
is read by one of a few pre-started reader processes (``workers.pool``'s worker
loop): each may map at most ``memory`` bytes beyond what it holds after
importing the decoders (RLIMIT_AS, so a huge allocation fails at once) and spend
``seconds`` of CPU (``wall_factor`` times that in all) per file. The calling
thread talks to a reader over its own pipe (no hop through a manager thread: a
submission pays one round trip per file). A reader that crashes or overruns is
killed and replaced in the background; only that request fails, with a verdict
naming the file:

- the file's fault (4xx ``invalid-input``): the reader aborted or crashed, ran
  out of its memory budget, or spent its whole CPU budget;
- the machine's fault (503 ``service-unavailable``): the reader was killed from
  outside (the OOM killer), got too little CPU to finish in time, or no reader
  was free.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import logging
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

from terrasift.errors import InputError, ProcessingError, TerrasiftError, Unavailable
from terrasift.tiling.lasfile import TileInfo, read_tile_info
from terrasift.workers.pool import _cpu_seconds, _worker_main

log = logging.getLogger(__name__)

#: modules a reader imports before its memory budget is set, so the first file is quick
PRELOAD = ("numpy", "laspy", "lazrs", "pyproj", "terrasift.tiling.lasfile")
#: signals that end a reader from outside (an operator, the OOM killer): not the file's fault
OUTSIDE_SIGNALS = {signal.SIGKILL, signal.SIGTERM, signal.SIGINT, signal.SIGHUP}
WALL_FACTOR = 2.0  # wall-clock budget per file, in multiples of its CPU budget
STARTUP_WAIT = 10.0  # seconds a file may also wait for a reader to start (the first, a replacement)
START_TIMEOUT = 120.0  # a reader not ready after this long is killed and started again
POLL = 0.05  # seconds between looks at a reader's CPU time while it reads


@dataclass(eq=False)
class _Reader:
    proc: Any
    conn: Connection


class HeaderInspector:
    """Reads tile headers in ``workers`` subprocesses; call it like ``jobs.plan.HeaderReader``.

    ``read`` is the function a subprocess runs per file (``read_tile_info``; tests
    pass one that misbehaves). The readers start with ``start`` (in the background)
    or with the first call.
    """

    def __init__(
        self,
        workers: int = 2,
        *,
        seconds: float = 5.0,
        memory: int = 512 * 1024**2,
        pid_dir: Path | None = None,
        read: Callable[..., TileInfo] = read_tile_info,
        wall_factor: float = WALL_FACTOR,
    ):
        self.workers = workers
        self.seconds = seconds
        self.memory = memory
        self.pid_dir = pid_dir
        self.read = read
        self.wall_factor = wall_factor
        self.replaced = 0  # readers that died or were stopped, and were replaced
        self._ctx = multiprocessing.get_context("spawn")  # the API runs threads: never fork
        self._cond = threading.Condition(threading.RLock())
        self._idle: list[_Reader] = []
        self._live: set[_Reader] = set()
        self._starting = 0  # readers asked for and not yet ready
        self._queued = 0  # of those, not yet being started
        self._starter: threading.Thread | None = None
        self._started = False
        self._closed = False
        self._ids = itertools.count()
        if pid_dir is not None:
            Path(pid_dir).mkdir(parents=True, exist_ok=True)

    # -- lifecycle --------------------------------------------------------

    def start(self) -> None:
        """Start the readers in the background (once)."""
        with self._cond:
            if self._closed:
                raise Unavailable("the service is shutting down; header reading has stopped")
            if self._started:
                return
            self._started = True
        for _ in range(self.workers):
            self._spawn()

    def _spawn(self) -> None:
        """Have one more reader started; it joins the idle ones once it is ready.

        Readers are started by one long-lived thread: a reader gets SIGKILL when the
        thread that started it ends (``PR_SET_PDEATHSIG`` follows the thread).
        """
        with self._cond:
            if self._closed:
                return
            self._starting += 1
            self._queued += 1
            if self._starter is None or not self._starter.is_alive():
                self._starter = threading.Thread(
                    target=self._starter_loop, name="header-reader-starter", daemon=True
                )
                self._starter.start()
            self._cond.notify_all()

    def _starter_loop(self) -> None:
        while True:
            with self._cond:
                while not self._closed and self._queued == 0:
                    self._cond.wait()
                if self._closed:
                    return
                self._queued -= 1
            self._start_reader()

    def _start_reader(self) -> None:
        reader = None
        try:
            parent_end, child_end = self._ctx.Pipe(duplex=True)
            proc = self._ctx.Process(
                target=_worker_main,
                args=(
                    child_end,
                    os.getpid(),
                    0,  # the API's own priority: a submission waits for its reader
                    str(self.pid_dir) if self.pid_dir else None,
                    PRELOAD,
                    self.memory,
                ),
                name="terrasift-header-reader",
                daemon=True,
            )
            proc.start()
            child_end.close()
            reader = _Reader(proc, parent_end)
            with self._cond:
                self._live.add(reader)
            ready = wait([parent_end, proc.sentinel], timeout=START_TIMEOUT)
            if parent_end not in ready or parent_end.recv() != (None, True, "ready"):
                raise RuntimeError(f"exit code {proc.exitcode}" if ready else "start-up timed out")
        except Exception as exc:  # noqa: BLE001 - logged; the next call starts another
            if not self._closed:
                log.error("a header reader did not start: %s", exc)
            with self._cond:
                self._starting -= 1
                self._cond.notify_all()
            if reader is not None:
                self._discard(reader)
            return
        with self._cond:
            self._starting -= 1
            if self._closed:
                closed = True
            else:
                closed = False
                self._idle.append(reader)
                self._cond.notify()
        if closed:
            self._discard(reader)

    def stop(self) -> None:
        """Stop the readers; a call still waiting for one gets a 503."""
        with self._cond:
            self._closed = True
            readers = list(self._live)
            self._idle.clear()
            self._cond.notify_all()
        for r in readers:
            with contextlib.suppress(OSError):
                os.kill(r.proc.pid, signal.SIGKILL)
        for r in readers:
            self._discard(r)

    @property
    def closed(self) -> bool:
        """True once ``stop`` was called."""
        return self._closed

    def pids(self) -> list[int]:
        """Pids of the live readers (for tests and the health check)."""
        with self._cond:
            return sorted(r.proc.pid for r in self._live if r.proc.pid)

    def _discard(self, reader: _Reader) -> None:
        """Forget a reader that was killed or died (its pid file goes too)."""
        with contextlib.suppress(OSError):
            os.kill(reader.proc.pid, signal.SIGKILL)
        with contextlib.suppress(Exception):
            reader.proc.join(5.0)
        with contextlib.suppress(Exception):
            reader.conn.close()
        if self.pid_dir is not None and reader.proc.pid:
            with contextlib.suppress(OSError):
                (Path(self.pid_dir) / str(reader.proc.pid)).unlink()
        with self._cond:
            self._live.discard(reader)

    def _replace(self, reader: _Reader) -> None:
        self._discard(reader)
        with self._cond:
            self.replaced += 1
        self._spawn()

    # -- reading ----------------------------------------------------------

    def __call__(
        self, paths: Sequence[str | Path], max_points: int | None = None
    ) -> list[TileInfo]:
        """Each path's ``TileInfo``, in order; a file found wrong raises naming it (the
        first in order of those read).

        Several files are read side by side, one per reader (this thread and up to
        ``workers - 1`` more): a request naming eight tiles waits for about half the
        round trips with two readers. After a file is found wrong no further file starts.
        """
        self.start()
        task = functools.partial(self.read, max_points=max_points)
        todo = [Path(p) for p in paths]
        lanes = min(len(todo), self.workers)
        if lanes < 2:
            return [self._read_one(task, p) for p in todo]
        results: list[TileInfo | None] = [None] * len(todo)
        errors: dict[int, BaseException] = {}
        turns = iter(range(len(todo)))  # next() on it is atomic under the GIL
        failed = threading.Event()

        def lane() -> None:
            for i in turns:
                if failed.is_set():
                    return
                try:
                    results[i] = self._read_one(task, todo[i])
                except BaseException as exc:  # noqa: BLE001 - raised in the calling thread
                    errors[i] = exc
                    failed.set()
                    return

        helpers = [threading.Thread(target=lane, daemon=True) for _ in range(lanes - 1)]
        for t in helpers:
            t.start()
        lane()
        for t in helpers:
            t.join()
        if errors:
            raise errors[min(errors)]
        return [r for r in results if r is not None]

    def _checkout(self, name: str) -> _Reader:
        """An idle reader, waiting for one at most the wall budget of those ahead, or start-up."""
        timeout = self.wall_factor * self.seconds + STARTUP_WAIT
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                if self._closed:
                    raise Unavailable(
                        f"{name}: header reading was stopped (the service is shutting down)"
                    )
                while self._idle:
                    reader = self._idle.pop()
                    if reader.proc.is_alive():
                        return reader
                    threading.Thread(target=self._replace, args=(reader,), daemon=True).start()
                if not self._live and self._starting == 0:  # every start failed: try again
                    for _ in range(self.workers):
                        self._spawn()  # the lock is re-entrant
                left = deadline - time.monotonic()
                if left <= 0:
                    raise Unavailable(
                        f"{name}: no header reader was free within {timeout:.0f} s "
                        "(the service is busy); try again later"
                    )
                self._cond.wait(min(left, 1.0))

    def _checkin(self, reader: _Reader) -> None:
        with self._cond:
            if self._closed:
                closed = True
            else:
                closed = False
                self._idle.append(reader)
                self._cond.notify()
        if closed:
            self._discard(reader)

    def _read_one(self, task: Callable[..., TileInfo], path: Path) -> TileInfo:
        name = path.name
        reader = self._checkout(name)
        pid = reader.proc.pid
        task_id = next(self._ids)
        try:
            reader.conn.send((task_id, task, (str(path),)))
        except Exception as exc:  # noqa: BLE001 - a dead pipe: the reader died while idle
            self._replace(reader)
            raise Unavailable(f"{name}: the header reader was lost ({exc}); try again") from None
        started = time.monotonic()
        cpu0 = _cpu_seconds(pid)
        limit = self.seconds
        while True:
            ready = wait([reader.conn, reader.proc.sentinel], timeout=POLL)
            if reader.conn in ready:
                try:
                    got_id, ok, value = reader.conn.recv()
                except (EOFError, OSError):
                    ready = [reader.proc.sentinel]  # it died replying
                except Exception as exc:  # noqa: BLE001 - a reply that does not unpickle
                    self._checkin(reader)
                    raise InputError(
                        f"{name}: the header reader's answer could not be read "
                        f"({type(exc).__name__}: {exc})"
                    ) from None
                else:
                    if got_id == task_id:
                        self._checkin(reader)
                        if ok:
                            return value
                        raise self.verdict(name, value)
                    continue  # not ours (cannot happen: one call per reader at a time)
            if reader.proc.sentinel in ready or not reader.proc.is_alive():
                reader.proc.join(1.0)
                code = reader.proc.exitcode
                self._replace(reader)
                raise self.died(name, code)
            cpu = _cpu_seconds(pid) - cpu0
            wall = time.monotonic() - started
            if cpu > limit or wall > self.wall_factor * limit:
                self._replace(reader)
                if cpu > limit:
                    raise InputError(
                        f"{name}: reading its header took more than {limit:g} s of CPU and was "
                        "stopped (the file is corrupt or built to exhaust the reader)"
                    )
                raise Unavailable(
                    f"{name}: reading its header got only {cpu:.1f} s of CPU in {wall:.0f} s "
                    "and was stopped (the service is too busy); try again later"
                )

    # -- verdicts ---------------------------------------------------------

    def died(self, name: str, code: int | None) -> TerrasiftError:
        """A reader that died reading ``name``: the file's fault unless killed from outside."""
        if code is not None and code < 0 and -code not in OUTSIDE_SIGNALS:
            return InputError(
                f"{name}: reading its header crashed the reader ({_signal_name(-code)}); the "
                "file is corrupt or built to crash a LAS/LAZ decoder"
            )
        if code is not None and code > 0:
            return InputError(
                f"{name}: reading its header made the reader exit (code {code}); the file is "
                "corrupt"
            )
        how = _signal_name(-code) if code is not None and code < 0 else "unknown cause"
        return Unavailable(
            f"{name}: the process reading its header was stopped from outside ({how}; the "
            "machine may be short of memory); try again later"
        )

    def verdict(self, name: str, exc: BaseException) -> TerrasiftError:
        """What an error raised while reading ``name`` tells the client."""
        if isinstance(exc, TerrasiftError) and not isinstance(exc, ProcessingError):
            return exc  # the header check's own verdict (InputError, ...)
        if isinstance(exc, MemoryError):
            return InputError(
                f"{name}: reading its header needs more than the reader's memory budget of "
                f"{self.memory / 2**20:.0f} MiB (the file is corrupt or built to exhaust memory)"
            )
        if isinstance(exc, ProcessingError):  # an exception that could not travel back
            return InputError(f"{name}: the header could not be read: {exc}")
        log.warning("header of %s: %s", name, exc, exc_info=exc)
        text = str(exc).strip() or "no message"
        return InputError(f"{name}: the header could not be read ({type(exc).__name__}: {text})")


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"
