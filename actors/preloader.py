"""The domain preloader: the third actor of a node (beside the management actor and the render
workers). It owns the node's domain cache, loads the domain the scheduler expects next on its
own thread while the render workers trace, evicts the resident domain the scheduler values
least, and counts what loading cost (load time, time the workers waited, bytes).

The scheduler drives it with two calls: ``prioritise`` (eviction order; least recently used
when it gives none) and ``preload`` (load this one ahead). ``get`` is what a render worker
awaits before tracing a domain; it returns at once for a resident domain, joins a preload in
flight, or loads on the preloader's thread.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from vastray.scene.bvh import DomainBVH
from vastray.scene.cache import DomainCache
from vastray.scene.store import Store


class CacheFront:
    """What a schedule reads of a node's domain cache and sets on it (``self.cache``, a
    ``DomainCache``): shared by the real preloader and the simulator's."""

    cache: DomainCache

    def prioritise(self, priority: np.ndarray | None, protect: Iterable[int] = ()) -> None:
        """Evict the lowest of ``priority`` ((D,), None: least recently used) first, and never
        ``protect`` (the active domain and the one preloaded next) for a preload."""
        self.cache.prioritise(priority, protect)

    def resident(self) -> frozenset[int]:
        """Domains resident or being loaded."""
        return self.cache.resident_set()

    def preloaded(self) -> frozenset[int]:
        """Domains of ``resident()`` preloaded (or preloading) and not taken since
        (``DomainCache.preloaded_set``)."""
        return self.cache.preloaded_set()

    def victim(self) -> int | None:
        """The domain a load now would evict (None while there is room)."""
        return self.cache.victim()

    def parting(self, domain: int) -> None:
        """``domain``, the victim, is served before it goes: its next use keeps it the victim
        (``DomainCache.parting``)."""
        self.cache.parting(domain)

    def load_count(self, domain: int) -> int:
        """Times ``domain`` has been loaded so far (preloads included)."""
        return self.cache.load_count(domain)

    def loads_per_domain(self) -> dict[int, int]:
        return dict(self.cache.stats.loads_per_domain)


class DomainPreloader(CacheFront):
    """A node's domain cache with a loading thread.

    Parameters
    ----------
    store : the store the node loads from.
    capacity : most domains resident at once (preloading needs 2: the one being traced stays).
    keep : attributes each loaded domain keeps for shading.
    pool : threads each loaded domain's queries split their rays over.
    load_bandwidth : bytes per second to emulate network storage with (None: the disk's).
    preload : False turns loading ahead off (``preload`` does nothing): the ablation of the
        temporal-coherence paper's Table 2 and the benchmarks' "no preloading" rows.
    drop_page_cache : make every load a real read from disk (out-of-core benchmarks).
    fast_builds : build Embree's fast BVH (the render's ``RenderSetup.fast_builds``).
    build_ahead : keep a slot of the cache for a domain built ahead (``build_ahead``).
    rss_ceiling : the cache's (``DomainCache``): RSS above which a build first trims the heap.
    max_bytes : the cache's (``DomainCache``): most bytes of domains it holds (None: no bound
        but ``capacity``).
    """

    def __init__(self, store: Store, capacity: int, keep: frozenset[str] = frozenset(),
                 pool: ThreadPoolExecutor | None = None, load_bandwidth: float | None = None,
                 preload: bool = True, drop_page_cache: bool = False, fast_builds: bool = False,
                 build_ahead: bool = False, rss_ceiling: int | None = None,
                 max_bytes: int | None = None):
        self.cache = DomainCache(store, capacity, keep, pool=pool, load_bandwidth=load_bandwidth,
                                 drop_page_cache=drop_page_cache, fast_builds=fast_builds,
                                 build_ahead=build_ahead and preload, rss_ceiling=rss_ceiling,
                                 max_bytes=max_bytes)
        self.enabled = preload
        self._loader = ThreadPoolExecutor(1, thread_name_prefix="loader")

    @property
    def capacity(self) -> int:
        return self.cache.capacity

    def reserve(self, capacity: int) -> None:
        """At least ``capacity`` domains resident from now on (``DomainCache.reserve``)."""
        self.cache.reserve(capacity)

    async def get(self, domain: int) -> DomainBVH:
        """The built domain, loading it if it is not resident (the wait is counted)."""
        if domain in self.cache:
            return self.cache.get(domain)  # resident: no thread hop
        return await asyncio.get_running_loop().run_in_executor(self._loader, self.cache.get,
                                                                domain)

    def preload(self, domain: int | None) -> None:
        """Start loading ``domain`` ahead (no-op when resident, loading, disabled, or when
        only protected domains could make room)."""
        if self.enabled and domain is not None:
            self.cache.prefetch(int(domain))

    def read_ahead(self, domain: int | None) -> None:
        """Start reading ``domain``'s files ahead, taking no slot (``DomainCache.read_ahead``;
        no-op when preloading is off)."""
        if self.enabled and domain is not None:
            self.cache.read_ahead(int(domain))

    @property
    def builds_ahead(self) -> bool:
        """Whether ``build_ahead`` builds anything (``DomainCache.builds_ahead``)."""
        return self.enabled and self.cache.builds_ahead

    def build_ahead(self, domain: int | None) -> None:
        """Start building ``domain`` in the slot kept for it, evicting nothing
        (``DomainCache.build_ahead``)."""
        if self.enabled and domain is not None:
            self.cache.build_ahead(int(domain))

    def load_bandwidth_mb_s(self) -> float | None:
        """The emulated storage bandwidth every load is held to, in MB/s (None: none)."""
        bandwidth = self.cache.load_bandwidth
        return None if bandwidth is None else bandwidth / 1e6

    def stats(self) -> dict:
        """Counters for the node's report: loads, preloads, load_s, load_wait_s,
        bytes_loaded, ..."""
        return self.cache.stats.as_dict()

    def close(self) -> None:
        self.cache.close()
        self._loader.shutdown(wait=True)
