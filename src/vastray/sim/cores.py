"""Cores shared by several virtual nodes, as an operating system shares them: processor
sharing, every busy process running at once at the same speed, and the machine's measured
aggregate throughput with k busy processes (``CostModel.throughput``: 2 cores here give 1.3 to
1.5 cores' work with 2 to 4 busy processes, not 2).

A node process computes on one core at a time however many of its threads have work (its
render worker, its loader and its event loop take turns holding Python's GIL): its jobs share
that one process's speed. Measured on a real node (``domain``, rm 128³, one node on 2 cores):
each of 354 extra loads added 2.3 ms to its busy span, more than the load's 1.2 ms alone, so
a node's loads do not run beside its traces on the idle second core.

One job alone in its process may be wider than a core: an Embree BVH build runs on Embree's
threads too (a domain of the out-of-core benchmark's store builds on 1.7-1.8 cores here). A
job's ``width`` is the cores it would keep busy alone; where the machine has cores no other
process is using (fewer busy processes than cores), a process whose one running job is wider
than a core gets a share of them, up to that width. With every core taken nothing changes.
Lone real nodes used 1.09-1.38 cores over their busy spans (``bench/simulate.py``'s
validation, 2026-12-01), and the simulator had charged them one: its 1-node rows were
over-predicted by up to 29 %. A process's other jobs beside such a job still take turns on
one core: letting them share its width made the scan's lone ``domain``, ``async`` and
``temporal`` rows 12-15 % too fast.

Processes of others beside nodes bound to their own cores (``scene.cpu_binding``, as
``vastray render --nodes`` binds local nodes) are not a fair sharer of every core: the
operating system can move only them, so each runs on a core no node is using while there is
one, and otherwise pairs up with a node on that node's core, taking half of it. Beside one
busy process, two bound nodes on 2 cores each got 0.77-0.82 of a core's work over 3-100 ms
bursts (unbound: 0.66-0.71, the fair two thirds; 2026-12-07), and a validation that charged
bound nodes the fair share over-predicted their 2-node runs by 9-41 %. ``bound`` charges
them so: with k busy processes of ours on C >= k cores and h others, the others first fill
the C - k idle cores, the rest pair up with ours as evenly as whole processes can (a
fractional h in proportion), and every running process is as fast as the machine's
aggregate throughput of k + h busy processes spread over the cores in use allows."""

from __future__ import annotations

import asyncio
import itertools
import math

from vastray.sim.costs import aggregate_throughput


