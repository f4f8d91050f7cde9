"""Cores shared by several virtual nodes, as an operating system shares them: processor
sharing, every job running at once at the same speed, and the machine's measured aggregate
throughput with k busy processes (``CostModel.throughput``: 2 cores here give 1.3 to 1.5 cores'
work with 2 to 4 busy processes, not 2)."""

from __future__ import annotations

import asyncio
import itertools


class SharedCores:
    """Processor sharing over ``cores`` cores.

    Parameters
    ----------
    cores : the cores.
    throughput : (K,) aggregate throughput, in single-process speeds, with 1..K busy jobs
        (empty: ideal, ``min(k, cores)``); beyond K, the last value.
    """

    def __init__(self, cores: int, throughput: tuple[float, ...] = ()):
        self.cores, self.throughput = cores, throughput
        self._jobs: dict[int, list] = {}  # id -> [work left (s at full speed), future]
        self._ids = itertools.count()
        self._last = 0.0
        self._timer: asyncio.TimerHandle | None = None

    def speed(self, k: int) -> float:
        """Each job's speed (1: a process alone on a core) with ``k`` jobs running."""
        total = (self.throughput[min(k, len(self.throughput)) - 1] if self.throughput
                 else min(k, self.cores))
        return min(1.0, total / k)

    async def run(self, seconds: float) -> None:
        """Work ``seconds`` (at full speed) among the other jobs."""
        loop = asyncio.get_running_loop()
        self._advance(loop.time())
        done = loop.create_future()
        self._jobs[next(self._ids)] = [seconds, done]
        self._schedule(loop)
        await done

    def _advance(self, now: float) -> None:
        """Charge the time since the last event to every running job."""
        if self._jobs:
            worked = (now - self._last) * self.speed(len(self._jobs))
            for job in self._jobs.values():
                job[0] -= worked
        self._last = now

    def _schedule(self, loop) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._jobs:
            first = min(job[0] for job in self._jobs.values())
            self._timer = loop.call_later(max(first, 0.0) / self.speed(len(self._jobs)),
                                          self._finish, loop)

    def _finish(self, loop) -> None:
        self._timer = None
        self._advance(loop.time())
        least = min(job[0] for job in self._jobs.values())
        for key in [k for k, job in self._jobs.items() if job[0] <= max(least, 0.0) + 1e-12]:
            self._jobs.pop(key)[1].set_result(None)
        self._schedule(loop)
