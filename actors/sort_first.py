"""The sort-first tile loop, one implementation for one process (``local.render_out_of_core``),
the sort-first nodes (which run it) and the simulator (``vastray.sim``): which tiles of which
passes a node traces (its share of the image-plane blocks, ``sort_first_tile_paths``), how
each tile's schedule is made and started, and how its paths enter the films. How a schedule's
activations run is the caller's: the domain loop it hands in (a ``DomainLoop`` over a real
cache and its preloading thread, or the simulator's ``VirtualDomainLoop`` on virtual time)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from vastray.actors.domain_loop import DomainLoop, LeadOrder, ScheduleOrder
from vastray.actors.job_options import JobOptions
from vastray.actors.render_setup import RenderSetup
from vastray.render.driver import paths_context
from vastray.render.film import FILM_BYTES_PER_PIXEL, Film
from vastray.render.integrators import (
    PathContext,
    PathResult,
    RenderSettings,
    launched_camera_rays,
)
from vastray.render.progressive import Progression
from vastray.scene.cache import CacheStats
from vastray.scene.store import Store
from vastray.schedule import image_cost, registry
from vastray.schedule.image import ImageSchedule
from vastray.schedule.image_cost import SweepWeights, pixel_weights
from vastray.schedule.ownership import sort_first_sweep_paths
from vastray.schedule.spec_ooc import SpeculationRules, SpeculativeSchedule


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


def tile_cache_capacity(options: JobOptions, store: Store) -> int:
    """Most domains a sort-first node holds: ``options.cache``, or all of the store's."""
    return options.cache or max(len(store.domains), 1)


#: Activations of a render with passes apart before its later passes may be traced ahead
#: (``SortFirstTiles.render_ahead``): enough to tell whether loads or traces take its time.
AHEAD_AFTER = 4
#: Most bytes of films of the passes traced ahead hold at once (a film of each such pass
#: with tiles in flight or done): past it, no other pass's tile starts. A pass is then most
#: of a tile or more, and passes apart cost little more than one pass's loads anyway.
AHEAD_FILM_BYTES = 256 << 20


