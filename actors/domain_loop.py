"""The domain-activation loop every scheduler drives: choose a domain, get it from the
preloader, start loading the schedule's guess at the next one, trace the rays waiting for the
chosen one, time that, and ship what it sent on.

Which domain comes next is the schedule's decision (an object of ``schedule/``, behind a
``DomainOrder``); how a domain is fetched, traced and timed is decided here, once, so every
runtime (one process out of core, the domain-decomposition nodes, the asynchronous and
temporal frames, the in-situ nodes) reports the same spans under the same names:

- ``schedule_s`` (here): time the schedule spent deciding (``next_domain``, which for
  spec-ooc filters the domain's queues, and ``likely_next``); the simulator charges the CPU
  time those calls take as it runs them (``decided``, ``CostModel.decision_scale``);
- ``load_wait_s`` (the preloader's counter): time a render worker waited for a domain's load,
  what preloading did not hide;
- ``trace_s`` (here): time spent tracing and shading the rays of activated domains, nothing
  else (no decision, no load, no send);
- ``handed_off`` (here): activations traced on a worker thread (a node runtime's larger ones,
  ``hands_off``), each paying the hand-off there and back;
- ``bookkeeping_cpu_s`` (``bookkeeping``): CPU a node spends moving rays between its
  queues and its messages outside any trace or decision (a received batch delivered to its
  queues, a round's rays taken out of them for its peers); the simulator charges it as it
  charges decisions.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from vastray.actors.preloader import DomainPreloader
from vastray.scene.embree.launch import cpu_time


@dataclass(frozen=True)
class Queries:
    """The ray queries a trace made: closest-hit queries of radiance rays and occlusion
    queries of shadow rays (they cost differently: the simulator charges each its own).
    Adds up with ``+``; ``int()`` is the total."""

    radiance: int = 0
    shadow: int = 0

    def __int__(self) -> int:
        return self.radiance + self.shadow

    def __bool__(self) -> bool:
        return bool(self.radiance or self.shadow)

    def __add__(self, other: Queries) -> Queries:
        return Queries(self.radiance + other.radiance, self.shadow + other.shadow)



class DomainOrder(Protocol):
    """What the loop needs of a schedule: its next domain, its guess at the one after, and
    how to trace a domain's rays."""

    def next_domain(self) -> int | None:
        """The domain to activate now; None when no ray waits."""

    def likely_next(self, current: int) -> int | None:
        """The domain to load while ``current`` is traced (asked after ``current`` is in
        memory, so that a cache-aware guess sees it resident); None: nothing."""

    def trace(self, domain: int, bvh) -> Queries:
        """Trace every ray waiting for ``domain`` against its loaded ``bvh``; returns the ray
        queries that made (none: the activation traced nothing)."""

    # Optional: ``rays(domain) -> int | None``, the rays that trace would take (radiance and
    # shadow rays waiting for it); an order without it, or answering None, is always handed
    # to a worker thread.


#: Most rays an activation of a node runtime traces on the event loop's own thread. Handing a
#: trace to a worker thread and back costs 0.1-0.25 ms on a 2-core machine (``asyncio.to_thread``
#: on uvloop; the simulator's ``offload_s``), as much as tracing about a hundred rays: a
#: node's many small activations (a few hundred rays each at 128 domains and 3 bounces) paid
#: it thousands of times. Up to this many rays a trace takes a few milliseconds, a delay the
#: event loop's heartbeats and deliveries do not notice; longer ones still leave the loop free.
INLINE_RAYS = 1024


def hands_off(order: DomainOrder, domain: int) -> bool:
    """Whether a node runtime's loop (``offload``) traces ``domain`` on a worker thread: when
    the order does not say how many rays it will trace, or they are more than
    ``INLINE_RAYS``."""
    rays = getattr(order, "rays", None)
    count = None if rays is None else rays(domain)
    return count is None or count > INLINE_RAYS


@dataclass(frozen=True)
class Activation:
    """One turn of the loop."""

    domain: int
    load_count: int  # times the domain had been loaded when it was traced (preloads included)
    schedule_s: float  # the schedule choosing it and guessing the next
    wait_s: float  # waiting for the domain (its load, or a preload in flight)
    trace_s: float  # tracing and shading its rays
    queries: int  # ray queries made


