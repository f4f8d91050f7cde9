"""What a node keeps from one frame of a job to the next (its domain preloader, query
threads, early ray batches, the temporal statistics, the simplified model and portals), and
the load counters of one frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from vastray.actors.domain_loop import DomainLoop
from vastray.actors.job_options import JobOptions
from vastray.actors.node_work import NodeWork
from vastray.actors.preloader import DomainPreloader
from vastray.scene.bvh import query_pool
from vastray.scene.heap import rss_ceiling

if TYPE_CHECKING:  # loaded only by the schedulers that use them
    from vastray.scene.bvh import DomainBVH
    from vastray.schedule.portals import Portals
    from vastray.schedule.temporal import FrameStats


@dataclass
class NodeState:
    """What a node keeps from one frame of an animation to the next: its domain preloader (the
    domains it holds stay resident), its query threads, ray batches that arrived for a later
    frame, and the frame's position in the job (``ordinal``), which labels its tiles."""

    preloader: DomainPreloader | None = None
    pool: object = None
    ordinal: int = 0
    #: the first tile label of the next frame or pass (its tiles take the labels after).
    tile_base: int = 0
    #: the animation frame being rendered (0 for a single image): recording frames of
    #: portals are those divisible by the portal interval.
    frame: int = 0
    #: tile label -> ray batches received for a tile this node has not reached yet.
    early: dict = field(default_factory=dict)
    #: the temporal scheduler's statistics of the last frame, summed over the nodes.
    temporal_stats: FrameStats | None = None
    #: the simplified model, loaded once and never evicted.
    simplified_bvh: DomainBVH | None = None
    #: the virtual portals recorded in the last recording frame.
    portals: Portals | None = None

    def preloader_for(self, store, capacity: int, keep, options: JobOptions, rank: int,
                      fast_builds: bool = False) -> DomainPreloader:
        """The node's preloader, made on the first frame (its threads, preloading switch and
        emulated storage bandwidth from ``options``, the bandwidth of ``rank``, the bytes its
        cache may hold (``options.cache_bytes``) and the RSS above which its builds trim the
        heap from ``options.memory_limit``; its BVH builds
        the render's, ``RenderSetup.fast_builds``); a later frame asking for a larger
        ``capacity`` gets it (``DomainPreloader.reserve``)."""
        if self.preloader is None:
            self.pool = query_pool(options.threads)
            self.preloader = DomainPreloader(
                store, capacity, keep, pool=self.pool,
                load_bandwidth=options.load_bytes_per_second(rank), preload=options.preload,
                drop_page_cache=options.cold_reads, fast_builds=fast_builds,
                build_ahead=options.build_ahead, rss_ceiling=rss_ceiling(options.memory_limit),
                max_bytes=options.cache_bytes)
        else:
            self.preloader.reserve(capacity)
        return self.preloader

    def domain_loop(self, preloader: DomainPreloader, stats: dict) -> DomainLoop:
        """The loop the node activates domains through (the simulator's runs on virtual
        time)."""
        return DomainLoop(preloader, stats)

    def tile_loop(self, preloader: DomainPreloader, stats: dict) -> DomainLoop:
        """The loop the node's sort-first tiles run through (``sort_first.SortFirstTiles``):
        on the calling thread, the tile loop's own (the simulator's runs on virtual time)."""
        return DomainLoop(preloader, stats, offload=False)

    def node_work(self, management, rank: int, stats: dict, preloader: DomainPreloader,
                  max_batch: int) -> NodeWork:
        """The node's side of domain decomposition, keeping this state's early batches."""
        return NodeWork(management, rank, stats, preloader, max_batch, early=self.early)

    async def traced(self, radiance: dict[int, int], shadow: dict[int, int],
                     cpu_seconds: float = 0.0) -> None:
        """Hears of ray queries traced outside the domain loop (the in-situ iterations):
        domain -> radiance queries, domain -> shadow queries, and the CPU seconds the trace
        took. A real node has spent that time already; the simulator charges it."""

    async def decided(self, cpu_seconds: float) -> None:
        """Hears of CPU time spent deciding outside the domain loop (the in-situ iterations'
        speculative copies and their resolution). Real time has passed; the simulator
        charges it (``CostModel.decision_scale``)."""

    def threads(self) -> int:
        return self.pool._max_workers if self.pool is not None else 1

    def close(self) -> None:
        if self.preloader is not None:
            self.preloader.close()
        if self.pool is not None:
            self.pool.shutdown()


#: Load counters a frame reports: what the preloader did during the frame.
_LOAD_COUNTERS = ("loads", "preloads", "load_s", "load_wait_s", "bytes_loaded", "load_throttle_s")


def frame_load_stats(before: dict, after: dict) -> dict:
    """The preloader's counters over one frame (its totals run over the whole job)."""
    return {k: (round(after[k] - before[k], 4) if isinstance(after[k], float)
                else after[k] - before[k]) for k in _LOAD_COUNTERS}
