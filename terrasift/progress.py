"""Job progress as work done: points × measured stage cost, not tasks counted.

Every task of a job is registered up front with its work, the seconds one
worker needs for it: its points times the cost per million points of its kind
(``COST``, CPU seconds measured by ``benchmarks/progress_trace.py``). The
percentage is work done over all work, so a 4-minute mosaic weighs what it
costs and a tiny block what it costs. Between completions the meter moves on at
the rate observed so far (never past 90 % of the current stage's outstanding
work), so long tasks do not freeze the bar; it never goes back.

Blocks are known only after sharding: the block stage is reserved as the
job's points times the block cost, and split over the blocks by their shard
sizes when they are known, so the total does not change.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

#: CPU seconds of one worker per million job points, per kind of task: medians of 3 runs
#: of ``make bench-progress`` (``costs``) on a 1.0 M point scene, 100 m blocks, 0.5 m cells
COST: dict[str, float] = {
    "shard": 0.80,
    "block": 5.06,
    "classified": 0.59,
    "raster": 0.076,  # per raster
    "slope": 0.128,
    "categories": 0.175,
    "quicklooks": 0.1,
    "report": 0.008,
}

STAGES = {
    "shard": "reading tiles into blocks",
    "blocks": "classifying blocks",
    "finish": "writing outputs",
    "report": "writing the report",
}

#: what a progress callback receives: work done and total (ms of one worker), and details
Emit = Callable[[int, int, Mapping[str, Any]], None]


@dataclass
class _Stage:
    work: float = 0.0
    reserved: float = 0.0
    done_work: float = 0.0
    items: int = 0
    done_items: int = 0
    points: float = 0.0
    done_points: float = 0.0
    pending: dict[Any, tuple[float, float]] = field(default_factory=dict)  # key -> (work, points)


class JobProgress:
    """Work of a job's tasks, what is done, and the percentage to report."""

    def __init__(
        self,
        emit: Emit,
        points: int,
        workers: int = 1,
        warnings: list[str] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self._emit, self.points, self.workers = emit, max(int(points), 1), max(workers, 1)
        self.warnings = list(warnings or [])
        self._clock = clock
        self._stages: dict[str, _Stage] = {name: _Stage() for name in STAGES}
        self.stage = "shard"
        self._start = clock()
        self._last_done_at = self._start
        self._done_at_start = 0.0
        self._reported = -1.0
        self._last: tuple[int, str] | None = None

    # -- registering work -------------------------------------------------

    def add(self, stage: str, key: Any, kind: str, points: float, done: bool = False) -> None:
        """A task of ``stage`` worth ``COST[kind]`` per million ``points``; ``done`` when already done."""
        s = self._stages[stage]
        work = COST[kind] * points / 1e6
        s.work += work
        s.items += 1
        s.points += points
        if done:
            s.done_work += work
            s.done_items += 1
            s.done_points += points
            self._done_at_start += work
        else:
            s.pending[key] = (work, points)

    def reserve(self, stage: str, kind: str) -> None:
        """Count ``stage`` in the total now as the job's points at ``COST[kind]``; ``split`` shares it out later."""
        self._stages[stage].reserved = COST[kind] * self.points / 1e6

    def split(self, stage: str, shares: Mapping[Any, float], kind: str) -> None:
        """Register ``stage`` as the job's points at ``COST[kind]``, shared by ``shares`` (sizes)."""
        total = sum(shares.values()) or 1.0
        for key, share in shares.items():
            self.add(stage, key, kind, self.points * share / total)
        self._stages[stage].reserved = 0.0  # now in the items (up to rounding)

    # -- reporting --------------------------------------------------------

    def enter(self, stage: str) -> None:
        self.stage = stage
        self.report(force=True)

    def done(self, stage: str, key: Any) -> None:
        s = self._stages[stage]
        work, points = s.pending.pop(key, (0.0, 0.0))
        s.done_work += work
        s.done_items += 1
        s.done_points += points
        self._last_done_at = self._clock()
        self.report()

    @property
    def total(self) -> float:
        return sum(max(s.work, s.reserved) for s in self._stages.values()) or 1.0

    @property
    def done_work(self) -> float:
        return sum(s.done_work for s in self._stages.values())

    def estimate(self) -> float:
        """Work done plus what the current stage's running tasks have likely done since the
        last completion, at the rate measured so far (one worker's rate before anything is
        done), never more than 90 % of the stage's outstanding work."""
        now = self._clock()
        measured = self.done_work - self._done_at_start
        elapsed = self._last_done_at - self._start  # the rate up to the last completion
        rate = measured / elapsed if measured > 0.01 * self.total and elapsed > 0 else 1.0
        stage = self._stages[self.stage]
        outstanding = max(stage.work, stage.reserved) - stage.done_work
        credit = min(rate * (now - self._last_done_at), 0.9 * outstanding)
        return self.done_work + max(credit, 0.0)

    @property
    def finished(self) -> bool:
        return not any(s.pending or s.reserved for s in self._stages.values())

    def percent(self) -> float:
        """Monotonic percentage, 0-100; exactly 100 once every registered task is done."""
        pct = 100.0 if self.finished else min(100.0, 100.0 * self.estimate() / self.total)
        self._reported = max(self._reported, pct)
        return self._reported

    def message(self) -> str:
        s = self._stages[self.stage]
        label = STAGES[self.stage]
        if self.stage in ("shard", "blocks"):
            unit = "parts" if self.stage == "shard" else "blocks"
            return (
                f"{label}: {s.done_items} of {s.items} {unit}, "
                f"{_points(s.done_points, self.points)} points"
            )
        if self.stage == "finish":
            return f"{label}: {s.done_items} of {s.items} done"
        return label

    def report(self, force: bool = False) -> None:
        """Call back when the integer percentage or the message changed."""
        pct = self.percent()
        msg = self.message()
        state = (int(pct), msg)
        if not force and state == self._last:
            return
        self._last = state
        self._emit(
            int(round(pct * 100)),
            10_000,
            {"stage": self.stage, "message": msg, "warnings": list(self.warnings)},
        )


def _points(done: float, total: float) -> str:
    """``"1.25 of 3.40 M"`` for millions, ``"1,250 of 3,400"`` below."""
    if total >= 1e6:
        return f"{done / 1e6:.2f} of {total / 1e6:.2f} M"
    return f"{round(done):,} of {round(total):,}"
