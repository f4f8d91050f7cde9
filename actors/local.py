"""The out-of-core runtime of one process (and of each sort-first node): tiles of paths, each
traced by the ``image`` or ``spec-ooc`` schedule through the one domain loop over a bounded
domain cache with its preloading thread; passes merged as the progression asks."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

import numpy as np

from vastray.actors.domain_loop import DomainLoop, ScheduleOrder
from vastray.actors.job_options import JobOptions, JobOptionsError
from vastray.actors.node_state import NodeState
from vastray.actors.preloader import DomainPreloader
from vastray.actors.render_setup import RenderSetup
from vastray.processes import disk_read_bytes, peak_rss_bytes
from vastray.render.driver import (
    RenderResult,
    path_context,
    run_passes,
)
from vastray.render.film import Film
from vastray.render.integrators import (
    PathContext,
    PathResult,
    RenderSettings,
    camera_rays,
)
from vastray.render.progress import RenderBar
from vastray.render.progressive import Progression
from vastray.render.scene_config import SceneConfig
from vastray.scene.bvh import query_pool
from vastray.scene.cache import CacheStats
from vastray.scene.store import Store
from vastray.schedule import registry
from vastray.schedule.belady import belady_loads
from vastray.schedule.image import ImageSchedule
from vastray.schedule.ownership import sort_first_tiles
from vastray.schedule.registry import Runtime
from vastray.schedule.spec_ooc import SpeculationRules, SpeculativeSchedule

log = logging.getLogger(__name__)



def tile_schedule(options: JobOptions, setup: RenderSetup, ctx: PathContext,
                  ablation: SpeculationRules | None = None):
    """A tile's schedule (``ImageSchedule``, or ``SpeculativeSchedule`` for a scheduler that
    speculates), as ``options`` (and ``ablation``) configure it."""
    if not registry.spec(options.scheduler).speculates:
        return ImageSchedule(ctx, setup.geometry, setup.color_source, setup.scalar_range,
                             resident_first=options.resident_first)
    rules = ablation or SpeculationRules()
    return SpeculativeSchedule(ctx, setup.geometry, setup.color_source, setup.scalar_range,
                               history_depth=options.history_depth,
                               resident_first=options.resident_first,
                               serve_before_evict=rules.serve_before_evict,
                               rescore=rules.rescore)


def render_out_of_core(store: Store, config: SceneConfig, settings: RenderSettings,
                       options: JobOptions | None = None, *, progress: bool = True,
                       share: tuple[int, int] = (0, 1),
                       on_tile: Callable[[int], None] | None = None,
                       ablation: SpeculationRules | None = None,
                       progression: Progression | None = None,
                       state: NodeState | None = None) -> RenderResult:
    """Render one node's image out of core with the ``image`` or ``spec-ooc`` schedule.

    Parameters
    ----------
    options : the job's options (default: ``JobOptions()``, the ``image`` schedule). This
        runtime reads ``scheduler`` (``"image"``, the baseline, or ``"spec-ooc"``, SpRay's
        speculative schedule), ``cache`` (most domains in memory; None: all),
        ``max_samples_in_flight`` (paths traced at once: the tile; None: all),
        ``history_depth`` (spec-ooc's H), ``preload`` (load the schedule's guess at its next
        domain, ``likely_next``, on a background thread while rendering the current one;
        False loads sequentially, as the papers do), ``resident_first`` (let the schedule
        serve domains in memory before loading others; False is the papers' order, SpRay
        Listings 1 and 2), ``threads`` (threads every Embree query splits its rays over) and
        ``load_bandwidth`` (emulated storage: every load takes at least its size over the
        bandwidth of rank ``share[0]``) and ``cold_reads`` (every load a real disk read).
    share : (k, n): render only tiles k, k + n, k + 2n, ... (sort-first split over n nodes).
    on_tile : called with the number of paths after each finished tile (progress reports).
    ablation : spec-ooc's own rules switched off (``SpeculationRules``), for ablations;
        None: all on.
    progression : render in the sample-major passes it asks for (``driver.render``'s);
        None: the whole of ``settings.spp`` at once (or the pass ``settings`` name).
    state : a node's state kept from pass to pass and frame to frame: its domain preloader
        (the domains it holds stay resident for the next pass, issue 40) and query threads;
        None: this call's own, closed at its end. The counters are this call's either way.
    """
    options = JobOptions() if options is None else options
    scheduler = options.scheduler
    sched = registry.find(scheduler)
    if sched is None or sched.runtime is not Runtime.TILES:
        raise JobOptionsError(f"the out-of-core runtime runs "
                              f"{' or '.join(registry.running(Runtime.TILES))}, not "
                              f"{scheduler!r} (the domain schedulers need --nodes N; the "
                              "in-core reference is vastray.render.driver.render)")
    if ablation is not None and not sched.speculates:
        raise JobOptionsError(f"the ablation {ablation} is of spec-ooc's rules, not {scheduler}'s")
    start = time.perf_counter()
    read_before = disk_read_bytes()
    setup = RenderSetup.of(store, config, settings)
    capacity = options.cache or max(len(store.domains), 1)
    bandwidth = options.load_bytes_per_second(share[0])
    if state is None:  # this call's own cache and threads
        pool = query_pool(options.threads)
        preloader = DomainPreloader(store, capacity, setup.keep, pool=pool,
                                    load_bandwidth=bandwidth, preload=options.preload,
                                    drop_page_cache=options.cold_reads)
    else:  # the node's, kept from pass to pass (what it holds is not loaded again)
        preloader = state.preloader_for(store, capacity, setup.keep, options, share[0])
        pool = state.pool
    before = _cache_counts(preloader.cache.stats)
    counters: dict = {}
    loop = DomainLoop(preloader, counters, offload=False)  # nothing else to serve meanwhile
    tile_limit = options.max_samples_in_flight
    tile = 1

    def trace_tile(ctx: PathContext, bar) -> PathResult:
        """Trace the paths of ``ctx`` through the domains in the schedule's order."""
        policy = tile_schedule(options, setup, ctx, ablation)
        policy.start(camera_rays(setup.camera, ctx))
        runner.run(loop.run(ScheduleOrder(policy, preloader, evicting=sched.evicts,
                                          by_demand=options.eviction == "demand")))
        _merge(counters, policy.counters)
        bar.update(len(ctx.pixel))
        if on_tile is not None:
            on_tile(len(ctx.pixel))
        return policy.result

    def trace_pass(window: RenderSettings, bar) -> Film:
        """The film of one pass (``window.samples``): this node's share of its tiles."""
        nonlocal tile
        film = Film(window.width, window.height)
        total = window.paths
        size = max(1, min(tile_limit or total, total))
        tile = max(tile, size)  # reported: the largest tile of any pass
        for first in sort_first_tiles(total, size, *share):
            ctx = path_context(setup.shading, window, first, min(first + size, total),
                               setup.ao_distance)
            film.add_paths(ctx.pixel, ctx.sample, trace_tile(ctx, bar))
        return film

    def trace_passes_together(bar) -> Film:
        """Every pass left, in tiles that run on from one pass into the next (a domain is
        loaded once per tile, not once per pass); each pass is merged once its last tile is
        done."""
        nonlocal tile
        spans = PassSpans(progression, settings)
        size = max(1, min(tile_limit or spans.total, spans.total))
        tile = max(tile, size)
        for first in sort_first_tiles(spans.total, size, *share):
            stop = min(first + size, spans.total)
            ctx, passes = spans.context(setup.shading, first, stop, setup.ao_distance)
            spans.add(ctx, passes, trace_tile(ctx, bar), stop)
        spans.add_rest()  # passes in other nodes' tiles only, and those after this node's last
        return progression.film

    # passes measured against a reference are rendered apart, so each pass's error comes
    # with the time it ended (a curve, not one point); the others run on across passes
    fused = (progression is not None and not progression.rules.paced
             and getattr(progression, "reference", None) is None)
    try:
        with (asyncio.Runner() as runner,
              RenderBar(total=settings.paths, unit="path", unit_scale=True, delay=2.0,
                        disable=not progress, desc=f"render ({scheduler})", leave=False) as bar):
            film = (trace_passes_together(bar) if fused
                    else run_passes(trace_pass, settings, progression, bar))
    finally:
        if state is None:
            preloader.close()
            if pool is not None:
                pool.shutdown()
    wall = time.perf_counter() - start
    stats = _CallStats(preloader.cache.stats, before)
    for name in ("radiance_tests", "shadow_tests", "shade_s"):  # a share of no tiles
        counters.setdefault(name, 0)
    render_seconds = counters.pop("trace_s")
    schedule_seconds = counters.pop("schedule_s")
    counters.update({
        "scheduler": scheduler,
        "domains": len(store.domains),
        "distinct_domains_loaded": len(stats.loaded_domains),
        "domains_traced": len(loop.traced_domains),
        "cache_capacity": capacity,
        "max_samples_in_flight": tile,
        "threads": pool._max_workers if pool is not None else 1,
        "load_bandwidth_mb_s": None if bandwidth is None else bandwidth / 1e6,
        **stats.as_dict(),
        "untraced_loads": stats.loads - len(loop.productive_loads),
        "activations": len(loop.sequence),
        "belady_loads": belady_loads(loop.sequence, capacity),
        "peak_rss_bytes": peak_rss_bytes(),
        # what storage delivered (the page cache's share not counted): with cold_reads about
        # bytes_loaded; None where the kernel does not say
        "disk_read_bytes": None if read_before is None else disk_read_bytes() - read_before,
    })
    seconds = {
        "total": round(wall, 4),
        "load": round(stats.load_seconds, 4),
        "load_wait": round(stats.wait_seconds, 4),
        "render": round(render_seconds, 4),
        "schedule": round(schedule_seconds, 4),
    }
    return RenderResult(film, setup.camera, seconds, counters)


class PassSpans:
    """The passes a progression has left, as one run of path ids: pass after pass, each
    pixel-major within (as ``path_context`` numbers them), so that a tile may run on from the
    end of one pass into the next.

    Parameters
    ----------
    progression : the passes (none of which may stop early: ``StopRules.paced`` False).
    settings : the render's settings.
    """

    def __init__(self, progression: Progression, settings: RenderSettings):
        self.progression, self.settings = progression, settings
        done = progression.snapshot.passes_done
        self.windows = progression.remaining()
        self.index = np.arange(done, done + len(self.windows))  # (K,) pass numbers
        self.first = np.array([w[0] for w in self.windows], np.int64)  # (K,) first sample
        self.per_pixel = np.array([w[1] - w[0] for w in self.windows], np.int64)  # (K,)
        paths = settings.width * settings.height * self.per_pixel
        self.offsets = np.concatenate([[0], np.cumsum(paths)])  # (K + 1,) first path id
        self.total = int(self.offsets[-1])
        self.films: dict[int, Film] = {}
        self.merged = 0  # passes of ``windows`` merged so far
        progression.start()

    def context(self, shading, first: int, stop: int, ao_distance: float
                ) -> tuple[PathContext, np.ndarray]:
        """The paths ``first <= id < stop`` and (n,) the position in ``windows`` of each's
        pass."""
        ids = np.arange(first, stop, dtype=np.int64)
        k = np.searchsorted(self.offsets, ids, side="right") - 1
        local = ids - self.offsets[k]
        pixel = (local // self.per_pixel[k]).astype(np.uint32)
        sample = (self.first[k] + local % self.per_pixel[k]).astype(np.uint32)
        return PathContext(shading, self.settings, pixel, sample, ao_distance), k

    def add(self, ctx: PathContext, passes: np.ndarray, result: PathResult, stop: int) -> None:
        """Add the traced tile of the paths up to id ``stop`` to its passes' films, and merge
        every pass it completes (tiles come in order)."""
        for k in np.unique(passes):
            rows = np.nonzero(passes == k)[0]
            if int(k) not in self.films:
                self.films[int(k)] = Film(self.settings.width, self.settings.height)
            self.films[int(k)].add_paths(ctx.pixel[rows], ctx.sample[rows], PathResult(
                result.radiance[rows], result.first_t[rows], result.first_normal[rows]))
        while self.merged < len(self.windows) and self.offsets[self.merged + 1] <= stop:
            self._merge_next()
        if self.merged == len(self.windows):
            self.progression.next_pass()  # says why it stops: every pass is in

    def add_rest(self) -> None:
        """Merge the passes not merged yet, once this process traced its last tile: a node's
        share of the tiles (every ``size``-th) may end before the last pass does, or miss a
        pass whole (its film then holds no path). Ends as ``add`` does."""
        if self.merged == len(self.windows) and self.total:
            return  # the last tile merged every pass and said why it stops
        while self.merged < len(self.windows):
            self._merge_next()
        self.progression.next_pass()  # says why it stops (also when resumed with none left)

    def _merge_next(self) -> None:
        step = self.progression.next_pass()
        if step is None or step[0] != self.index[self.merged]:
            raise RuntimeError(f"pass {self.index[self.merged]} is not the next one")
        film = self.films.pop(self.merged, None)
        if film is None:  # no path of this pass among this process's tiles
            film = Film(self.settings.width, self.settings.height)
        self.progression.add_pass(step[0], film)
        self.merged += 1


#: The cache counters that are totals over a cache's life (a call reports its own share).
_CACHE_TOTALS = ("loads", "hits", "evictions", "load_seconds", "read_seconds", "build_seconds",
                 "preloads", "wait_seconds", "bytes_loaded", "throttle_seconds")


def _cache_counts(stats: CacheStats) -> dict:
    """What ``_CallStats`` subtracts: the totals so far and the domains loaded so far."""
    return {**{name: getattr(stats, name) for name in _CACHE_TOTALS},
            "loaded_domains": set(stats.loaded_domains)}


class _CallStats(CacheStats):
    """A cache's counters over one call: ``stats`` less the totals ``before`` it
    (``_cache_counts``); peaks are the cache's own."""

    def __init__(self, stats: CacheStats, before: dict):
        super().__init__(**{name: getattr(stats, name) - before[name]
                            for name in _CACHE_TOTALS},
                         loaded_domains=stats.loaded_domains - before["loaded_domains"],
                         peak_resident_bytes=stats.peak_resident_bytes,
                         peak_resident_domains=stats.peak_resident_domains)


def _merge(total: dict, part: dict) -> None:
    for key, value in part.items():
        if key.endswith("_peak"):
            total[key] = max(total.get(key, 0), value)
        else:
            total[key] = total.get(key, 0) + value