class SharedCores:
    """Processor sharing over ``cores`` cores.

    Parameters
    ----------
    cores : the cores.
    throughput : (K,) aggregate throughput, in single-process speeds, with 1..K busy jobs
        (empty: ideal, ``min(k, cores)``); beyond K, the last value.
    others : busy processes that are not the simulated nodes' (``CostModel.others``): always
        running beside them, taking their share of the cores as the operating system gives
        it (k jobs of the nodes run as k of k + ``others`` busy processes).
    bound : whether the nodes are bound to cores of their own, so that the others take the
        idle cores first and then half of a node's core each (``paired_share``; the module
        docstring), not a fair share of all of them.
    """

    def __init__(self, cores: int, throughput: tuple[float, ...] = (), others: float = 0.0,
                 bound: bool = False):
        self.cores, self.throughput, self.others = cores, throughput, others
        self.bound = bound
        #: id -> [work left (s at full speed), future, owner, width]
        self._jobs: dict[int, list] = {}
        self._owned: dict = {}  # owner -> its jobs running now
        #: owner -> the width of its one running job, for processes whose one job is wider
        #: than a core (several jobs of a process share one core: no entry)
        self._wide: dict = {}
        self._bonus: dict = {}  # owner -> speed beyond the equal share (``_share``)
        self._ids = itertools.count()
        self._last = 0.0
        self._timer: asyncio.TimerHandle | None = None

    def speed(self, k: int) -> float:
        """Each job's speed (1: a process alone on a core) with ``k`` jobs running (beside
        ``others``)."""
        busy = k + self.others
        if self.bound and self.others > 0.0 and 0 < k <= self.cores:
            per_core = aggregate_throughput(self.throughput, self.cores, busy) / min(busy, self.cores)
            excess = max(self.others - (self.cores - k), 0.0)
            return min(1.0, per_core * paired_share(excess, k))
        return min(1.0, aggregate_throughput(self.throughput, self.cores, busy) / busy)

    async def run(self, seconds: float, owner=None, width: float = 1.0) -> None:
        """Work ``seconds`` (at full speed on one core) among the other jobs. ``owner``: the
        process the job is part of; its jobs share one process's speed (None: a process of
        its own). ``width``: the cores the job keeps busy alone (>= 1; see the module
        docstring)."""
        await self.start(seconds, owner, width)

    def start(self, seconds: float, owner=None, width: float = 1.0) -> asyncio.Future:
        """``run``'s job started now; the future is done when it has worked ``seconds``."""
        if not width >= 1.0:
            raise ValueError(f"a job's width is at least one core, got {width!r}")
        loop = asyncio.get_running_loop()
        self._advance(loop.time())
        done = loop.create_future()
        key = next(self._ids)
        owner = ("job", key) if owner is None else owner
        self._jobs[key] = [seconds, done, owner, float(width)]
        self._owned[owner] = self._owned.get(owner, 0) + 1
        self._widen(owner)
        self._schedule(loop)
        return done

    def _widen(self, owner) -> None:
        """Note ``owner``'s width (its one running job's, where wider than a core) and share
        the spare cores afresh."""
        self._wide.pop(owner, None)
        if self._owned.get(owner, 0) == 1:
            width = next(job[3] for job in self._jobs.values() if job[2] == owner)
            if width > 1.0:
                self._wide[owner] = width
        self._bonus = self._share()

    def _share(self) -> dict:
        """What each wide process gets beyond the equal share ``speed(busy)``: the cores no
        process is using (fewer busy processes than cores), shared among the processes whose
        one job is wider than a core, each up to its width (water-filling)."""
        busy = len(self._owned)
        if not self._wide or busy + self.others >= self.cores:
            return {}
        base = self.speed(busy)
        room = {owner: width - base for owner, width in self._wide.items() if width > base}
        bonus = dict.fromkeys(room, 0.0)
        spare = (self.cores - busy - self.others) * base
        while spare > 1e-12 and room:
            grant = min(spare / len(room), min(room.values()))
            for owner in room:
                bonus[owner] += grant
                room[owner] -= grant
            spare -= grant * len(room)
            room = {owner: left for owner, left in room.items() if left > 1e-12}
        return bonus

    def _rate(self, job: list) -> float:
        """A running job's speed now: its process's share of the machine, split among the
        process's running jobs."""
        owner = job[2]
        return (self.speed(len(self._owned)) + self._bonus.get(owner, 0.0)) / self._owned[owner]

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
            seconds, done, owner, _ = self._jobs.pop(key)
            self._owned[owner] -= 1
            if not self._owned[owner]:
                del self._owned[owner]
            self._widen(owner)
            done.set_result(None)
        self._schedule(loop)


def paired_share(others: float, cores: int) -> float:
    """The mean share of its core a process bound to each of ``cores`` cores keeps beside
    ``others`` (>= 0, may be fractional) busy processes that the operating system spreads
    over those cores as evenly as whole processes go: a core with n of them gives ours
    1 / (n + 1); a fractional count in proportion between the two whole counts around it.

    >>> paired_share(1, 2)  # one on one of two cores: 1/2 there, 1 on the other
    0.75
    """
    if cores < 1:
        raise ValueError(f"a share needs at least one core, got {cores!r}")

    def whole(count: int) -> float:
        each, extra = divmod(count, cores)
        return (extra / (each + 2) + (cores - extra) / (each + 1)) / cores

    low = math.floor(others)
    part = others - low
    return (1.0 - part) * whole(low) + (part * whole(low + 1) if part else 0.0)