@contextmanager
def counted_bookkeeping(stats: dict, charge: Callable[[float], None]) -> Iterator[None]:
    """Count the calling thread's CPU in the enclosed code (which must not await: the event
    loop's other tasks would count too) as ``stats["bookkeeping_cpu_s"]``, and pass it to
    ``charge``, even when the code raises."""
    cpu = cpu_time()
    try:
        yield
    finally:
        spent = cpu_time() - cpu
        stats["bookkeeping_cpu_s"] = stats.get("bookkeeping_cpu_s", 0.0) + spent
        charge(spent)


class DomainLoop:
    """Activates domains in a schedule's order through a node's preloader.

    Parameters
    ----------
    preloader : the node's domain cache with its loading thread.
    stats : the counters of the node's report; ``schedule_s`` and ``trace_s`` are added to.
    offload : trace on a worker thread, so the event loop keeps routing messages meanwhile
        (the nodes), except activations of at most ``INLINE_RAYS`` rays where the order says
        so (``hands_off``); False traces on the calling thread (one process, nothing else to
        serve).
    """

    def __init__(self, preloader: DomainPreloader, stats: dict, offload: bool = True):
        self.preloader, self.stats, self.offload = preloader, stats, offload
        #: the clock spans are measured by (the simulator's loop reads virtual time)
        self.clock = time.perf_counter
        stats.setdefault("schedule_s", 0.0)
        stats.setdefault("trace_s", 0.0)
        #: ray queries traced against each load of a domain while it stayed resident, by
        #: (domain, its load number): how much work a load bought (issue 40's tail loads)
        self.load_queries: dict[tuple[int, int], int] = {}
        # the loads before this loop's (a loop the simulator's tests make may have no cache)
        self._earlier_loads = {} if preloader is None else preloader.loads_per_domain()
        #: every activated domain in order: the access sequence whose optimal load count
        #: (``schedule.belady``) the report gives beside the loads made.
        self.sequence: list[int] = []
        #: CPU seconds of tile starts and bookkeeping not yet charged (the simulator's loop
        #: charges them with its next decision; this loop has nothing to charge)
        self.uncharged_cpu_s = 0.0

    def start_tile(self, policy, rays) -> None:
        """``policy.start(rays)``: queue a tile's camera rays to their first domains (the
        schedule's ray-domain enumeration, about 0.6 µs a path on the turbine-blade scan, 15 ms
        for a node's 24,576 paths), its CPU counted in ``start_cpu_s`` and charged by the
        simulator as a decision. Making the camera rays is not part of it (``camera_ray_s``
        charges that)."""
        cpu = cpu_time()
        policy.start(rays)
        cpu = cpu_time() - cpu
        self.stats["start_cpu_s"] = self.stats.get("start_cpu_s", 0.0) + cpu
        self.uncharged_cpu_s += cpu

    @contextmanager
    def bookkeeping(self) -> Iterator[None]:
        """Count the CPU of the enclosed code in ``bookkeeping_cpu_s``: a node's work on its
        rays outside traces and decisions (delivering a received batch to the schedule's
        queues, taking a round's rays out of them). The simulator runs the same code and
        charges that CPU with the node's next decision. Uncharged, it was missing from the
        simulation: 0.45-0.60 s of 6.0-8.2 s of CPU in real 8-node ``dynamic`` renders of
        rm 128³ (96x72 x 2 spp, 3 bounces, 32 domains cached a node; four runs)."""
        with counted_bookkeeping(self.stats, self._leave_uncharged):
            yield

    def _leave_uncharged(self, cpu_seconds: float) -> None:
        self.uncharged_cpu_s += cpu_seconds

    async def step(self, order: DomainOrder,
                   ship: Callable[[], Awaitable[None]] | None = None) -> Activation | None:
        """Activate ``order``'s next domain and ship what tracing it sent on; None when the
        order has no domain left."""
        clock = self.clock
        start = clock()
        cpu = cpu_time()
        domain = order.next_domain()
        await self.decided(cpu_time() - cpu)
        chosen = clock()
        if domain is None:
            self.stats["schedule_s"] += chosen - start
            return None
        self.sequence.append(domain)
        bvh = await self.preloader.get(domain)
        loaded = clock()
        if self.preloader.enabled:
            cpu = cpu_time()
            guess = order.likely_next(domain)
            next_load = getattr(order, "next_load", None)
            ahead = None if next_load is None else next_load(domain, guess)
            build = guess is None and ahead is not None and self.preloader.builds_ahead
            # building ahead, the reader reads the load after that one meanwhile
            then = next_load(domain, ahead) if build else None
            await self.decided(cpu_time() - cpu)
            if build:
                # no preload the cache can make room for now: build the next load in the
                # slot kept for it (its read too, unless read ahead), evicting nothing until
                # it is taken
                self.preloader.build_ahead(ahead)
                self.preloader.read_ahead(then)
            else:
                self.preloader.preload(guess)
                self.preloader.read_ahead(ahead)
        guessed = clock()
        queries = await self.trace(order, domain, bvh)
        done = clock()
        activation = Activation(domain, self.preloader.load_count(domain),
                                (chosen - start) + (guessed - loaded), loaded - chosen,
                                done - guessed, int(queries))
        self.stats["schedule_s"] += activation.schedule_s
        self.stats["trace_s"] += activation.trace_s
        key = (domain, activation.load_count)
        self.load_queries[key] = self.load_queries.get(key, 0) + int(queries)
        if ship is not None:
            await ship()
        return activation

    @property
    def productive_loads(self) -> set[tuple[int, int]]:
        """(domain, its load number) of the loads followed by at least one ray query."""
        return {key for key, queries in self.load_queries.items() if queries}

    @property
    def traced_domains(self) -> set[int]:
        """The domains any ray was traced against (each must be loaded at least once: the
        floor)."""
        return {domain for (domain, _), queries in self.load_queries.items() if queries}

    def loads_serving_under(self, loads: int, queries: int) -> int:
        """How many of this render's ``loads`` bought fewer than ``queries`` ray queries
        while they stayed resident (loads no ray was traced after included): the tail loads
        whose read and build buy almost nothing (issue 40). A domain still resident from a
        load before this loop began (an earlier pass's) is not counted."""
        earlier = self._earlier_loads
        served = [q for (domain, count), q in self.load_queries.items()
                  if count > earlier.get(domain, 0)]
        return loads - len(served) + sum(1 for q in served if q < queries)

    async def decided(self, cpu_seconds: float) -> None:
        """The schedule spent ``cpu_seconds`` of this thread's CPU deciding (``next_domain``,
        ``likely_next``, a round's plan). Nothing to do here: real time has passed; the
        simulator's loop charges it to the virtual node."""

    async def trace(self, order: DomainOrder, domain: int, bvh) -> Queries:
        """``order.trace(domain, bvh)``, with ``offload`` on a worker thread unless it traces
        few rays (``hands_off``); returns the ray queries made. Its CPU seconds on the thread
        that traces (split pieces included) add to ``trace_cpu_s``: beside ``trace_s``, a
        wall span that also counts the time other threads and processes held the core."""
        if self.offload and hands_off(order, domain):
            self.stats["handed_off"] = self.stats.get("handed_off", 0) + 1
            return await asyncio.to_thread(self._timed_trace, order, domain, bvh)
        return self._timed_trace(order, domain, bvh)

    def _timed_trace(self, order: DomainOrder, domain: int, bvh) -> Queries:
        cpu = cpu_time()
        queries = order.trace(domain, bvh)
        # one addition on the event loop's thread or, offloaded, while that thread awaits
        # this one: never two at once
        self.stats["trace_cpu_s"] = self.stats.get("trace_cpu_s", 0.0) + cpu_time() - cpu
        return queries

    async def run(self, order: DomainOrder,
                  ship: Callable[[], Awaitable[None]] | None = None) -> int:
        """Activate domains until ``order`` has none left; returns how many."""
        count = 0
        while await self.step(order, ship) is not None:
            count += 1
        return count

    async def load_all(self, domains: list[int]) -> dict[int, object]:
        """Every one of ``domains`` in memory, got in turn while the next one loads (in situ:
        a node's data stays loaded); returns them by id."""
        held: dict[int, object] = {}

        def keep(domain: int, bvh) -> Queries:
            held[domain] = bvh
            return Queries()

        await self.run(ListOrder(domains, keep))
        return held