class SortFirstTiles:
    """A node's share of the sort-first tiles of a pass, or of several passes swept together.

    Parameters
    ----------
    options : the job's options (``scheduler``, ``max_samples_in_flight``: the tile,
        ``eviction``, and what ``tile_schedule`` reads).
    setup : the render's set-up.
    loop : the domain loop every tile's schedule runs through (its ``preloader``: the node's
        cache, whose counters from now on ``cache_stats`` gives).
    share : (k, n): node k of n, rendering its share of every sweep's image-plane blocks
        (``ownership.sort_first_tile_paths``).
    ablation : spec-ooc's rules switched off (None: all on).
    on_tile : called with the number of paths after each finished tile.
    counters : where each tile's schedule counters are summed (default: a dict of its own).
    """

    def __init__(self, options: JobOptions, setup: RenderSetup, loop: DomainLoop,
                 share: tuple[int, int] = (0, 1), ablation: SpeculationRules | None = None,
                 on_tile: Callable[[int], None] | None = None, counters: dict | None = None):
        if loop.preloader.capacity >= len(setup.geometry.ids):
            # Occupancy masks keep a ray out of a domain whose box it crosses only through
            # empty cells: out of core they save that domain's load. A cache holding every
            # domain loads each once whatever the masks say, so there their test only
            # costs (10-30 % of such renders' CPU, bench/README "masks.py"); the image is
            # the same either way.
            setup = setup.without_masks()
        self.options, self.setup, self.loop, self.share = options, setup, loop, share
        self.ablation, self.on_tile = ablation, on_tile
        self.counters = {} if counters is None else counters
        self.preloader = loop.preloader
        #: the largest tile of any sweep (paths)
        self.tile = 1
        self._before = _cache_counts(self.preloader.cache.stats)
        self._pixel_weights = None  # (W * H,) int64, ``image_cost.pixel_weights``, on demand

    async def trace(self, ctx: PathContext) -> PathResult:
        """Trace the paths of ``ctx`` through the domains in their schedule's order."""
        policy = self._started(ctx)
        await self.loop.run(self._order(policy))
        self._finished(policy, len(ctx.pixel))
        return policy.result

    def _started(self, ctx: PathContext):
        """A tile's schedule, its camera rays queued."""
        policy = tile_schedule(self.options, self.setup, ctx, self.ablation)
        self.loop.start_tile(policy, launched_camera_rays(self.setup.camera, ctx, policy.result))
        return policy

    def _order(self, policy) -> ScheduleOrder:
        return ScheduleOrder(policy, self.preloader,
                             evicting=registry.spec(self.options.scheduler).evicts,
                             by_demand=self.options.eviction == "demand")

    def _finished(self, policy, paths: int | None) -> None:
        """Count a tile's schedule; ``paths`` (None: a tile given up) go to ``on_tile``."""
        _merge(self.counters, policy.counters)
        if self.on_tile is not None and paths is not None:
            self.on_tile(paths)

    async def render_pass(self, window: RenderSettings) -> Film:
        """The film of one pass (``window.samples``): this node's share of its tiles."""
        film = Film(window.width, window.height)
        for ids in self._tiles(window.paths, [window.samples[1] - window.samples[0]]):
            ctx = paths_context(self.setup.shading, window, ids, self.setup.ao_distance)
            film.add_paths(ctx.pixel, ctx.sample, await self.trace(ctx))
        return film

    async def render_passes(self, spans: PassSpans) -> Film:
        """Every pass of ``spans``, in tiles that run on from one pass into the next (a domain
        is loaded once per tile, not once per pass); each pass is merged into the
        progression once its last tile is done. Returns the progression's film."""
        for ids in self._tiles(spans.total, spans.per_pixel):
            ctx, passes = spans.context(self.setup.shading, ids, self.setup.ao_distance)
            spans.add(ctx, passes, await self.trace(ctx), int(ids[-1]) + 1)
        spans.add_rest()  # passes in other nodes' tiles only, and those after this node's last
        return spans.progression.film

    async def render_ahead(self, progression: Progression, settings: RenderSettings) -> Film:
        """Passes apart (``progression`` may stop after any, or wants each one's error as it
        ends), out of core, with later passes traced ahead where loads are most of the time.

        A tile of the current pass leads: its schedule alone chooses the domains, so the
        pass ends as soon as its own rays do. Tiles after it ride along, as many as fit in
        the tile's paths beside it: each activation also traces the rays they have waiting
        for its domain, at no load of their own (``LeadOrder``). The tiles of the current
        pass and of the next one ride; those of later passes once the render has waited for
        loads at least as long as it traced (from its ``AHEAD_AFTER``-th activation): their
        traces then delay the current pass less than the loads they save would cost. Other
        passes' tiles start only while their films fit in ``AHEAD_FILM_BYTES``, and only
        while the progression's time rule may still grant their pass
        (``Progression.may_grant``; each pass is merged with the seconds it spent on later
        passes and those each pass was traced ahead of its turn, so that a time limit's rule
        predicts each pass as if swept alone, less what was traced of it ahead). Where
        traces take most of the time, the current pass ends later by at most its riders'
        traces, and each pass's error still comes early.

        A pass's film is merged as its last tile ends and the progression rules on the next
        pass; where it stops, the tiles traced ahead are given up (``given_up_paths``).
        Alone, each pass swept the domains anew: 2.9-4.1x one pass's loads at a quarter cache
        where a pass is less than a tile; traced ahead, 1.2-1.3x where loads take the time
        and 2.5-2.9x where traces do (``tests/test_pass_loads.py``). Returns the
        progression's film.

        Bit for bit the films of passes traced one after another: a path's radiance does not
        depend on which tile or activation traces it, nor a film on the order of its paths.
        """
        step = progression.next_pass()
        if step is None:
            return progression.film
        cap = self.options.max_samples_in_flight or np.inf
        current = step[0]
        films: dict[int, Film] = {}  # pass -> the film of its tiles done so far
        tiles = self._tiles_of_passes(progression, settings, current)
        following = next(tiles, None)  # (pass, window, path ids), or (pass, None, None): its end
        in_flight: dict[int, int] = {}  # pass -> its tiles started and not finished
        enumerated: set[int] = set()  # passes whose every tile has started
        flight: list = []  # (pass, paths context, schedule), the leader first
        riders: list = []  # the schedules of flight[1:]
        waited, traced = self.preloader.cache.stats.wait_seconds, self.loop.stats["trace_s"]
        activations = len(self.loop.sequence)
        film_bytes = settings.width * settings.height * FILM_BYTES_PER_PIXEL
        pass_of: dict[int, int] = {}  # id of a rider's schedule -> its pass
        # pass -> seconds its rays were traced before it led, in the leader runs done; and
        # that sum over the passes after the current one when it was granted
        rode: dict[int, float] = {}
        before = 0.0
        order = None  # the leader run under way

        def traced_now() -> dict[int, float]:
            """``rode`` with the leader run under way's riders."""
            now = dict(rode)
            for key, seconds in ({} if order is None else order.follower_seconds).items():
                if pass_of[key] != current:
                    now[pass_of[key]] = now.get(pass_of[key], 0.0) + seconds
            return now

        def time_rule(now: dict[int, float], passes: int) -> dict:
            """What the time rule predicts from (``Progression.add_pass``): the current
            pass's seconds spent on later passes, and what each of ``passes`` passes from
            the current one had traced ahead of its turn."""
            later = sum(seconds for k, seconds in now.items() if k > current)
            return {"ahead_seconds": later - before,
                    "traced_ahead": [now.get(current + j, 0.0) for j in range(passes)]}

        def loads_dominate() -> bool:
            return (len(self.loop.sequence) - activations >= AHEAD_AFTER
                    and self.preloader.cache.stats.wait_seconds - waited
                    >= self.loop.stats["trace_s"] - traced)

        def films_fit(index: int) -> bool:
            ahead = {k for k, _, _ in flight} | set(films) | {index}
            ahead.discard(current)
            return len(ahead) * film_bytes <= AHEAD_FILM_BYTES

        def start_following() -> None:
            """Start the tiles that may go now, in order."""
            nonlocal following
            while following is not None:
                index, window, ids = following
                if ids is None:
                    enumerated.add(index)
                elif flight and (sum(len(c.pixel) for _, c, _ in flight) + len(ids) > cap
                                 or index != current and not films_fit(index)
                                 or index > current + 1 and not loads_dominate()
                                 or not progression.may_grant(
                                     index, **time_rule(traced_now(), index - current + 1))):
                    return
                else:
                    ctx = paths_context(self.setup.shading, window, ids, self.setup.ao_distance)
                    flight.append((index, ctx, self._started(ctx)))
                    pass_of[id(flight[-1][2])] = index
                    if len(flight) > 1:
                        riders.append(flight[-1][2])
                    in_flight[index] = in_flight.get(index, 0) + 1
                following = next(tiles, None)

        while True:
            start_following()
            if current in enumerated and not in_flight.get(current):
                progression.add_pass(current, films.pop(current, None)
                                     or Film(settings.width, settings.height),
                                     **time_rule(rode, len(progression.passes) - current))
                step = progression.next_pass()
                if step is None:
                    break
                current = step[0]
                before = sum(seconds for k, seconds in rode.items() if k > current)
                continue
            index, ctx, policy = flight[0]  # leads, in flight until it is done
            order = LeadOrder(self._order(policy), riders, self.preloader.resident,
                              start_following)
            await self.loop.run(order)
            rode = traced_now()
            _merge(self.counters, {"ahead_queries": order.ahead_queries})
            order = None
            flight.pop(0)
            if riders:
                riders.pop(0)  # the next leader
            self._finished(policy, len(ctx.pixel))
            if index not in films:
                films[index] = Film(settings.width, settings.height)
            films[index].add_paths(ctx.pixel, ctx.sample, policy.result)
            in_flight[index] -= 1
        for _, ctx, policy in flight:  # traced ahead of a pass the rules stopped before
            self._finished(policy, None)
            _merge(self.counters, {"given_up_paths": len(ctx.pixel)})
        return progression.film

    def _tiles_of_passes(self, progression: Progression, settings: RenderSettings, first: int):
        """This node's tiles of passes ``first``, ``first`` + 1, ... of ``progression``, in
        order, as (pass, its window, (n,) path ids), each pass's followed by (pass, None,
        None)."""
        for index in range(first, len(progression.passes)):
            window = settings.window(*progression.passes[index])
            for ids in self._tiles(window.paths, [window.samples[1] - window.samples[0]]):
                yield index, window, ids
            yield index, None, None

    def cache_stats(self) -> CacheStats:
        """The cache's counters since this object was made (peaks: the cache's own)."""
        return _CallStats(self.preloader.cache.stats, self._before)

    def _tiles(self, total: int, per_pixel):
        """This node's tiles of a sweep of ``total`` paths, each (n,) path ids: passes of
        (K,) ``per_pixel`` samples a pixel, each pass shared among the nodes as it would be
        alone (``ownership.sort_first_sweep_paths``), its bands cut at equal estimated cost
        (``image_cost``) where the scheduler's are (``image_cost.CUT_BY_COST``)."""
        per_pixel = np.asarray(per_pixel, np.int64)
        pixels = total // max(int(per_pixel.sum()), 1)
        weights = None
        if self.share[1] > 1 and self.options.scheduler in image_cost.CUT_BY_COST:
            if self._pixel_weights is None:  # once: the camera and boxes do not change
                self._pixel_weights = pixel_weights(self.setup.camera, self.setup.geometry,
                                                    self.setup.camera.width,
                                                    self.setup.camera.height)
            weights = SweepWeights(self._pixel_weights, per_pixel).of_pass
        for ids in sort_first_sweep_paths(pixels * per_pixel,
                                          self.options.max_samples_in_flight or total,
                                          *self.share, weight_before_pass=weights):
            self.tile = max(self.tile, len(ids))
            yield ids


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

    def context(self, shading, ids: np.ndarray, ao_distance: float
                ) -> tuple[PathContext, np.ndarray]:
        """The paths ``ids`` ((n,) int64, ascending) and (n,) the position in ``windows`` of
        each's pass."""
        k = np.searchsorted(self.offsets, ids, side="right") - 1
        local = ids - self.offsets[k]
        pixel = (local // self.per_pixel[k]).astype(np.uint32)
        sample = (self.first[k] + local % self.per_pixel[k]).astype(np.uint32)
        return PathContext(shading, self.settings, pixel, sample, ao_distance), k

    def add(self, ctx: PathContext, passes: np.ndarray, result: PathResult, stop: int) -> None:
        """Add the traced tile whose last path is ``stop - 1`` to its passes' films, and merge
        every pass this node's tiles complete (they come in path order)."""
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
                 "preloads", "wait_seconds", "bytes_loaded", "throttle_seconds", "reads_ahead",
                 "reads_ahead_used", "builds_ahead", "builds_ahead_used", "heap_trims")


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
