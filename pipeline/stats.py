"""The figures of a pipeline's run: per stage, per queue, as a snapshot while it runs,
and in all at its end. The same in the thread runtime and in processes (a worker sends
its figures as JSON, :meth:`StageStats.to_json`, and the main process rebuilds them)."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any


@dataclass
class QueueStats:
    name: str
    capacity: int
    policy: str
    puts: int = 0
    dropped: int = 0
    max_fill: int = 0
    fill_sum: int = 0

    @property
    def mean_fill(self) -> float:
        return self.fill_sum / self.puts if self.puts else 0.0

    def to_json(self) -> dict[str, Any]:
        """The figures as JSON (``QueueStats(**d)`` rebuilds them: a worker's report)."""
        return dataclasses.asdict(self)


@dataclass
class StageStats:
    name: str
    unit: str = "frames"
    items_in: int = 0
    items_out: int = 0
    frames: int = 0  # input items handled (frames for most stages; see ``unit``)
    busy_s: float = 0.0  # wall time inside the stage's own code
    cpu_s: float = 0.0  # CPU time of the stage's thread inside its own code

    @property
    def frames_per_s(self) -> float:
        """Items handled per second of this stage's own busy time."""
        return self.frames / self.busy_s if self.busy_s > 0 else 0.0

    def to_json(self) -> dict[str, Any]:
        """The figures as JSON (``StageStats(**d)`` rebuilds them: a worker's report)."""
        return dataclasses.asdict(self)


@dataclass(frozen=True, slots=True)
class StatsSnapshot:
    """The pipeline's statistics at ``elapsed_s``, sent to sinks with ``wants_stats``."""

    elapsed_s: float
    stages: tuple[StageStats, ...]
    queues: tuple[QueueStats, ...]


def stats_snapshot(elapsed_s: float, stages: Iterable[StageStats],
                   queues: Iterable[QueueStats]) -> StatsSnapshot:
    """A copy of the figures as they are now (the stages go on counting in theirs)."""
    return StatsSnapshot(elapsed_s, tuple(copy.copy(s) for s in stages),
                         tuple(copy.copy(q) for q in queues))


@dataclass
class PipelineResult:
    wall_s: float
    stages: list[StageStats]
    queues: list[QueueStats]
    extras: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: names of the sinks (their stats and queues come last in ``stages`` and ``queues``)
    sinks: tuple[str, ...] = ()

    @property
    def dropped(self) -> int:
        """Items dropped between the main stages (a sink's own drops are not frames lost)."""
        return sum(q.dropped for q in self.queues
                   if q.name.rsplit("->", 1)[-1] not in self.sinks)