class ScheduleOrder:
    """A tile schedule of ``schedule/`` (``ImageSchedule``, ``SpeculativeSchedule``) as a
    ``DomainOrder``.

    Parameters
    ----------
    policy : the tile's schedule.
    preloader : whose resident domains the schedule may serve first.
    resident_aware : tell the schedule what is resident (its ``resident_first`` rule); False
        hands it an empty set (the ``domain`` nodes' rounds, which own their domains).
    evicting : hand the schedule the cache's next eviction victim (spec-ooc's
        ``serve_before_evict``).
    by_demand : evict the resident domain the schedule will need last (the lowest of
        ``policy.demand()``, asked afresh before each choice and each guess), never the
        chosen domain or the guessed next one; False: the least recently used.
    """

    def __init__(self, policy, preloader: DomainPreloader, resident_aware: bool = True,
                 evicting: bool = False, by_demand: bool = False):
        self.policy, self.preloader = policy, preloader
        self.resident_aware, self.evicting, self.by_demand = resident_aware, evicting, by_demand

    def next_domain(self) -> int | None:
        if self.by_demand:  # before the choice: spec-ooc's serve_before_evict asks the victim
            self.preloader.prioritise(self.policy.demand())
        resident = self.preloader.resident() if self.resident_aware else frozenset()
        if self.evicting:
            domain = self.policy.next_domain(resident, victim=self.preloader.victim,
                                             preloaded=self.preloader.preloaded())
            if domain is not None and domain == getattr(self.policy, "parting", None):
                self.preloader.parting(domain)  # served before it goes: still the victim
        else:
            domain = self.policy.next_domain(resident)
        if self.by_demand and domain is not None:
            self.preloader.prioritise(self.policy.demand(), protect=(domain,))
        return domain

    def likely_next(self, current: int) -> int | None:
        guess = self.policy.likely_next(current)
        if self.by_demand and guess is not None:
            self.preloader.prioritise(self.policy.demand(), protect=(current, guess))
        return guess

    def next_load(self, current: int, guess: int | None) -> int | None:
        """A guess at the next domain that will need a load besides ``guess`` (the preload's):
        its files are read ahead (``DomainPreloader.read_ahead``). The policy's own
        ``next_load`` where it has one (spec-ooc: the next in its round's schedule), else
        the domain of highest ``demand()`` not resident (the image schedule's fullest queue,
        lowest id on ties, which it loads next once no resident domain has rays)."""
        exclude = set(self.preloader.resident()) | {current}
        if guess is not None:
            exclude.add(guess)
        own = getattr(self.policy, "next_load", None)
        if own is not None:
            return own(exclude)
        demand = np.asarray(self.policy.demand(), np.float64).copy()
        demand[list(exclude)] = 0.0
        best = int(np.argmax(demand))
        return best if demand[best] > 0 else None

    def trace(self, domain: int, bvh) -> Queries:
        return traced_queries(self.policy, domain, bvh)

    def rays(self, domain: int) -> int:
        return waiting_rays(self.policy, domain)


