"""A node's domain cache and preloader in virtual time.

The cache's rules are ``scene.cache.DomainCache``'s own (capacity, LRU or the scheduler's
priorities, protected domains, preloads counted against the capacity); only a load differs:
it hands back the domain already built in memory (``Domains``) and charges the load's cost in
virtual time: the read and the build on the node's core, beside its traces (``_load``).
"""

from __future__ import annotations

import asyncio
import time

import numpy as np

from vastray.actors.preloader import CacheFront
from vastray.scene.bvh import DomainBVH
from vastray.scene.cache import DomainCache
from vastray.scene.store import Store


def domain_sizes(store: Store, keep: frozenset[str] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(D,) int64 bytes and (D,) int64 triangles of each of ``store``'s domains (what a load
    costs), read from its manifest: nothing is loaded. ``keep``: the attributes a load reads
    besides the triangles (``DomainInfo.read_bytes``; None: every file)."""
    return (np.array([d.read_bytes(keep) for d in store.domains], np.int64),
            store.domain_triangles())


class Domains:
    """Every domain of a store built once, in memory, shared by all virtual nodes (the
    simulator traces real rays against them; which node holds which is the virtual caches'
    business).

    Parameters
    ----------
    store : the store.
    keep : attributes the domains keep for shading.
    """

    def __init__(self, store: Store, keep: frozenset[str]):
        self.store = store
        self._real = DomainCache(store, max(len(store.domains), 1), keep)
        #: (D,) bytes and triangles of each domain: what a load costs.
        self.nbytes, self.triangles = domain_sizes(store, keep)
        #: (domain, scene quality, mesh quality) -> (read, build) CPU seconds of one load here
        #: and the cores its build kept busy (its CPU over its wall time)
        self._load_cpu: dict[tuple, tuple[float, float, float]] = {}

    def get(self, domain: int) -> DomainBVH:
        return self._real.get(domain)

    def load_cpu_s(self, domain: int, scene_quality: int | None = None,
                   mesh_quality: int | None = None) -> tuple[float, float]:
        """(read, build): CPU seconds a node's load of ``domain`` takes on this machine, its
        read (from the page cache, as a render's loads once the store has been read) and its
        BVH build at the node cache's qualities, timed once (``time.process_time``:
        Embree's build threads too, as ``sim.calibrate`` times builds) and remembered.

        Why measured, not the calibration's line: a build's cost per triangle depends on the
        geometry, not only on its count. The turbine-blade scan's domains build at 200-225
        ns a triangle here, rm 64³'s triangles merged to the same counts at 175 ns, so the
        calibration's fit charged the scan's loads about a quarter less than they cost.

        A load at the qualities of the domains kept here becomes the kept one (no second
        build); at other qualities (a cache smaller than the store builds Embree's LOW scene
        quality) it is built once more, timed, and dropped. The first measurement of a
        process builds once untimed first: a first build pays first uses, 4-8x a warm one.
        """
        return self._timed(domain, scene_quality, mesh_quality)[:2]

    def build_width(self, domain: int, scene_quality: int | None = None,
                    mesh_quality: int | None = None) -> float:
        """The cores ``domain``'s build at these qualities kept busy here (its CPU seconds
        over its wall seconds, at least 1; measured with ``load_cpu_s``)."""
        return self._timed(domain, scene_quality, mesh_quality)[2]

    def _timed(self, domain: int, scene_quality: int | None,
               mesh_quality: int | None) -> tuple[float, float, float]:
        """(read CPU s, build CPU s, build width) of one load, timed once (``load_cpu_s``)."""
        key = (domain, scene_quality, mesh_quality)
        timed = self._load_cpu.get(key)
        if timed is not None:
            return timed
        real = self._real
        if not self._load_cpu:
            DomainBVH(domain, self.store.load_domain(domain, attributes=real.keep), real.keep,
                      None, scene_quality,
                      mesh_quality).close()
        start = time.process_time()
        arrays = self.store.load_domain(domain, attributes=real.keep)
        read, read_wall = time.process_time(), time.perf_counter()
        bvh = DomainBVH(domain, arrays, real.keep, None, scene_quality, mesh_quality)
        build, build_wall = time.process_time() - read, time.perf_counter() - read_wall
        # Embree builds on its own threads too: the cores the build kept busy (1 where it
        # was too short to time)
        width = max(1.0, build / build_wall) if build_wall > 1e-4 else 1.0
        timed = self._load_cpu[key] = (read - start, build, width)
        if ((scene_quality, mesh_quality) == (real.build_quality, real.mesh_quality)
                and domain not in real and domain not in real._pending):
            with real._lock:
                real._insert(domain, bvh)
        else:
            bvh.close()
        return timed

    def load_seconds(self, scene_quality: int | None = None, mesh_quality: int | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
        """(D,) read and (D,) build CPU seconds of every domain (``load_cpu_s``; 0 for an
        empty one)."""
        out = np.zeros((2, len(self.store.domains)))
        for domain in np.flatnonzero(self.triangles):
            out[:, domain] = self.load_cpu_s(int(domain), scene_quality, mesh_quality)
        return out[0], out[1]

    def close(self) -> None:
        self._real.close()


class _VirtualCache(DomainCache):
    """``DomainCache`` whose ``load`` takes the built domain from ``Domains`` (the cost is
    charged by ``VirtualPreloader``)."""

    def __init__(self, domains: Domains, capacity: int, build_ahead: bool = False):
        super().__init__(domains.store, capacity, build_ahead=build_ahead)
        self.domains = domains

    def load(self, domain_id: int) -> DomainBVH:
        self.count_load(domain_id, int(self.domains.nbytes[domain_id]))
        return self.domains.get(domain_id)


class VirtualPreloader(CacheFront):
    """A node's preloader in virtual time, with ``actors.preloader.DomainPreloader``'s
    interface (what schedules and frames call; what reads and sets the cache is theirs).

    Parameters
    ----------
    cluster : the virtual nodes (for cores and the clock).
    rank : this node.
    domains : the built domains.
    capacity : most domains resident at once.
    preload : load the schedule's guess ahead (False: every load is waited for).
    bandwidth : emulated storage, bytes per second (``--load-bandwidth``): a load's read
        lasts at least its size over this (as ``DomainCache.load``), the rest of it a wait
        that needs no core; None: no floor.
    build_ahead : keep a slot of the cache for a domain built ahead (as ``DomainCache``).
    """

    def __init__(self, cluster, rank: int, domains: Domains, capacity: int,
                 preload: bool = True, bandwidth: float | None = None,
                 build_ahead: bool = False):
        self.cluster, self.rank, self.domains = cluster, rank, domains
        self.cache = _VirtualCache(domains, capacity, build_ahead and preload)
        self.enabled, self.bandwidth = preload, bandwidth
        self.load_wait_s = 0.0
        self._preloading = asyncio.Lock()
        self._reads: dict[int, asyncio.Future] = {}  # domain -> its read ahead
        self._built: dict[int, asyncio.Future] = {}  # domain -> its build ahead (at most one)
        self._replaced: set[asyncio.Future] = set()  # builds ahead replaced, running to the end

    @property
    def capacity(self) -> int:
        return self.cache.capacity

    async def _load(self, domain: int, insert: bool = True) -> None:
        """Charge one load of ``domain`` (the read and the BVH build on the node's core,
        beside whatever else it computes: the CPU time they take here where
        ``CostModel.load_scale`` is set, else the constants; then what the emulated storage
        bandwidth adds to the read, a wait) and make it resident.

        The read is compute, not a wait: the calibration times reads from the page cache,
        as a render's loads are once a store has been read, and such a read is the loader
        thread's CPU (opening the files, copying, checks: 0.4 ms a domain here, most of a
        small domain's load) on the node's one core. Charged as a wait, a preload's read
        overlapped the node's traces for free, and the real-code simulator charged the
        sort-first nodes of the replay's check a third less than the replay (which charges
        a load on the node's timeline)."""
        cache = self.cache
        ahead = self._reads.pop(domain, None)
        if ahead is not None:  # read ahead: its cost charged as it ran; waited for if running
            read_s, throttle = await ahead
            build_s, width = self._costs(domain)[1:]
            cache.stats.reads_ahead_used += 1
        else:
            read_s, build_s, width = self._costs(domain)
            # the read on the loader thread, then the build on Embree's threads too
            await self.cluster.compute(self.rank, read_s)
            throttle = 0.0
        # where the machine has a core no other node is using, the build uses it
        # (``SharedCores``)
        await self.cluster.compute(self.rank, build_s, width)
        if ahead is None:
            throttle = await self._throttle(domain, read_s)
        cache.stats.load_seconds += read_s + build_s + throttle
        cache.stats.throttle_seconds += throttle
        if insert:
            self._insert(domain)

    def _insert(self, domain: int) -> None:
        """Count a load of ``domain`` and make it resident."""
        # the domain, built here once for every virtual node (its first ``Domains.get`` builds
        # it): the simulator's own work, not the node's code
        with self.cluster.meter.simulators_own():
            self.cache._insert(domain, self.cache.load(domain))

    def _costs(self, domain: int) -> tuple[float, float, float]:
        """(read seconds, build seconds, cores the build keeps busy) of a load of ``domain``."""
        cache, costs = self.cache, self.cluster.costs
        if costs.load_scale:  # the simulator's own load of it is its work, not the node's
            with self.cluster.meter.simulators_own():
                qualities = (cache.build_quality, cache.mesh_quality)
                read_s, build_s = (costs.load_scale * s
                                   for s in self.domains.load_cpu_s(domain, *qualities))
                return read_s, build_s, self.domains.build_width(domain, *qualities)
        return (costs.read_s(int(self.domains.nbytes[domain])),
                costs.build_s(int(self.domains.triangles[domain])), 1.0)

    async def _throttle(self, domain: int, read_s: float) -> float:
        """As ``DomainCache.load``: the read lasts at least the bytes over the bandwidth."""
        nbytes = int(self.domains.nbytes[domain])
        throttle = 0.0 if self.bandwidth is None else max(0.0, nbytes / self.bandwidth - read_s)
        await asyncio.sleep(throttle)
        return throttle

    def read_ahead(self, domain: int | None) -> None:
        """As ``DomainCache.read_ahead``: start ``domain``'s read (its CPU on the node's core,
        then the bandwidth's wait) without a slot; its load then only builds."""
        cache = self.cache
        if (domain is None or not self.enabled or domain in cache
                or domain in cache._pending or domain in self._reads or domain in self._built):
            return
        for other in [d for d in self._reads if d not in cache._pending and d not in self._built]:
            del self._reads[other]  # replaced: wasted, as the real reader's (it runs on)
        self._reads[domain] = asyncio.ensure_future(self._read(int(domain)))
        cache.stats.reads_ahead += 1

    async def _read(self, domain: int) -> tuple[float, float]:
        read_s = self._costs(domain)[0]
        await self.cluster.compute(self.rank, read_s)
        return read_s, await self._throttle(domain, read_s)

    async def get(self, domain: int) -> DomainBVH:
        """The domain, after its load's cost if it is not resident (joining a preload in
        flight; a resident domain or a joined preload counts as a hit, as in the real
        cache)."""
        cache = self.cache
        start = self.cluster.now()
        cache._preloaded.discard(domain)
        built = self._built.pop(domain, None)
        if built is not None and domain not in cache:  # built ahead: taken, evicting now
            cache._pending[domain] = built
            try:
                await built
            finally:
                cache._pending.pop(domain, None)
            cache._make_room(1)
            self._insert(domain)
            cache.stats.builds_ahead_used += 1
            self.load_wait_s += self.cluster.now() - start
            return cache._resident[domain]
        pending = cache._pending.get(domain)
        if pending is None and domain not in cache:
            cache._make_room(1)
            # in flight like a preload, so room-making and other requests count it
            cache._pending[domain] = load = asyncio.ensure_future(self._load(domain))
            try:
                await load
            finally:
                cache._pending.pop(domain, None)
            self.load_wait_s += self.cluster.now() - start
            return cache._resident[domain]
        if pending is not None:
            await pending
        self.load_wait_s += self.cluster.now() - start
        return cache._get(domain)

    def preload(self, domain: int | None) -> None:
        """Start loading ``domain`` ahead (as ``DomainCache.prefetch``: not when resident,
        loading, disabled, or when only protected domains could make room)."""
        cache = self.cache
        if (not self.enabled or domain is None or cache._limit < 2 or domain in cache
                or domain in cache._pending or domain in self._built
                or not cache._make_room(1, for_preload=True)):
            return
        cache._pending[domain] = asyncio.ensure_future(self._preload(int(domain)))
        cache._preloaded.add(domain)

    async def _preload(self, domain: int) -> None:
        cache = self.cache
        try:
            async with self._preloading:  # one preloading thread: preloads queue
                await self._load(domain)
            cache.stats.preloads += 1
        finally:
            cache._pending.pop(domain, None)

    @property
    def builds_ahead(self) -> bool:
        """As ``DomainPreloader.builds_ahead``."""
        return self.enabled and self.cache.builds_ahead

    def build_ahead(self, domain: int | None) -> None:
        """As ``DomainCache.build_ahead``: the load of ``domain`` on the preloading thread
        (queued behind a preload), into the slot kept for it; ``get`` takes it."""
        cache = self.cache
        if (domain is None or not self.builds_ahead or domain in cache
                or domain in cache._pending or domain in self._built):
            return
        for replaced in self._built.values():
            # not taken: it runs on, wasted, as the real preloader thread's build does (not
            # cancelled: its compute is charged to the node's core to the end)
            self._replaced.add(replaced)
            replaced.add_done_callback(self._replaced.discard)
        self._built.clear()
        self._built[domain] = asyncio.ensure_future(self._build_ahead(int(domain)))
        cache.stats.builds_ahead += 1

    async def _build_ahead(self, domain: int) -> None:
        async with self._preloading:  # the one preloading thread
            await self._load(domain, insert=False)

    def load_bandwidth_mb_s(self) -> float | None:
        return None if self.bandwidth is None else self.bandwidth / 1e6

    def stats(self) -> dict:
        return {**self.cache.stats.as_dict(), "load_wait_s": round(self.load_wait_s, 4)}

    def close(self) -> None:
        """Drop the reads ahead still running (no thread to stop)."""
        for read in [*self._reads.values(), *self._built.values(), *self._replaced]:
            read.cancel()
        self._reads.clear()
        self._built.clear()
        self._replaced.clear()
