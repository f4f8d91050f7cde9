"""The domain cache: at most ``capacity`` domains resident (and, under ``--memory-limit``, at
most ``max_bytes`` of them as the preflight counts a domain's bytes); the least recently used
is evicted, or, when a scheduler gives priorities, the resident domain of lowest priority."""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from vastray.processes import rss_bytes
from vastray.scene.bvh import DomainBVH
from vastray.scene.embree.library import RTC_BUILD_QUALITY_LOW
from vastray.scene.footprint import domain_footprints
from vastray.scene.heap import trim_heap
from vastray.scene.store import Store

log = logging.getLogger(__name__)


@dataclass
class CacheStats:
    """Counters of a domain cache, for the report."""

    loads: int = 0
    hits: int = 0
    evictions: int = 0
    load_seconds: float = 0.0
    read_seconds: float = 0.0
    build_seconds: float = 0.0
    loaded_domains: set = field(default_factory=set)
    loads_per_domain: dict = field(default_factory=dict)
    peak_resident_bytes: int = 0
    preloads: int = 0
    wait_seconds: float = 0.0
    bytes_loaded: int = 0
    throttle_seconds: float = 0.0
    peak_resident_domains: int = 0
    reads_ahead: int = 0
    reads_ahead_used: int = 0
    builds_ahead: int = 0
    builds_ahead_used: int = 0
    heap_trims: int = 0

    def as_dict(self) -> dict:
        return {
            "loads": self.loads,
            "cache_hits": self.hits,
            "evictions": self.evictions,
            "distinct_domains_loaded": len(self.loaded_domains),
            "preloads": self.preloads,
            "load_s": round(self.load_seconds, 4),
            "load_wait_s": round(self.wait_seconds, 4),
            "bytes_loaded": self.bytes_loaded,
            "load_throttle_s": round(self.throttle_seconds, 4),
            "read_s": round(self.read_seconds, 4),
            "bvh_build_s": round(self.build_seconds, 4),
            "peak_resident_bytes": self.peak_resident_bytes,
            "peak_resident_domains": self.peak_resident_domains,
            "reads_ahead": self.reads_ahead,
            "reads_ahead_used": self.reads_ahead_used,
            "builds_ahead": self.builds_ahead,
            "builds_ahead_used": self.builds_ahead_used,
            "heap_trims": self.heap_trims,
        }