class LeadOrder:
    """A leading order whose every activation also traces the rays ``followers`` (tile
    schedules started ahead, ``ImageSchedule`` or ``SpeculativeSchedule``) have waiting for
    its domain: they ride on the leader's loads and choose nothing (passes traced ahead,
    ``SortFirstTiles.render_ahead``). Before the leader loads a domain, the followers' rays
    waiting in ``resident()`` domains are traced, the fullest domain first: they cost no load
    now, and the load may evict their domain. The leader's rays go first in an activation.
    ``before()``, if given, is called before each choice (it may add followers to the list).
    """

    def __init__(self, lead: DomainOrder, followers: list,
                 resident: Callable[[], frozenset[int]] = frozenset,
                 before: Callable[[], None] | None = None):
        self.lead, self.followers, self.resident, self.before = (lead, followers, resident,
                                                                 before)
        self._riding: int | None = None  # a domain activated for the followers alone
        #: ray queries the followers made
        self.ahead_queries = 0
        #: seconds each follower's traces took, by ``id`` of its schedule
        self.follower_seconds: dict[int, float] = {}

    def next_domain(self) -> int | None:
        if self.before is not None:
            self.before()  # may add followers
        domain = self.lead.next_domain()
        self._riding = None
        if domain is None or not self.followers:
            return domain
        resident = self.resident()
        if domain in resident:
            return domain
        waiting = {d: sum(waiting_rays(policy, d) for policy in self.followers)
                   for d in resident}
        best = max(waiting, key=lambda d: (waiting[d], -d), default=None)
        if best is None or not waiting[best]:
            return domain
        self._riding = best
        return best

    def likely_next(self, current: int) -> int | None:
        return self.lead.likely_next(current)

    def next_load(self, current: int, guess: int | None) -> int | None:
        """The leader's guess at the load after ``guess`` (``ScheduleOrder.next_load``)."""
        own = getattr(self.lead, "next_load", None)
        return None if own is None else own(current, guess)

    def trace(self, domain: int, bvh) -> Queries:
        lead = Queries() if domain == self._riding else self.lead.trace(domain, bvh)
        followers = Queries()
        for policy in self.followers:
            if waiting_rays(policy, domain):
                start = time.perf_counter()
                followers += traced_queries(policy, domain, bvh)
                self.follower_seconds[id(policy)] = (self.follower_seconds.get(id(policy), 0.0)
                                                     + time.perf_counter() - start)
        self.ahead_queries += int(followers)
        return lead + followers

    def rays(self, domain: int) -> int | None:
        own = getattr(self.lead, "rays", None)
        count = 0 if domain == self._riding else None if own is None else own(domain)
        if count is None:
            return None
        return count + sum(waiting_rays(policy, domain) for policy in self.followers)


