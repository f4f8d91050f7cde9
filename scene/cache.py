"""The domain cache: at most ``capacity`` domains resident; the least recently used is evicted,
or, when a scheduler gives priorities, the resident domain of lowest priority."""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

from vastray.scene.bvh import DomainBVH
from vastray.scene.embree.library import RTC_BUILD_QUALITY_LOW
from vastray.scene.sparse import MAX_RAYS as SPARSE_MAX_RAYS
from vastray.scene.sparse import MAX_SHARE as SPARSE_MAX_SHARE
from vastray.scene.sparse import RaySegments, Selection, SparseDomainBVH
from vastray.scene.sparse import enabled as sparse_loads_enabled
from vastray.scene.sparse import select as select_for
from vastray.scene.store import DomainArrays, Store

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
    #: loads built for an activation's rays alone (``scene.sparse``), not cached
    sparse_loads: int = 0
    #: triangles those builds took, of their domains' triangles
    sparse_triangles: int = 0
    sparse_domain_triangles: int = 0
    #: sparse preloads of a domain the schedule did not activate next
    sparse_preloads_unused: int = 0

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
            "sparse_loads": self.sparse_loads,
            "sparse_preloads_unused": self.sparse_preloads_unused,
            "sparse_triangle_share": (round(self.sparse_triangles / self.sparse_domain_triangles, 4)
                                      if self.sparse_domain_triangles else 0.0),
        }