class DomainCache:
    """LRU cache of built domains.

    Parameters
    ----------
    store : the store to load from.
    capacity : most domains resident at once (>= 1).
    keep : attributes each loaded domain keeps for shading (see ``DomainBVH``).
    drop_page_cache : advise the kernel to drop the domain files' pages once read, so a reload
        after eviction is a real disk read (out-of-core benchmarks). Either way a load reads
        the files into memory and checks their checksums (``Store.load_domain``).
    pool : threads each loaded domain's queries split their rays over (``query_pool``).
    load_bandwidth : bytes per second, to emulate network storage (the temporal-coherence
        paper's cluster): after the real read of a domain, the load waits until its size
        divided by this has passed (a sleep, costing no CPU). None: as fast as the disk.
    fast_builds : build Embree's fast (Morton, compact) BVH for every domain (``scene.bvh_choice``: the
        render's choice, made from the store alone, so that every cache of a render builds
        the same BVH); False: Embree's default build.
    build_ahead : keep one of the ``capacity`` slots for a domain built ahead
        (``build_ahead``), where the cache is smaller than the store and holds at least 3.
    rss_ceiling : bytes of process RSS above which each build first gives the C heap's free
        memory back to the system (``scene.heap``: what earlier builds freed, which the heap
        keeps for the next ones); None: never (no memory limit).
    max_bytes : most bytes the domains resident or being loaded may take, each counted as
        the preflight counts it (``scene.footprint.domain_footprints``, for this cache's BVH);
        None: no bound but ``capacity``. Why: a count of domains must be sized by the
        largest ones so that any choice of that many fits a memory limit, and where domains
        differ in size (the 100 M-triangle store's hold 17-216 MB) that left a third of the
        limit unused. Bounded by bytes, the cache holds as many as fit of those it is given.
    """

    def __init__(self, store: Store, capacity: int, keep: frozenset[str] = frozenset(),
                 drop_page_cache: bool = False, pool: ThreadPoolExecutor | None = None,
                 load_bandwidth: float | None = None, fast_builds: bool = False,
                 build_ahead: bool = False, rss_ceiling: int | None = None,
                 max_bytes: int | None = None):
        if capacity < 1:
            raise ValueError("cache capacity must be at least 1 domain")
        if max_bytes is not None and max_bytes < 1:
            raise ValueError(f"a cache's byte bound must be positive, got {max_bytes}")
        if load_bandwidth is not None and not load_bandwidth > 0:
            raise ValueError(f"load bandwidth must be positive, got {load_bandwidth}")
        self.load_bandwidth = load_bandwidth
        self.rss_ceiling = rss_ceiling
        #: (D,) eviction priorities from the scheduler (lowest evicted first) and domains never
        #: evicted for a preload; None: least recently used first.
        self._priority = None
        self._protect: frozenset[int] = frozenset()
        self._parting: int | None = None  # served before its eviction: keeps its place
        self._preloaded: set[int] = set()  # preloading or preloaded, not taken by a get yet
        self.store = store
        self.capacity = capacity
        self.keep = keep
        self.drop_page_cache = drop_page_cache
        self.pool = pool  # the threads every loaded domain's queries split their rays over
        # A cache smaller than the store reloads what it evicts: its builds are Embree's
        # scene quality LOW (a two-level BVH, 10-25 % faster to build than the default; the
        # same hits bit for bit, tests/test_build_quality.py), since a load's build is paid
        # again at every reload. The mesh level is the render's choice, not the cache's: LOW
        # there (the Morton builder) builds a 2.1 M-triangle domain 3-4x faster but changes
        # hits near vertices (6 rays in 50,000 in that test took another triangle), so a
        # cache choosing it for itself would break the out-of-core image's equality with the
        # in-core one (scene.bvh_choice).
        self.fast_builds = fast_builds
        self.build_quality = (RTC_BUILD_QUALITY_LOW if capacity < len(store.domains)
                              or fast_builds else None)
        self.max_bytes = max_bytes
        #: (D,) int64 bytes each domain is charged against ``max_bytes`` (None: no bound),
        #: and the largest of them
        self._footprint: np.ndarray | None = None
        self._largest = 0
        if max_bytes is not None:
            self._footprint = np.asarray(domain_footprints(store.domains, fast_builds),
                                         np.int64)
            self._largest = int(self._footprint.max(initial=0))
        self.stats = CacheStats()
        self._resident: OrderedDict[int, DomainBVH] = OrderedDict()
        self._resident_bytes = 0  # sum of the resident domains' nbytes()
        # Render workers and the preloader share the cache.
        self._lock = threading.RLock()
        self._pending: dict[int, Future] = {}
        self._preloader: ThreadPoolExecutor | None = None
        # domain -> the Future of its files' read ahead (``read_ahead``): one unclaimed, and
        # one a load of its domain has been started for (a preload) and will take
        self._reads: dict[int, Future] = {}
        self._reader: ThreadPoolExecutor | None = None
        self._build_ahead = build_ahead
        # domain -> the Future of its load built ahead (``build_ahead``; at most one), which
        # is in no slot of the resident domains' until ``get`` takes it
        self._built: dict[int, Future] = {}

    @property
    def builds_ahead(self) -> bool:
        """Whether ``build_ahead`` builds anything: asked for, a cache smaller than the store
        and holding at least 3 (two resident, as a preload needs, and the one built ahead;
        under a byte bound, room for three of the largest)."""
        roomy = self.max_bytes is None or self.max_bytes >= 3 * self._largest
        return self._build_ahead and roomy and 3 <= self.capacity < len(self.store.domains)

    @property
    def _limit(self) -> int:
        """Most domains resident or being loaded into a slot: ``capacity``, less the slot of
        the one built ahead where the cache builds ahead."""
        return self.capacity - 1 if self.builds_ahead else self.capacity

    @property
    def _byte_limit(self) -> int | None:
        """Most bytes charged to domains resident or being loaded (``max_bytes``, less the
        largest domain's where one is built ahead outside them); None: no bound."""
        if self.max_bytes is None:
            return None
        return self.max_bytes - (self._largest if self.builds_ahead else 0)

    def charged_bytes(self, more: Iterable[int] = ()) -> int:
        """Bytes charged to the domains resident or being loaded, and ``more`` (0 without a
        byte bound)."""
        if self._footprint is None:
            return 0
        with self._lock:
            held = self._resident.keys() | self._pending.keys() | set(more)
            return int(self._footprint[list(held)].sum()) if held else 0

    def _full(self, slots: int, incoming: int | None) -> bool:
        """Whether ``slots`` more domains (``incoming`` among them, where known) would
        exceed the count or the byte bound."""
        if len(self._resident) + len(self._pending) + slots > self._limit:
            return True
        limit = self._byte_limit
        if limit is None:
            return False
        # an unknown domain is charged as the largest: whatever comes next fits
        extra = () if incoming is None else (incoming,)
        largest = 0 if incoming is not None else self._largest
        return self.charged_bytes(extra) + largest > limit

    @property
    def mesh_quality(self) -> int | None:
        """The mesh's build quality of every domain built here (LOW: the fast BVH)."""
        return RTC_BUILD_QUALITY_LOW if self.fast_builds else None

    def count_afresh(self) -> None:
        """Start the counters again (a new frame): the resident domains stay, so a domain
        loaded earlier counts as a hit, and the peaks start at what is resident now."""
        with self._lock:
            self.stats = CacheStats(peak_resident_bytes=self._resident_bytes,
                                    peak_resident_domains=len(self._resident))

    def __contains__(self, domain_id: int) -> bool:
        return domain_id in self._resident

    def resident(self) -> list[int]:
        """Ids of the resident domains, least recently used first."""
        return list(self._resident)

    def resident_domains(self) -> dict[int, DomainBVH]:
        """The resident domains by id (a snapshot; neither counted as hits nor moved in the
        LRU order)."""
        with self._lock:
            return dict(self._resident)

    def resident_set(self) -> frozenset[int]:
        """Domains resident or being preloaded."""
        with self._lock:
            return frozenset(self._resident) | frozenset(self._pending)

    def preloaded_set(self) -> frozenset[int]:
        """Domains a preload (``prefetch``) has made or is making resident that no ``get`` has
        taken since: whether the load has ended or not, so that what a schedule decides from
        it does not depend on how fast loads run."""
        with self._lock:
            return frozenset(self._preloaded)

    def load_count(self, domain_id: int) -> int:
        """How many times ``domain_id`` has been loaded (preloads included) so far."""
        with self._lock:
            return self.stats.loads_per_domain.get(domain_id, 0)

    def get(self, domain_id: int) -> DomainBVH:
        """The built domain, loading it (and evicting the LRU one) if needed.

        The lock is held only to look up, make room and insert, never through a read or a
        BVH build: a load in flight is registered in ``_pending`` (so a second caller for the
        same domain waits for it rather than loading it again, and room-making counts it),
        and callers for resident domains are served meanwhile (issue 42: one thread's load
        held up every other thread's hits for the whole load).
        """
        start = time.perf_counter()
        while True:
            with self._lock:
                self._preloaded.discard(domain_id)  # taken now (a no-op on a second pass)
                if domain_id in self._resident:
                    bvh = self._get(domain_id)
                    break
                built = self._built.pop(domain_id, None)
                pending = self._pending.get(domain_id)
                if built is not None:  # in flight now: another caller waits for it
                    self._pending[domain_id] = built
                elif pending is None:
                    self._make_room(1, incoming=domain_id)
                    mine: Future = Future()
                    self._pending[domain_id] = mine
            if built is not None:
                bvh = self._take_built(domain_id, built)
                break
            if pending is not None:
                pending.result()  # being built (a preload, another thread): wait for that
                continue  # resident now, unless evicted meanwhile
            try:
                bvh = self.load(domain_id)
            except BaseException as exc:
                with self._lock:
                    self._pending.pop(domain_id, None)
                mine.set_exception(exc)
                raise
            with self._lock:
                self._insert(domain_id, bvh)  # resident and no longer pending at once
                self._pending.pop(domain_id, None)
            mine.set_result(None)
            break
        self.stats.wait_seconds += time.perf_counter() - start
        return bvh

    def _get(self, domain_id: int) -> DomainBVH:
        if domain_id in self._resident:
            parting, self._parting = self._parting, None
            if domain_id != parting:  # (the parting domain stays the next to go)
                self._resident.move_to_end(domain_id)
            self.stats.hits += 1
            return self._resident[domain_id]
        self._make_room(1, incoming=domain_id)
        bvh = self.load(domain_id)
        self._insert(domain_id, bvh)
        return bvh

    def reserve(self, capacity: int) -> None:
        """Raise the capacity to at least ``capacity`` domains (never lowers it): a node's
        later frame that holds more domains than its first (in situ, a camera that gives it
        more holdings; after a node's loss, the survivors' larger shares). Without it the
        cache would evict what the frame still uses from its accounting only. The bytes stay
        bounded by the render's memory check, which covers the most any node holds. Raising
        the count lifts the byte bound too: the holdings must stay resident."""
        with self._lock:
            if int(capacity) > self.capacity:
                self.max_bytes = None
            self.capacity = max(self.capacity, int(capacity))

    def prioritise(self, priority, protect: Iterable[int] = ()) -> None:
        """Evict by ``priority`` ((D,) numbers, lowest first; None: least recently used) and
        never evict a domain of ``protect`` (the active domain and the next one) to make room
        for a preload. A load the renderer waits for may still evict a protected domain when
        nothing else is resident: the cache never holds more than ``capacity``."""
        with self._lock:
            self._priority = priority
            self._protect = frozenset(int(d) for d in protect)

    def parting(self, domain_id: int) -> None:
        """The next ``get`` of ``domain_id`` (resident) leaves its place in the eviction order
        as it is: a schedule serves the domain the cache would evict next (``victim``) before
        it goes, and that use must not make it recently used. Counted as used, the served
        domain was no longer the victim, the next one was served in turn, and so on through
        every resident domain with rays before each load: at a quarter of ``bench/ooc.py
        --large``'s domains cached, 1,853 activations for 195 loads (session 69).

        The mark holds for the next hit only, whichever domain it is for."""
        with self._lock:
            self._parting = int(domain_id)

    def victim(self) -> int | None:
        """The domain a load now would evict (None while there is room; under a byte bound,
        room for the largest domain, whichever comes next): what a schedule serves before it
        goes (see ``SpeculativeSchedule``'s ``serve_before_evict``)."""
        with self._lock:
            if not self._resident or not self._full(1, None):
                return None
            return self._victim(False)

    def _victim(self, for_preload: bool) -> int | None:
        """The resident domain to evict next: the lowest priority (least recently used on
        ties, or when there are no priorities) outside the protected set."""
        order = list(self._resident)  # least recently used first
        free = [d for d in order if d not in self._protect]
        if not free:
            return None if for_preload else order[0]
        if self._priority is None:
            return free[0]
        return min(free, key=lambda d: self._priority[d])  # min keeps the first (LRU) on ties

    def _make_room(self, slots: int, for_preload: bool = False,
                   incoming: int | None = None) -> bool:
        """Evict domains until ``slots`` more fit (loads in flight count), ``incoming`` (the
        domain to load) within the byte bound too; False when a preload would have to evict a
        protected domain (nothing is evicted then)."""
        while self._full(slots, incoming):
            evicted = self._victim(for_preload) if self._resident else None
            if evicted is None:
                return False
            gone = self._resident.pop(evicted)
            self._preloaded.discard(evicted)
            self._resident_bytes -= gone.nbytes()
            self.stats.evictions += 1
            log.debug("evicted domain %d", evicted)
        return True

    def _insert(self, domain_id: int, bvh: DomainBVH) -> None:
        replaced = self._resident.get(domain_id)
        if replaced is not None:
            self._resident_bytes -= replaced.nbytes()
        self._resident[domain_id] = bvh
        # A running total: summing over every resident domain at each load costs O(domains).
        self._resident_bytes += bvh.nbytes()
        # A preloaded domain is still pending while it is inserted: count it once. A domain
        # built ahead is in memory too, in the slot kept for it.
        built = [f.result()[0] for f in self._built.values() if f.done() and not f.exception()]
        self.stats.peak_resident_bytes = max(
            self.stats.peak_resident_bytes,
            self._resident_bytes + sum(bvh.nbytes() for bvh in built))
        self.stats.peak_resident_domains = max(
            self.stats.peak_resident_domains,
            len(self._resident.keys() | self._pending.keys()) + len(self._built))

    def prefetch(self, domain_id: int | None) -> None:
        """Start loading ``domain_id`` on the preloader thread, so its read and BVH build
        overlap the caller's rendering. Needs room for two domains (the one in use stays)."""
        if domain_id is None or self._limit < 2:
            return
        with self._lock:
            if domain_id in self._resident or domain_id in self._pending or domain_id in self._built:
                return
            if not self._make_room(1, for_preload=True, incoming=domain_id):
                return
            if self._preloader is None:
                self._preloader = ThreadPoolExecutor(1, thread_name_prefix="preloader")
            self._pending[domain_id] = self._preloader.submit(self._preload, domain_id)
            self._preloaded.add(domain_id)

    def build_ahead(self, domain_id: int | None) -> None:
        """Start loading ``domain_id`` on the preloader thread into the slot kept for it,
        evicting nothing: ``get`` takes it, and only then evicts to make it resident. One
        domain is built ahead at a time: a new one replaces one not taken, finished or not (a
        build wasted, no load). No-op unless ``builds_ahead``.

        Why: out of core the cache is full, and a preload must evict. spec-ooc serves the
        domain the cache would evict before it goes (``serve_before_evict``), so while that
        domain still has rays it names no preload (``likely_next`` is None) and the
        preloader idled while the render served the resident domains in turn: at a quarter
        of ``rm`` 1600³'s 72 domains, the builds kept the preloader busy 5.0 of 8.0 s and
        184 of 195 loads were waited for while in flight. (Since session 71 spec-ooc serves
        that domain before it traces a preloaded one, while the preload runs, so it names a
        preload at nearly every step and rarely builds ahead.) The slot kept for a domain built
        ahead holds what a preload would have evicted for, so the cache never holds more
        than ``capacity`` built domains (a replaced build still running holds its memory
        until it ends; the next starts after it, on the same thread). Replacing whatever the
        build's state keeps the loads the same however fast the builds run."""
        if domain_id is None or not self.builds_ahead:
            return
        with self._lock:
            if (domain_id in self._resident or domain_id in self._pending
                    or domain_id in self._built):
                return
            for replaced in self._built.values():
                replaced.cancel()  # not taken: its build, if it started, is wasted
            self._built.clear()
            if self._preloader is None:
                self._preloader = ThreadPoolExecutor(1, thread_name_prefix="preloader")
            self._built[domain_id] = self._preloader.submit(self._build, domain_id)
            self.stats.builds_ahead += 1

    def _take_built(self, domain_id: int, built: Future) -> DomainBVH:
        """The domain built ahead (waited for if still building), made resident: counted as
        a load now, evicting what the cache's order gives to make room."""
        try:
            result = built.result()
        except BaseException:
            with self._lock:
                self._pending.pop(domain_id, None)
            raise
        self._count_built(domain_id, result)
        with self._lock:
            self._pending.pop(domain_id, None)
            self._make_room(1, incoming=domain_id)
            self._insert(domain_id, result[0])
            self.stats.builds_ahead_used += 1
        return result[0]

    def _preload(self, domain_id: int) -> None:
        try:
            bvh = self.load(domain_id)
            with self._lock:
                # resident and no longer pending at once: between two locked steps the domain
                # was both, and counted twice against the capacity (an extra eviction)
                self._insert(domain_id, bvh)
                self._pending.pop(domain_id, None)
                self.stats.preloads += 1
        finally:
            with self._lock:
                self._pending.pop(domain_id, None)

    def read_ahead(self, domain_id: int | None) -> None:
        """Start reading ``domain_id``'s files on the reader thread, taking no slot and
        evicting nothing: its load, when it comes, builds from the bytes read (the read,
        a disk's latency or ``load_bandwidth``'s wait, overlapped with the render and with the
        preloader's build of another domain). One domain is read ahead at a time (besides one
        a started load or the domain built ahead will take: the slot kept for that one holds
        its arrays); a new one replaces it (a replaced read is wasted; it was no
        load). Out of core, two reads' arrays are what the preflight reserves besides the
        builds (``preflight.domain_build_bytes``); a cache holding every domain needs no
        more: what it reads ahead is the arrays of a domain it will hold.

        Why: out of core the cache is full, and a preload must evict, so the schedules guess
        one domain ahead and only where a domain can go (``likely_next``); the loads then ran
        one after another, each started one short activation before it was needed (at a
        quarter of ``rm`` 1600³'s 72 domains cached, 183 of 195 loads were waited for, for 34
        of their 37 ms). A read needs no slot. In core too: there the preloader read each
        domain and then built it, one step ahead of the render, so the render waited for every
        read (session 70, ``bench/ooc.py --large`` with all 72 domains cached: 2.4-3.2 s of
        waits for loads, 1.1 s of them for reads with no build running; reading ahead,
        4.12-4.14 s -> 3.42-3.57 s a render, the same image)."""
        if domain_id is None:
            return
        with self._lock:
            if (domain_id in self._resident or domain_id in self._pending
                    or domain_id in self._reads or domain_id in self._built):
                return
            for other in [d for d in self._reads
                          if d not in self._pending and d not in self._built]:
                del self._reads[other]  # replaced: its load is not coming (yet)
            if self._reader is None:
                self._reader = ThreadPoolExecutor(1, thread_name_prefix="reader")
            self._reads[domain_id] = self._reader.submit(self._read, domain_id)
            self.stats.reads_ahead += 1

    def _read(self, domain_id: int):
        """The domain's arrays, as a load reads them (``load_bandwidth`` waited out), with
        the seconds the read and the wait took, and the wait's."""
        start = time.perf_counter()
        # read, not mapped: a domain file truncated or rewritten under a running render
        # changes nothing it has loaded (mapped, it would be a SIGBUS or a changed picture)
        arrays = self.store.load_domain(domain_id, drop_cache=self.drop_page_cache,
                                        attributes=self.keep)
        throttle = 0.0
        if self.load_bandwidth is not None:  # emulated network storage: wait out the rest
            size = self.store.domains[domain_id].read_bytes(self.keep)
            throttle = max(0.0, size / self.load_bandwidth - (time.perf_counter() - start))
            time.sleep(throttle)
        return arrays, time.perf_counter() - start, throttle

    def _take_read(self, domain_id: int):
        """The read ahead of ``domain_id`` (waited for if still running), or None."""
        with self._lock:
            future = self._reads.pop(domain_id, None)
        return None if future is None else future.result()

    def close(self) -> None:
        """Stop the preloader (waits for a load in flight) and the reader."""
        if self._preloader is not None:
            self._preloader.shutdown(wait=True)
            self._preloader = None
        self._built.clear()
        if self._reader is not None:
            self._reader.shutdown(wait=True)
            self._reader = None
            self._reads.clear()

    def count_load(self, domain_id: int, size: int) -> None:
        """Count one load of ``domain_id`` (``size`` bytes) in the stats."""
        self.stats.loads += 1
        self.stats.loaded_domains.add(domain_id)
        self.stats.loads_per_domain[domain_id] = self.stats.loads_per_domain.get(domain_id, 0) + 1
        self.stats.bytes_loaded += size

    def load(self, domain_id: int) -> DomainBVH:
        """Read and build one domain without caching it (counted as a load)."""
        built = self._build(domain_id)
        self._count_built(domain_id, built)
        return built[0]

    def _build(self, domain_id: int) -> tuple:
        """Read (or take the read ahead) and build one domain, not yet counted: (the built
        domain, bytes read, whether it was read ahead, read seconds, the bandwidth's wait in
        them, build seconds)."""
        start = time.perf_counter()
        self._relieve_heap()
        size = self.store.domains[domain_id].read_bytes(self.keep)
        ahead = self._take_read(domain_id)  # waited for here if it is still running
        arrays, read_s, throttle = ahead if ahead is not None else self._read(domain_id)
        read_done = time.perf_counter()
        bvh = DomainBVH(domain_id, arrays, self.keep, self.pool, self.build_quality,
                        self.mesh_quality)
        done = time.perf_counter()
        log.debug("loaded domain %d (%d triangles) in %.3f s", domain_id, bvh.n_triangles,
                  done - start)
        return bvh, size, ahead is not None, read_s, throttle, done - read_done

    def _relieve_heap(self) -> None:
        """Above ``rss_ceiling``, give the C heap's free memory back before a build takes
        more (``scene.heap``), counted in ``heap_trims``."""
        if self.rss_ceiling is not None and rss_bytes() > self.rss_ceiling and trim_heap():
            with self._lock:
                self.stats.heap_trims += 1

    def _count_built(self, domain_id: int, built: tuple) -> None:
        """Count a load ``_build`` made in the stats."""
        _, size, read_ahead, read_s, throttle, build_s = built
        with self._lock:
            self.count_load(domain_id, size)
            self.stats.reads_ahead_used += read_ahead
            self.stats.read_seconds += read_s
            self.stats.throttle_seconds += throttle
            self.stats.build_seconds += build_s
            self.stats.load_seconds += read_s + build_s
