"""The out-of-core runtime of one process (and of each sort-first node): tiles of paths, each
traced by the ``image`` or ``spec-ooc`` schedule through the one domain loop over a bounded
domain cache with its preloading thread; passes merged as the progression asks. The tile loop
itself is ``sort_first.SortFirstTiles``, which the simulator runs too."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

from vastray.actors.job_options import JobOptions, JobOptionsError
from vastray.actors.node_state import NodeState
from vastray.actors.render_setup import RenderSetup
from vastray.actors.sort_first import PassSpans, SortFirstTiles, tile_cache_capacity
from vastray.processes import disk_read_bytes, peak_rss_bytes, stoppable
from vastray.render.driver import RenderResult, run_passes
from vastray.render.integrators import RenderSettings
from vastray.render.progress import RenderBar
from vastray.render.progressive import Progression
from vastray.render.scene_config import SceneConfig
from vastray.scene.store import Store
from vastray.schedule import registry
from vastray.schedule.belady import belady_loads
from vastray.schedule.registry import Runtime
from vastray.schedule.spec_ooc import SpeculationRules

log = logging.getLogger(__name__)


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
    capacity = tile_cache_capacity(options, store)
    own = state is None  # else the node's, kept from pass to pass (what it holds stays)
    state = NodeState() if own else state
    preloader = state.preloader_for(store, capacity, setup.keep, options, share[0],
                                    setup.fast_builds)
    bandwidth = options.load_bytes_per_second(share[0])
    counters: dict = {}
    loop = state.tile_loop(preloader, counters)
    # passes measured against a reference are rendered apart, so each pass's error comes
    # with the time it ended (a curve, not one point); the others run on across passes
    fused = (progression is not None and not progression.rules.paced
             and getattr(progression, "reference", None) is None)
    try:
        with (asyncio.Runner() as runner,
              RenderBar(total=settings.paths, unit="path", unit_scale=True, delay=2.0,
                        disable=not progress, desc=f"render ({scheduler})", leave=False) as bar):
            tiles = SortFirstTiles(options, setup, loop, share, ablation,
                                   on_tile=_tile_reports(bar, on_tile), counters=counters)
            if fused:
                film = runner.run(stoppable(tiles.render_passes(PassSpans(progression,
                                                                          settings))))
            elif (progression is not None and capacity < len(store.domains)
                  and options.trace_ahead):
                # passes apart, out of core: the next passes traced on the current one's
                # loads (under a time limit, those its rule may still grant)
                film = runner.run(stoppable(tiles.render_ahead(progression, settings)))
                if progression.stopped_by != "spp":  # the bar ends where the render does
                    bar.total = bar.n
            else:
                film = run_passes(lambda window, _: runner.run(stoppable(
                    tiles.render_pass(window))),
                                  settings, progression, bar)
    finally:
        if own:
            state.close()
    wall = time.perf_counter() - start
    stats = tiles.cache_stats()
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
        "cache_bytes": preloader.cache.max_bytes,
        "max_samples_in_flight": tiles.tile,
        "threads": state.threads(),
        "load_bandwidth_mb_s": None if bandwidth is None else bandwidth / 1e6,
        **stats.as_dict(),
        "untraced_loads": stats.loads - len(loop.productive_loads),
        "loads_under_100_queries": loop.loads_serving_under(stats.loads, 100),
        "loads_under_1000_queries": loop.loads_serving_under(stats.loads, 1000),
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


def _tile_reports(bar, on_tile: Callable[[int], None] | None) -> Callable[[int], None]:
    """What a finished tile of ``paths`` paths tells: the progress bar, then ``on_tile``."""
    def finished(paths: int) -> None:
        bar.update(paths)
        if on_tile is not None:
            on_tile(paths)
    return finished