@dataclass
class _Ahead:
    """A sparse preload: the domain read (``DomainCache._read``'s result, when it began and
    ended), its build for the rays waiting then (None: built whole, or not built) and when
    that ended; ``cached``: built whole and cached instead."""

    read: tuple
    start: float
    read_done: float
    bvh: SparseDomainBVH | None
    done: float
    cached: bool = False


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
    fast_builds : build Embree's fast (Morton) BVH for every domain (``scene.bvh_choice``: the
        render's choice, made from the store alone, so that every cache of a render builds
        the same BVH); False: Embree's default build.
    """

    def __init__(self, store: Store, capacity: int, keep: frozenset[str] = frozenset(),
                 drop_page_cache: bool = False, pool: ThreadPoolExecutor | None = None,
                 load_bandwidth: float | None = None, fast_builds: bool = False):
        if capacity < 1:
            raise ValueError("cache capacity must be at least 1 domain")
        if load_bandwidth is not None and not load_bandwidth > 0:
            raise ValueError(f"load bandwidth must be positive, got {load_bandwidth}")
        self.load_bandwidth = load_bandwidth
        #: (D,) eviction priorities from the scheduler (lowest evicted first) and domains never
        #: evicted for a preload; None: least recently used first.
        self._priority = None
        self._protect: frozenset[int] = frozenset()
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
        self.stats = CacheStats()
        self._resident: OrderedDict[int, DomainBVH] = OrderedDict()
        self._resident_bytes = 0  # sum of the resident domains' nbytes()
        # Render workers and the preloader share the cache.
        self._lock = threading.RLock()
        self._pending: dict[int, Future] = {}
        self._preloader: ThreadPoolExecutor | None = None
        #: (domain, its sparse preload in flight or done): at most one, beside the cache
        self._ahead: tuple[int, Future] | None = None

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

    def load_count(self, domain_id: int) -> int:
        """How many times ``domain_id`` has been loaded (preloads included) so far."""
        with self._lock:
            return self.stats.loads_per_domain.get(domain_id, 0)

    def get(self, domain_id: int, read: tuple | None = None) -> DomainBVH:
        """The built domain, loading it (and evicting the LRU one) if needed.

        The lock is held only to look up, make room and insert, never through a read or a
        BVH build: a load in flight is registered in ``_pending`` (so a second caller for the
        same domain waits for it rather than loading it again, and room-making counts it),
        and callers for resident domains are served meanwhile (issue 42: one thread's load
        held up every other thread's hits for the whole load).

        ``read``: the domain already read (``_read``'s result and when it began), built here
        if a load is needed (``get_for``'s whole builds).
        """
        start = time.perf_counter()
        if read is None and self._ahead is not None and self._ahead[0] == domain_id:
            ahead = self._take_ahead(domain_id)
            if ahead is not None:  # read already: build it whole from that
                read = (ahead.read, ahead.start, ahead.read_done)
        while True:
            with self._lock:
                if domain_id in self._resident:
                    bvh = self._get(domain_id)
                    break
                pending = self._pending.get(domain_id)
                if pending is None:
                    self._make_room(1)
                    mine: Future = Future()
                    self._pending[domain_id] = mine
            if pending is not None:
                pending.result()  # being built (a preload, another thread): wait for that
                continue  # resident now, unless evicted meanwhile
            try:
                bvh = self.load(domain_id, read)
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
            self._resident.move_to_end(domain_id)
            self.stats.hits += 1
            return self._resident[domain_id]
        self._make_room(1)
        bvh = self.load(domain_id)
        self._insert(domain_id, bvh)
        return bvh

    def reserve(self, capacity: int) -> None:
        """Raise the capacity to at least ``capacity`` domains (never lowers it): a node's
        later frame that holds more domains than its first (in situ, a camera that gives it
        more holdings; after a node's loss, the survivors' larger shares). Without it the
        cache would evict what the frame still uses from its accounting only. The bytes stay
        bounded by the render's memory check, which covers the most any node holds."""
        with self._lock:
            self.capacity = max(self.capacity, int(capacity))

    def prioritise(self, priority, protect: Iterable[int] = ()) -> None:
        """Evict by ``priority`` ((D,) numbers, lowest first; None: least recently used) and
        never evict a domain of ``protect`` (the active domain and the next one) to make room
        for a preload. A load the renderer waits for may still evict a protected domain when
        nothing else is resident: the cache never holds more than ``capacity``."""
        with self._lock:
            self._priority = priority
            self._protect = frozenset(int(d) for d in protect)

    def victim(self) -> int | None:
        """The domain a load now would evict (None while there is room): what a schedule
        serves before it goes (see ``SpeculativeSchedule``'s ``serve_before_evict``)."""
        with self._lock:
            if len(self._resident) + len(self._pending) < self.capacity or not self._resident:
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

    def _make_room(self, slots: int, for_preload: bool = False) -> bool:
        """Evict domains until ``slots`` more fit (loads in flight count); False when a
        preload would have to evict a protected domain (nothing is evicted then)."""
        while len(self._resident) + len(self._pending) + slots > self.capacity:
            evicted = self._victim(for_preload) if self._resident else None
            if evicted is None:
                return False
            gone = self._resident.pop(evicted)
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
        self.stats.peak_resident_bytes = max(self.stats.peak_resident_bytes,
                                             self._resident_bytes)
        # A preloaded domain is still pending while it is inserted: count it once.
        self.stats.peak_resident_domains = max(
            self.stats.peak_resident_domains, len(self._resident.keys() | self._pending.keys()))

    def prefetch(self, domain_id: int | None, segments: RaySegments | None = None) -> None:
        """Start loading ``domain_id`` on the preloader thread, so its read and BVH build
        overlap the caller's rendering. Needs room for two domains (the one in use stays).

        With ``segments`` (the rays waiting for it now, where a sparse load may serve them):
        read it and build it for those rays alone (``_load_ahead``), held beside the cache
        for ``get_for``, which takes it where the rays waiting then are covered, and builds
        again from the arrays read where not. Where the rays select too many triangles it is
        built whole and cached, as any preload."""
        if domain_id is None or self.capacity < 2:
            return
        if self._sparse_eligible(segments):
            with self._lock:
                if (domain_id in self._resident or domain_id in self._pending
                        or (self._ahead is not None and self._ahead[0] == domain_id)):
                    return
                if self._preloader is None:
                    self._preloader = ThreadPoolExecutor(1, thread_name_prefix="preloader")
                self._ahead = (domain_id, self._preloader.submit(self._load_ahead, domain_id,
                                                                 segments))
            return
        with self._lock:
            if domain_id in self._resident or domain_id in self._pending:
                return
            if not self._make_room(1, for_preload=True):
                return
            if self._preloader is None:
                self._preloader = ThreadPoolExecutor(1, thread_name_prefix="preloader")
            self._pending[domain_id] = self._preloader.submit(self._preload, domain_id)

    def _preload(self, domain_id: int) -> None:
        try:
            self._preload_built(domain_id, self.load(domain_id))
        finally:
            with self._lock:
                self._pending.pop(domain_id, None)

    def _preload_built(self, domain_id: int, bvh: DomainBVH) -> None:
        with self._lock:
            # resident and no longer pending at once: between two locked steps the domain
            # was both, and counted twice against the capacity (an extra eviction)
            self._insert(domain_id, bvh)
            self._pending.pop(domain_id, None)
            self.stats.preloads += 1

    def _load_ahead(self, domain_id: int, segments: RaySegments) -> _Ahead:
        """``prefetch``'s sparse preload: the domain read, its selection for ``segments`` and
        the sparse build of it (None where the selection is too large: then built whole and
        cached now if a preload may make room, as ``_preload``)."""
        start = time.perf_counter()
        read = self._read(domain_id)
        read_done = time.perf_counter()
        arrays = read[0]
        chosen = self._select(domain_id, arrays, segments)
        if len(chosen.triangles) <= SPARSE_MAX_SHARE * arrays.n_triangles:
            bvh = SparseDomainBVH(domain_id, arrays, chosen, self.keep, self.pool,
                                  self.build_quality, self.mesh_quality)
            return _Ahead(read, start, read_done, bvh, time.perf_counter())
        with self._lock:
            if (domain_id in self._resident or domain_id in self._pending
                    or not self._make_room(1, for_preload=True)):
                return _Ahead(read, start, read_done, None, read_done)
            mine: Future = Future()
            self._pending[domain_id] = mine
        try:
            self._preload_built(domain_id, self.load(domain_id, (read, start, read_done)))
        finally:
            with self._lock:
                self._pending.pop(domain_id, None)
            mine.set_result(None)
        return _Ahead(read, start, read_done, None, read_done, cached=True)

    def _take_ahead(self, domain_id: int) -> _Ahead | None:
        """The sparse preload of ``domain_id`` (waited for), taken; None where there is none
        or it was cached whole. A sparse preload of another domain is dropped (the guess was
        wrong: counted in ``sparse_preloads_unused`` where it had begun)."""
        with self._lock:
            ahead, self._ahead = self._ahead, None
        if ahead is None:
            return None
        if ahead[0] != domain_id:  # not waited for: cancelled, or left to finish unused
            if not ahead[1].cancel():
                self.stats.sparse_preloads_unused += 1
            return None
        got = ahead[1].result()
        return None if got.cached else got

    def close(self) -> None:
        """Stop the preloader (waits for a load in flight)."""
        if self._preloader is not None:
            self._preloader.shutdown(wait=True)
            self._preloader = None

    def count_load(self, domain_id: int, size: int) -> None:
        """Count one load of ``domain_id`` (``size`` bytes) in the stats."""
        self.stats.loads += 1
        self.stats.loaded_domains.add(domain_id)
        self.stats.loads_per_domain[domain_id] = self.stats.loads_per_domain.get(domain_id, 0) + 1
        self.stats.bytes_loaded += size

    def load(self, domain_id: int, read: tuple | None = None) -> DomainBVH:
        """Read and build one domain without caching it (counted as a load); ``read``: as
        ``get``'s."""
        if read is None:
            start = time.perf_counter()
            arrays, size, throttle = self._read(domain_id)
            read_done = time.perf_counter()
        else:
            (arrays, size, throttle), start, read_done = read
        bvh = DomainBVH(domain_id, arrays, self.keep, self.pool, self.build_quality,
                        self.mesh_quality)
        done = time.perf_counter()
        with self._lock:
            self.count_load(domain_id, size)
            self._count_times(start, read_done, done, throttle)
        log.debug("loaded domain %d (%d triangles) in %.3f s", domain_id, bvh.n_triangles,
                  done - start)
        return bvh

    def _read(self, domain_id: int) -> tuple[DomainArrays, int, float]:
        """The domain's arrays, its bytes on disk, and the seconds waited for the emulated
        storage bandwidth."""
        start = time.perf_counter()
        # read, not mapped: a domain file truncated or rewritten under a running render
        # changes nothing it has loaded (mapped, it would be a SIGBUS or a changed picture)
        arrays = self.store.load_domain(domain_id, drop_cache=self.drop_page_cache)
        size = self.store.domains[domain_id].nbytes
        throttle = 0.0
        if self.load_bandwidth is not None:  # emulated network storage: wait out the rest
            throttle = max(0.0, size / self.load_bandwidth - (time.perf_counter() - start))
            time.sleep(throttle)
        return arrays, size, throttle

    def _count_times(self, start: float, read_done: float, done: float, throttle: float) -> None:
        self.stats.read_seconds += read_done - start
        self.stats.throttle_seconds += throttle
        self.stats.build_seconds += done - read_done
        self.stats.load_seconds += done - start

    def _sparse_eligible(self, segments: RaySegments | None) -> bool:
        """Whether a sparse load may serve ``segments``: some rays, at most
        ``sparse.MAX_RAYS``, sparse loads on, and a cache smaller than the store."""
        return (segments is not None and 0 < len(segments) <= SPARSE_MAX_RAYS
                and sparse_loads_enabled() and self.capacity < len(self.store.domains))

    def _select(self, domain_id: int, arrays: DomainArrays, segments: RaySegments) -> Selection:
        lo, hi = self.store.domain_boxes()
        return select_for(arrays.vertices, arrays.indices, lo[domain_id], hi[domain_id],
                          segments)

    def get_for(self, domain_id: int, segments: RaySegments | None) -> DomainBVH | SparseDomainBVH:
        """The domain for tracing the rays ``segments`` (and those ``covers`` accepts).

        A resident domain, or one being loaded whole, is ``get``'s. Otherwise the domain is
        read (or taken from a sparse preload), and where those rays can hit at most
        ``sparse.MAX_SHARE`` of its triangles, a ``SparseDomainBVH`` of them is built (or
        the preload's taken, where it covers them) and returned without entering the cache
        (it evicts nothing; counted in ``sparse_loads``, its read and build in the load
        times); else the domain is built whole and cached, a load as ``get``'s.
        """
        if not self._sparse_eligible(segments):
            return self.get(domain_id)
        start = time.perf_counter()
        with self._lock:
            whole = domain_id in self._resident or domain_id in self._pending
        if whole:
            return self.get(domain_id)
        ahead = self._take_ahead(domain_id)
        if ahead is None:
            read = self._read(domain_id)
            read_start, read_done = start, time.perf_counter()
        else:
            read, read_start, read_done = ahead.read, ahead.start, ahead.read_done
            if ahead.bvh is not None and ahead.bvh.covers(segments.origins, segments.directions,
                                                          segments.limits, segments.pad).all():
                self._count_sparse(ahead.bvh, read, read_start, read_done, ahead.done)
                self.stats.wait_seconds += time.perf_counter() - start
                return ahead.bvh
        arrays = read[0]
        chosen = self._select(domain_id, arrays, segments)
        if len(chosen.triangles) > SPARSE_MAX_SHARE * arrays.n_triangles:
            # built whole, as ``get`` would, from the arrays read
            return self.get(domain_id, (read, read_start, read_done))
        bvh = SparseDomainBVH(domain_id, arrays, chosen, self.keep, self.pool,
                              self.build_quality, self.mesh_quality)
        self._count_sparse(bvh, read, read_start, read_done, time.perf_counter())
        self.stats.wait_seconds += time.perf_counter() - start
        log.debug("loaded %d of domain %d's %d triangles for %d rays", bvh.n_triangles,
                  domain_id, bvh.domain_triangles, len(segments))
        return bvh

    def _count_sparse(self, bvh: SparseDomainBVH, read: tuple, start: float, read_done: float,
                      done: float) -> None:
        with self._lock:
            self.stats.sparse_loads += 1
            self.stats.sparse_triangles += bvh.n_triangles
            self.stats.sparse_domain_triangles += bvh.domain_triangles
            self.stats.bytes_loaded += read[1]
            self._count_times(start, read_done, done, read[2])
            self.stats.peak_resident_bytes = max(self.stats.peak_resident_bytes,
                                                 self._resident_bytes + bvh.nbytes())
