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

Processes of others beside nodes bound to cores of their own (``scene.cpu_binding``, as
``vastray render --nodes`` binds local nodes) are no fair sharer of every core: the
operating system can move only them, and it seldom does. A core idle for moments does not
pull a task (that would cost more than the moment); an idle one is handed work at a busy
core's next tick (4 ms at this kernel's 250 Hz), and busy cores swap work every few hundred
ms. So a busy process of others sits on one node's core, halving it, and moves when another
node has waited a tick or after a long stay. Beside one busy process, the one on two bound
nodes' cores stayed 230-520 ms while ``image``'s nodes traced side by side, and 14-20 ms
under ``dynamic``'s rounds (9 ms each), whose node beside it is each round's last:
``dynamic`` ran 1.8-2.2x slower beside it, ``image`` 1.4-1.45x (rm 128³ and the
turbine-blade scan, 2026-12-07; ``bench/hog_placement.py``). Charged the fair share, a
validation under-predicted the first by 32-37 % and over-predicted the second by 10-25 %.
``bound_nodes`` charges them so: the others' whole busy processes (``others`` rounded) fill
the cores no node is bound to, then each sits on one node's core, whose jobs run at 1 / (1 +
those on it) of a core there (times its block's width); a node's core idle for
``IDLE_PULL_S`` with none on it takes one from a busy node's core, and one that sat
``BUSY_MOVE_S`` on a busy node's core moves to a busy node's core with fewer. Every process
is also as fast as the machine's aggregate throughput of its busy processes and all the
others over the cores allows, and a fractional remainder of ``others`` shares the cores
fairly."""

from __future__ import annotations

import asyncio
import itertools

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
    bound_nodes : the nodes bound to cores of their own, as (count, cores each): owners 0 ..
        count - 1 are those nodes; None: none is bound (the module docstring).
    """

    #: How long a bound node's core stays idle before it takes a busy process of others
    #: from another node's core (the module docstring).
    IDLE_PULL_S = 0.004
    #: How long a busy process of others stays on a busy node's core before the operating
    #: system moves it to a busy node's core with fewer (the module docstring).
    BUSY_MOVE_S = 0.3

    def __init__(self, cores: int, throughput: tuple[float, ...] = (), others: float = 0.0,
                 bound_nodes: tuple[int, int] | None = None):
        self.cores, self.throughput, self.others = cores, throughput, others
        self.bound_nodes = bound_nodes
        #: where each whole busy process of others sits beside bound nodes: a node's rank,
        #: on its core(s); those on cores no node is bound to are not listed
        self._sitting: list[int] = []
        if bound_nodes is not None:
            count, width = bound_nodes
            if count < 1 or width < 1 or count * width > cores:
                raise ValueError(f"{count} nodes of {width} cores each do not fit {cores} cores")
            placed = max(int(round(others)) - (cores - count * width), 0)
            # at first on the last nodes' cores: deterministic, and moved as cores fall idle
            self._sitting = [count - 1 - i % count for i in range(placed)]
        #: when each of ``_sitting`` came to sit where it is (the loop's time)
        self._sat_since: list[float] = []
        #: each bound node whose core is idle -> since when (the loop's time)
        self._idle_since: dict[int, float] = {}
        self._pull: asyncio.TimerHandle | None = None
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
        if self.bound_nodes is not None:
            # the others' whole processes take what ``_beside`` says; a remainder shares
            # fairly, and all of them slow the machine's aggregate throughput
            remainder = max(self.others - round(self.others), 0.0)
            return min(1.0, aggregate_throughput(self.throughput, self.cores, busy)
                       / (k + remainder))
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
        self._move_others()
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
        return ((self.speed(len(self._owned)) * self._beside(owner) + self._bonus.get(owner, 0.0))
                / self._owned[owner])

    def _beside(self, owner) -> float:
        """The share of its cores a bound node keeps beside the others sitting there (1 for
        anything else)."""
        if not self._sitting:
            return 1.0
        width = self.bound_nodes[1]
        return min(1.0, width / (1 + self._sitting.count(owner)))

    def _move_others(self) -> None:
        """The operating system's balancing beside bound nodes, at each change and on its
        timer: a node's core idle for ``IDLE_PULL_S`` with none of the others on it takes
        one from a busy node's core (the most crowded; idle cores in the order they fell
        idle), and one that has sat ``BUSY_MOVE_S`` on a busy node's core moves to a busy
        node's core with fewer of them. The timer is set for the next such moment."""
        if not self._sitting:
            return
        loop = asyncio.get_running_loop()
        now = loop.time()
        count = self.bound_nodes[0]
        for rank in range(count):  # note when each node's core fell idle or woke
            if rank in self._owned:
                self._idle_since.pop(rank, None)
            else:
                self._idle_since.setdefault(rank, now)
        self._sat_since += [now] * (len(self._sitting) - len(self._sat_since))
        later = []
        for since, rank in sorted((since, rank) for rank, since in self._idle_since.items()
                                  if rank not in self._sitting):
            crowded = [r for r in set(self._sitting) if r in self._owned]
            if not crowded:
                break
            if since + self.IDLE_PULL_S > now + 1e-12:
                later.append(since + self.IDLE_PULL_S)
                continue
            source = max(crowded, key=lambda r: (self._sitting.count(r), -r))
            self._move(self._sitting.index(source), rank, now)
        for other in range(len(self._sitting)):
            fewer = self._fewer(other)
            if fewer is not None and self._sat_since[other] + self.BUSY_MOVE_S <= now + 1e-12:
                self._move(other, fewer, now)
        later += [self._sat_since[other] + self.BUSY_MOVE_S
                  for other in range(len(self._sitting)) if self._fewer(other) is not None]
        if self._pull is not None:
            self._pull.cancel()
            self._pull = None
        if later:
            self._pull = loop.call_at(min(later), self._pull_now, loop)

    def _fewer(self, other: int) -> int | None:
        """The busy node's core with the fewest of the others, where process ``other`` sits
        on a busy node's core with more; else None."""
        rank = self._sitting[other]
        busy = [r for r in range(self.bound_nodes[0]) if r in self._owned]
        if rank not in self._owned or not busy:
            return None
        fewest = min(busy, key=lambda r: (self._sitting.count(r), r))
        return fewest if self._sitting.count(fewest) < self._sitting.count(rank) else None

    def _move(self, other: int, rank: int, now: float) -> None:
        """Process of others number ``other`` moves to node ``rank``'s core now."""
        self._sitting[other] = rank
        self._sat_since[other] = now

    def _pull_now(self, loop) -> None:
        """The pull timer: charge the time so far at the old rates, move, re-rate (a move
        changes no process's width, so the spare cores' shares stand)."""
        self._pull = None
        self._advance(loop.time())
        self._move_others()
        self._schedule(loop)

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
        self._move_others()
        self._schedule(loop)
