"""Cores shared by several virtual nodes, as an operating system shares them: processor
sharing, every busy process running at once at the same speed, and the machine's measured
aggregate throughput with k busy processes (``CostModel.throughput``: 2 cores here give 1.3 to
1.5 cores' work with 2 to 4 busy processes, not 2).

A node process computes on one core at a time however many of its threads have work (its
render worker, its loader and its event loop take turns holding Python's GIL): its jobs share
that one process's speed. Measured on a real node (``domain``, rm 128³, one node on 2 cores):
each of 354 extra loads added 2.3 ms to its busy span, more than the load's 1.2 ms alone, so
a node's loads do not run beside its traces on the idle second core."""

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
        #: id -> [work left (s at full speed), future, owner]
        self._jobs: dict[int, list] = {}
        self._owned: dict = {}  # owner -> its jobs running now
        self._ids = itertools.count()
        self._last = 0.0
        self._timer: asyncio.TimerHandle | None = None

    def speed(self, k: int) -> float:
        """Each job's speed (1: a process alone on a core) with ``k`` jobs running."""
        total = (self.throughput[min(k, len(self.throughput)) - 1] if self.throughput
                 else min(k, self.cores))
        return min(1.0, total / k)

    async def run(self, seconds: float, owner=None) -> None:
        """Work ``seconds`` (at full speed) among the other jobs. ``owner``: the process the
        job is part of; its jobs share one process's speed (None: a process of its own)."""
        await self.start(seconds, owner)

    def start(self, seconds: float, owner=None) -> asyncio.Future:
        """``run``'s job started now; the future is done when it has worked ``seconds``."""
        loop = asyncio.get_running_loop()
        self._advance(loop.time())
        done = loop.create_future()
        key = next(self._ids)
        owner = ("job", key) if owner is None else owner
        self._jobs[key] = [seconds, done, owner]
        self._owned[owner] = self._owned.get(owner, 0) + 1
        self._schedule(loop)
        return done

    def _rate(self, job: list) -> float:
        """A running job's speed now: its process's share of the machine, split among the
        process's running jobs."""
        return self.speed(len(self._owned)) / self._owned[job[2]]

    def _advance(self, now: float) -> None:
        """Charge the time since the last event to every running job."""
        if self._jobs:
            elapsed = now - self._last
            for job in self._jobs.values():
                job[0] -= elapsed * self._rate(job)
        self._last = now

    def _schedule(self, loop) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._jobs:
            first = min(max(job[0], 0.0) / self._rate(job) for job in self._jobs.values())
            self._timer = loop.call_later(first, self._finish, loop)

    def _finish(self, loop) -> None:
        self._timer = None
        self._advance(loop.time())
        least = min(job[0] for job in self._jobs.values())
        for key in [k for k, job in self._jobs.items() if job[0] <= max(least, 0.0) + 1e-12]:
            seconds, done, owner = self._jobs.pop(key)
            self._owned[owner] -= 1
            if not self._owned[owner]:
                del self._owned[owner]
            done.set_result(None)
        self._schedule(loop)