class ListOrder:
    """Domains in a given order (a round's assignment, a node's own domains to load), each
    traced by ``trace(domain, bvh)`` (default: nothing, the domains are only loaded);
    ``rays(domain)``: how many rays that traces (default: unknown)."""

    def __init__(self, domains: list[int], trace: Callable[[int, object], int] | None = None,
                 rays: Callable[[int], int] | None = None):
        self.domains, self.position = list(domains), 0
        self._trace, self._rays = trace, rays

    def next_domain(self) -> int | None:
        if self.position == len(self.domains):
            return None
        self.position += 1
        return self.domains[self.position - 1]

    def likely_next(self, current: int) -> int | None:
        return self.domains[self.position] if self.position < len(self.domains) else None

    def trace(self, domain: int, bvh) -> Queries:
        return Queries() if self._trace is None else self._trace(domain, bvh)

    def rays(self, domain: int) -> int | None:
        return None if self._rays is None else self._rays(domain)


def waiting_rays(policy, domain: int) -> int:
    """Rays of a tile schedule (``ImageSchedule``, ``SpeculativeSchedule``) waiting for
    ``domain``, radiance and shadow."""
    return policy.radiance.count(domain) + policy.shadow.count(domain)


def traced_tiles(policies, domain: int, bvh) -> Queries:
    """``traced_queries`` of every tile schedule in ``policies`` (in their order) that has rays
    waiting for ``domain``: a frame with several tiles in flight traces them in one activation."""
    return sum((traced_queries(policy, domain, bvh) for policy in policies
                if waiting_rays(policy, domain)), Queries())


def traced_queries(policy, domain: int, bvh) -> Queries:
    """``policy.process(domain, bvh)``; returns the ray queries it made (from its counters)."""
    counters = policy.counters
    radiance, shadow = counters["radiance_tests"], counters["shadow_tests"]
    policy.process(domain, bvh)
    return Queries(counters["radiance_tests"] - radiance, counters["shadow_tests"] - shadow)
