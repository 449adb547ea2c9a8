"""A process pool whose workers are disposable.

``concurrent.futures.ProcessPoolExecutor`` breaks for good when one worker
dies (an abort in a decoder, the OOM killer, ``kill -9``): every later task
fails. Here each worker has its own pipe, a manager thread knows which task
each worker runs, and a worker that dies, overruns its time limit, grows past
its memory limit or runs a task whose job was dismissed is killed and
replaced. Only that task fails; a task whose worker died is tried once more
(the death may have been someone else's fault, e.g. the OOM killer).

Workers run at a lower CPU priority than the process that owns the pool (in a
session and scheduling group of their own where the kernel groups by session), die
with it (``PR_SET_PDEATHSIG`` and a thread watching the parent pid), and
leave a pid file so that the next start can kill any that outlived a crash.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import itertools
import logging
import multiprocessing
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from multiprocessing.reduction import ForkingPickler
from pathlib import Path
from typing import Any

from terrasift.errors import InputError, JobCancelled, ProcessingError

log = logging.getLogger(__name__)

PR_SET_PDEATHSIG = 1
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096
_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
WALL_FACTOR = 4  # a task's wall-clock limit, in multiples of its CPU limit
KILL_WAIT = 3.0  # seconds a stopping pool waits for killed workers to be gone


class WorkerLost(ProcessingError):
    """The worker running a task died (a crash, an abort, the OOM killer, a kill)."""

    #: the worker's exit code (negative: the signal that ended it; None when unknown)
    exitcode: int | None = None


class TaskTimeout(ProcessingError):
    """A task ran longer than its time limit."""

    #: the CPU limit, and the CPU and wall seconds the task had used when it was stopped
    limit: float = 0.0
    cpu: float = 0.0
    wall: float = 0.0


class PoolFailed(ProcessingError):
    """The pool itself stopped working (no task's fault); a new pool is needed."""


class TaskOutOfMemory(ProcessingError, MemoryError):
    """A task's worker grew past the memory limit."""


def describe(fn: Callable[..., Any], args: tuple) -> str:
    """A task in words for error messages: its function and the names among its arguments."""
    names = [Path(a).name for a in args if isinstance(a, str) and a]
    return f"{getattr(fn, '__name__', 'task')}({', '.join(names)})"


# ------------------------------------------------------------------ worker side


def _proc_start_time(pid: int) -> str | None:
    """Start time of ``pid`` in clock ticks since boot (tells a pid from a reused one)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]


def _die_with_parent(parent: int) -> None:
    """Get SIGKILL when the parent goes (Linux), and watch its pid as a fallback."""
    with contextlib.suppress(Exception):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _lower_priority(nice: int) -> None:
    """Run ``nice`` steps below the owner, also where the kernel shares CPU time
    between sessions first (autogroup): there a nice value counts only within the
    session's group, and workers left in the owner's session would use up the
    group's share, so the owner's threads would wait for a CPU with them. A worker
    starts a session of its own and gives its group the same nice value."""
    with contextlib.suppress(OSError):
        os.nice(nice)
    with contextlib.suppress(OSError):
        os.setsid()
        Path("/proc/self/autogroup").write_text(f"{nice}\n")


def _limit_address_space(extra: int) -> None:
    """Let the process map at most ``extra`` bytes more than it has mapped now (RLIMIT_AS).

    An allocation beyond it fails at once (MemoryError in Python, an abort in a
    Rust decoder) instead of growing until a watchdog or the OOM killer notices.
    """
    import resource

    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                mapped = int(line.split()[1]) * 1024
                break
        else:
            return
        resource.setrlimit(resource.RLIMIT_AS, (mapped + extra, mapped + extra))
    except (OSError, ValueError) as exc:
        log.warning("worker %s: no address-space limit (%s)", os.getpid(), exc)


def _worker_main(
    conn: Connection,
    parent: int,
    nice: int,
    pid_dir: str | None,
    preload: tuple[str, ...] = (),
    address_space: int | None = None,
) -> None:
    """Run tasks from ``conn`` until told to stop; each reply is (task id, ok, value).

    ``preload`` modules are imported first (a task then starts at once), and only
    then is the address space limited to ``address_space`` bytes more.
    """
    _die_with_parent(parent)
    if nice:
        _lower_priority(nice)
    for module in preload:
        try:
            importlib.import_module(module)
        except Exception:  # noqa: BLE001 - the task that needs it will say why
            log.exception("worker %s: cannot preload %s", os.getpid(), module)
    if address_space is not None:
        _limit_address_space(address_space)
    with contextlib.suppress(OSError):
        conn.send((None, True, "ready"))  # no task is sent (or timed) before this
    peaks = os.environ.get(TASK_PEAKS_ENV, "")
    pid_file = None
    if pid_dir:
        pid_file = Path(pid_dir) / str(os.getpid())
        with contextlib.suppress(OSError):
            pid_file.write_text(f"{_proc_start_time(os.getpid())}\n")
    try:
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                return
            if msg is None:
                return
            task_id, fn, args = msg
            record = _TaskRecord(fn, args) if peaks else None
            try:
                reply = (task_id, True, fn(*args))
            except BaseException as exc:  # noqa: BLE001 - the caller gets it through the future
                reply = (task_id, False, _portable(exc, fn, args))
            if record is not None:
                record.write(peaks, reply[1])
            try:
                conn.send(reply)
            except Exception as exc:  # noqa: BLE001 - a result that does not pickle
                conn.send(
                    (
                        task_id,
                        False,
                        ProcessingError(
                            f"{describe(fn, args)} finished, but its result could not be "
                            f"sent back ({type(exc).__name__}: {exc})"
                        ),
                    )
                )
    finally:
        if pid_file is not None:
            with contextlib.suppress(OSError):
                pid_file.unlink()


TASK_PEAKS_ENV = "TERRASIFT_TASK_PEAKS"


def _status_bytes(key: str) -> int:
    """A ``/proc/self/status`` size (``VmRSS``, ``VmHWM``) in bytes (0 when unknown)."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    return 0


class _TaskRecord:
    """Peak resident memory of one task in this worker (Linux), for benchmarks: the
    process's high-water mark is reset when the task starts (``clear_refs``) and read
    when it ends, so each task's peak is its own even in a reused process. Written as
    one JSON line per task to ``<folder>/<pid>.jsonl`` when ``TERRASIFT_TASK_PEAKS``
    names a folder."""

    def __init__(self, fn: Callable[..., Any], args: tuple) -> None:
        self.fn, self.args = fn, args
        with contextlib.suppress(OSError):
            Path("/proc/self/clear_refs").write_text("5")
        self.rss_start = _status_bytes("VmRSS")
        self.wall = time.perf_counter()
        self.cpu = time.process_time()

    def write(self, folder: str, ok: bool) -> None:
        import json

        line = {
            "fn": getattr(self.fn, "__name__", "task"),
            "task": describe(self.fn, self.args),
            "ok": ok,
            "rss_start": self.rss_start,
            "peak_rss": _status_bytes("VmHWM"),
            "rss_end": _status_bytes("VmRSS"),
            "cpu_s": time.process_time() - self.cpu,
            "wall_s": time.perf_counter() - self.wall,
        }
        with contextlib.suppress(OSError), open(Path(folder) / f"{os.getpid()}.jsonl", "a") as f:
            f.write(json.dumps(line) + "\n")


def _portable(exc: BaseException, fn: Callable[..., Any], args: tuple) -> BaseException:
    """``exc`` itself when it survives the trip to the owner, else an error that does.

    Some exceptions do not pickle (pyo3's ``PanicException``, raised when a Rust
    decoder such as lazrs panics on corrupt data, lives in a module that cannot be
    imported) or do not unpickle (a constructor that wants other arguments). The
    owner then gets the task, the exception's type and its message instead of an
    opaque transfer error; an ``InputError`` stays one.
    """
    try:
        ForkingPickler.loads(ForkingPickler.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 - any failure to round-trip
        pass
    kind = InputError if isinstance(exc, InputError) else ProcessingError
    text = str(exc).strip() or "no message"
    return kind(f"{describe(fn, args)} failed: {type(exc).__name__}: {text}")


def reap_leftovers(pid_dir: Path) -> list[int]:
    """Kill workers a crashed owner left behind (their pid files say who); the pids killed."""
    killed = []
    for entry in Path(pid_dir).glob("[0-9]*"):
        pid = int(entry.name)
        try:
            started = entry.read_text().strip()
        except OSError:
            started = ""
        if started and _proc_start_time(pid) == started and pid != os.getpid():
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
        with contextlib.suppress(OSError):
            entry.unlink()
    return killed


# ------------------------------------------------------------------ pool side


@dataclass(eq=False)
class _Task:
    id: int
    fn: Callable[..., Any]
    args: tuple
    future: Future
    timeout: float | None
    tries: int = 0
    started: float = 0.0
    cpu0: float = 0.0  # the worker's CPU seconds when the task started
    kill: BaseException | None = None  # why the manager must kill the worker running it


@dataclass(eq=False)
class _Worker:
    proc: Any
    conn: Connection
    task: _Task | None = None
    ready: bool = False  # said it is ready (started up and preloaded)
    lost: bool = False
    peak_rss: int = field(default=0)


class WorkerPool:
    """``workers`` processes; ``submit`` returns a ``concurrent.futures.Future``.

    ``memory_limit`` (bytes of resident memory per worker, None = none) and a
    task's ``timeout`` (seconds of CPU; WALL_FACTOR times that in all) fail the
    task with a message naming it; ``cancel`` stops queued and running tasks alike.
    ``preload`` names modules each worker imports when it starts, ``address_space``
    the bytes it may map beyond what it holds after that (RLIMIT_AS; None = no limit).
    """

    def __init__(
        self,
        workers: int,
        *,
        start_method: str = "spawn",
        nice: int = 0,
        memory_limit: int | None = None,
        retries: int = 1,
        pid_dir: Path | None = None,
        preload: tuple[str, ...] = (),
        address_space: int | None = None,
        name: str = "terrasift-worker",
    ):
        self.workers = workers
        self.preload = tuple(preload)
        self.address_space = address_space
        self.name = name
        self.start_method = start_method
        self.nice = nice
        self.memory_limit = memory_limit
        self.retries = retries
        self.pid_dir = pid_dir
        if pid_dir is not None:
            Path(pid_dir).mkdir(parents=True, exist_ok=True)
        self.replaced = 0
        self.peak_rss = 0
        self._ids = itertools.count()
        self._queue: deque[_Task] = deque()
        self._tasks: dict[Future, _Task] = {}
        self._lock = threading.Lock()
        self._closing = False
        self._kill_by: float | None = None  # set when stopping: when to stop waiting for deaths
        self._wake_r, self._wake_w = multiprocessing.Pipe(duplex=False)
        self._workers: list[_Worker] = []
        # A replacement is always spawned: by then the owner may run threads.
        self._spawn_ctx = multiprocessing.get_context("spawn")
        if start_method == "fork":
            ctx = multiprocessing.get_context("fork")
            self._workers = [self._start(ctx) for _ in range(workers)]
        self._manager = threading.Thread(target=self._manage, name="worker-pool", daemon=True)
        self._manager.start()

    # -- public -----------------------------------------------------------

    def submit(self, fn: Callable[..., Any], *args: Any, timeout: float | None = None) -> Future:
        future: Future = Future()
        task = _Task(next(self._ids), fn, args, future, timeout)
        with self._lock:
            if self._closing:
                raise RuntimeError("the worker pool is shut down")
            self._tasks[future] = task
            self._queue.append(task)
        self._wake()
        return future

    def cancel(self, futures: Iterable[Future], reason: str = "the job was dismissed") -> int:
        """Cancel queued futures and kill the workers running the others; how many were stopped."""
        stopped = 0
        with self._lock:
            for f in futures:
                task = self._tasks.get(f)
                if task is None or f.done():
                    continue
                if f.cancel():
                    stopped += 1
                elif task.kill is None:
                    task.kill = JobCancelled(reason)
                    stopped += 1
        self._wake()
        return stopped

    def shutdown(
        self, wait: bool = True, *, kill: bool = False, grace: float | None = None
    ) -> None:
        """Stop taking tasks; queued ones are cancelled. Running ones finish, or are
        stopped now (``kill``) or after ``grace`` seconds (``wait`` only).

        When tasks are stopped, idle workers are killed too instead of being asked to
        exit: a worker starved of CPU (low priority on a busy machine) can take tens of
        seconds to shut its interpreter down.
        """
        self._close(kill)
        if wait and grace is not None and not kill:
            self._manager.join(grace)
            if self._manager.is_alive():
                self._close(True)
        if wait:
            self._manager.join()

    def _close(self, kill: bool) -> None:
        with self._lock:
            self._closing = True
            for task in self._queue:
                task.future.cancel()
            self._queue.clear()
            if kill:
                if self._kill_by is None:
                    self._kill_by = time.monotonic() + KILL_WAIT
                for task in self._tasks.values():
                    if not task.future.done() and task.kill is None:
                        task.kill = JobCancelled("the service is shutting down")
        self._wake()

    def worker_pids(self) -> list[int]:
        """Pids of the live workers (for tests and the health check)."""
        return [w.proc.pid for w in list(self._workers) if w.proc.pid and not w.lost]

    def busy_pids(self) -> list[int]:
        """Pids of the workers running a task."""
        return [w.proc.pid for w in list(self._workers) if w.task is not None and not w.lost]

    # -- manager thread ---------------------------------------------------

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            self._wake_w.send_bytes(b".")

    def _start(self, ctx: Any) -> _Worker:
        parent_end, child_end = ctx.Pipe(duplex=True)
        proc = ctx.Process(
            target=_worker_main,
            args=(
                child_end,
                os.getpid(),
                self.nice,
                str(self.pid_dir) if self.pid_dir else None,
                self.preload,
                self.address_space,
            ),
            name=self.name,
            daemon=True,
        )
        proc.start()
        child_end.close()
        return _Worker(proc, parent_end)

    def _manage(self) -> None:
        try:
            while len(self._workers) < self.workers:
                self._workers.append(self._start(self._spawn_ctx))
            while True:
                self._dispatch()
                with self._lock:
                    busy = any(w.task is not None for w in self._workers)
                    if self._closing and not busy and not self._queue:
                        break
                    if self._kill_by is not None and time.monotonic() > self._kill_by:
                        break  # killed; they die with us at the latest (PDEATHSIG)
                ready = wait(
                    [self._wake_r]
                    + [w.conn for w in self._workers]
                    + [w.proc.sentinel for w in self._workers],
                    timeout=0.25,
                )
                if self._wake_r in ready:
                    with contextlib.suppress(OSError, EOFError):
                        while self._wake_r.poll():
                            self._wake_r.recv_bytes()
                for w in list(self._workers):
                    if w.conn in ready:
                        self._receive(w)
                for w in list(self._workers):
                    if w.proc.sentinel in ready or not w.proc.is_alive():
                        self._lost(w)
                self._police()
        except BaseException:  # noqa: BLE001 - the pool must not hang its callers
            log.exception("worker pool manager failed")
            with self._lock:
                for task in self._tasks.values():
                    if not task.future.done():
                        task.future.set_exception(PoolFailed("the worker pool failed"))
        finally:
            self._stop_workers()

    def _dispatch(self) -> None:
        with self._lock:
            for w in self._workers:
                while w.ready and w.task is None and self._queue and not w.lost:
                    task = self._queue.popleft()
                    if task.future.done():
                        continue  # cancelled after a retry was queued
                    if task.tries == 0 and not task.future.set_running_or_notify_cancel():
                        self._tasks.pop(task.future, None)
                        continue
                    try:
                        w.conn.send((task.id, task.fn, task.args))
                    except Exception as exc:  # noqa: BLE001 - unpicklable task or a dead pipe
                        if isinstance(exc, (BrokenPipeError, OSError)):
                            self._queue.appendleft(task)
                            w.lost = True
                            break
                        self._settle(task, exc)
                        continue
                    task.tries += 1
                    task.started = time.monotonic()
                    task.cpu0 = _cpu_seconds(w.proc.pid)
                    w.task = task

    def _receive(self, w: _Worker) -> None:
        try:
            task_id, ok, value = w.conn.recv()
        except (EOFError, OSError):
            w.lost = True
            return
        except Exception as exc:  # noqa: BLE001 - a reply that cannot be unpickled
            task_id, ok = (w.task.id if w.task else -1), False
            what = describe(w.task.fn, w.task.args) if w.task else "a task"
            value = ProcessingError(
                f"the reply of {what} could not be read ({type(exc).__name__}: {exc})"
            )
        if task_id is None:  # the worker's start-up is done
            w.ready = True
            return
        task = w.task
        if task is None or task.id != task_id:
            return
        w.task = None
        if ok:
            self._settle(task, None, value)
        else:
            self._settle(task, value)

    def _settle(self, task: _Task, exc: BaseException | None, value: Any = None) -> None:
        with self._lock:
            self._tasks.pop(task.future, None)
        if task.future.done():
            return
        if exc is None:
            task.future.set_result(value)
        else:
            task.future.set_exception(exc)

    def _lost(self, w: _Worker) -> None:
        """Replace a dead worker; its task is tried again once, or fails naming it."""
        if w in self._workers:
            self._workers.remove(w)
        with contextlib.suppress(Exception):
            w.proc.join(0.1)
        code = w.proc.exitcode
        self._forget(w)
        task = w.task
        if task is not None:
            if task.kill is not None:
                self._settle(task, task.kill)
            elif task.tries <= self.retries and not self._closing:
                log.warning(
                    "worker %s died (exit %s) in %s; trying it again",
                    w.proc.pid,
                    code,
                    describe(task.fn, task.args),
                )
                with self._lock:
                    self._queue.appendleft(task)
            else:
                how = (
                    f"signal {signal.Signals(-code).name}"
                    if code and code < 0
                    else f"exit code {code}"
                )
                lost = WorkerLost(
                    f"the worker running {describe(task.fn, task.args)} died ({how}) "
                    f"{task.tries} time(s); the input may be corrupt or too large for the memory limit"
                )
                lost.exitcode = code
                self._settle(task, lost)
        if not self._closing:
            self.replaced += 1
            self._workers.append(self._start(self._spawn_ctx))

    def _forget(self, w: _Worker) -> None:
        with contextlib.suppress(Exception):
            w.conn.close()
        if self.pid_dir is not None and w.proc.pid:
            with contextlib.suppress(OSError):
                (Path(self.pid_dir) / str(w.proc.pid)).unlink()

    def _police(self) -> None:
        """Kill workers whose task was dismissed, ran out of time or grew past the memory limit."""
        now = time.monotonic()
        for w in list(self._workers):
            task = w.task
            if task is None:
                continue
            # The limit is CPU time, so a busy machine does not fail honest tasks;
            # a task that waits instead of computing is stopped at WALL_FACTOR times it.
            if task.kill is None and task.timeout is not None:
                cpu = _cpu_seconds(w.proc.pid) - task.cpu0
                wall = now - task.started
                if cpu > task.timeout or wall > WALL_FACTOR * task.timeout:
                    late = TaskTimeout(
                        f"{describe(task.fn, task.args)} ran longer than its limit of "
                        f"{task.timeout:.0f} s of CPU ({WALL_FACTOR * task.timeout:.0f} s "
                        f"in all) and was stopped after {cpu:.0f} s of CPU, {wall:.0f} s in all"
                    )
                    late.limit, late.cpu, late.wall = task.timeout, cpu, wall
                    task.kill = late
            if task.kill is None:
                rss = _rss(w.proc.pid)
                self.peak_rss = max(self.peak_rss, rss)
                if self.memory_limit is not None and rss > self.memory_limit:
                    task.kill = TaskOutOfMemory(
                        f"{describe(task.fn, task.args)} needed more than the worker memory limit "
                        f"of {self.memory_limit / 2**30:.1f} GiB and was stopped; the input may be "
                        "corrupt, or the limit (TERRASIFT_WORKER_MEMORY) too low"
                    )
            if task.kill is not None:
                with contextlib.suppress(OSError):
                    os.kill(w.proc.pid, signal.SIGKILL)

    def _stop_workers(self) -> None:
        killing = self._kill_by is not None
        for w in self._workers:
            with contextlib.suppress(Exception):
                if killing and w.proc.pid:
                    os.kill(w.proc.pid, signal.SIGKILL)
                else:
                    w.conn.send(None)
        deadline = time.monotonic() + (KILL_WAIT if killing else 5.0)
        for w in self._workers:
            w.proc.join(max(0.0, deadline - time.monotonic()))
        deadline = time.monotonic() + 1.0
        for w in self._workers:
            if w.proc.is_alive():
                with contextlib.suppress(Exception):
                    w.proc.kill()
                w.proc.join(max(0.0, deadline - time.monotonic()))
            self._forget(w)
        self._workers = []


def _cpu_seconds(pid: int | None) -> float:
    """User and system CPU seconds of ``pid`` so far (0 when unknown)."""
    if not pid:
        return 0.0
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / _TICKS
    except (OSError, IndexError, ValueError):
        return 0.0


def _rss(pid: int | None) -> int:
    """Resident bytes of ``pid`` (0 when unknown)."""
    if not pid:
        return 0
    try:
        return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * _PAGE
    except (OSError, IndexError, ValueError):
        return 0
