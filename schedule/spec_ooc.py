"""SpRay's speculative out-of-core schedule (Park et al., Listings 2-4).

Every ray is queued at once into *every* domain its path enters ("speculative queuing"), so a
domain, once loaded, serves all the rays that may need it instead of waiting for them to arrive
one domain at a time. A radiance ray that hits something in a domain is shaded right away, even
though a closer hit may still turn up in another domain: its shadow and continuation rays are
speculative. Correctness comes from the **history buffer**: for every path and depth it holds
the closest (t, domain) found so far, and every speculative ray carries the (t, domain) of the
hits it descends from. A ray whose history no longer matches the buffer was spawned from a hit
that lost, and is dropped (wasted); a shadow ray brings its light only once every hit it
descends from is final and still matches.

Per round, domains are processed in order of the **front-to-back traversal score**
``Score[i] = sum_j (M - j) * Counter[i][j]``, where ``Counter[i][j]`` counts queued rays for which
domain i is the j-th box along the ray (``traversal_order``). Before a domain is loaded its rays
are **filtered** (Listing 2, lines 15-19): radiance rays whose closest hit so far is nearer than
the domain, rays with a stale history and shadow rays already found occluded are dropped, and a
domain left with nothing to trace is skipped without a load. Unoccluded shadow rays that have
visited all their domains are **committed**; at the end of a round the **retire** queue
(committed in the previous round) is resolved against the history buffer, and the queues swap
(double buffering).

The **history depth** H bounds speculation across bounces: a window holds H + 1 path vertices;
continuation rays beyond it wait in the **spill queue** until the window is resolved.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit

from vastray.render.integrators import (
    PathContext,
    PathResult,
    RadianceRays,
    ShadowRays,
    shade,
)
from vastray.render.tracer import NO_DOMAIN, ClosestHits
from vastray.schedule.geometry import DomainGeometry
from vastray.schedule.paths import RADIANCE_FIELDS, as_radiance, as_shadow, shadow_soa
from vastray.schedule.soa import DomainQueues, GrowingArray, SoA, index_of


@dataclass(frozen=True)
class SpeculationRules:
    """Our two additions to SpRay's order, each switched off for ablations (``bench/ooc.py``):
    ``serve_before_evict`` and ``rescore``, as ``SpeculativeSchedule`` describes them."""

    serve_before_evict: bool = True
    rescore: bool = True


class SpeculativeSchedule:
    """Speculative out-of-core scheduling of one tile of paths.

    Parameters
    ----------
    ctx : the tile's paths.
    geometry : domain boxes.
    color_source, scalar_range : what hit records interpolate.
    history_depth : H, bounces speculated per window (default: every bounce of the path).
    resident_first : start each round with the domains in memory (``next_domain``'s
        ``resident``) and serve a resident domain again when rays reach it after its turn,
        before anything new is loaded. False is the paper's pure score order. Default True.
    serve_before_evict : with ``resident_first``, serve a resident domain's new rays when the
        cache is about to evict it (``next_domain``'s ``victim``) rather than as soon as they
        arrive: the same loads are avoided with fewer, larger batches. Default True.
    rescore : with ``resident_first``, re-rank the rest of a round by the traversal scores of
        now before each pick (the paper ranks a round once, Listing 2, line 12): rays queued
        during the round count for the domains they will reach. Default True.
    """

    name = "spec-ooc"

    def __init__(self, ctx: PathContext, geometry: DomainGeometry, color_source: str | None,
                 scalar_range: tuple[float, float], history_depth: int | None = None,
                 resident_first: bool = True, serve_before_evict: bool = True,
                 rescore: bool = True):
        self.rescore = rescore
        self.resident_first = resident_first
        self.serve_before_evict = serve_before_evict
        self._victim_of: Callable[[], int | None] | None = None
        #: The domain ``next_domain`` chose because the cache evicts it next (served before
        #: it goes), None for any other choice: its use must leave it the cache's victim.
        self.parting: int | None = None
        self.ctx = ctx
        self.geometry = geometry
        self.color_source = color_source
        self.scalar_range = scalar_range
        bounces = ctx.settings.bounces if ctx.settings.integrator == "pt" else 0
        self.window = 1 + max(0, min(bounces, bounces if history_depth is None else history_depth))
        n_paths, n_domains = len(ctx.pixel), geometry.n_domains
        self.result = PathResult.empty(n_paths)
        # History buffer: closest (t, domain) per path and window depth, and how many queued
        # radiance-ray visits could still change it.
        self.hbuf_t = np.full((n_paths, self.window), np.inf, np.float32)
        self.hbuf_d = np.full((n_paths, self.window), NO_DOMAIN, np.int32)
        self.pending = np.zeros((n_paths, self.window), np.int32)
        self.first_normal = np.zeros((n_paths, 3), np.float32)
        self.window_start = 0
        self.radiance = DomainQueues(n_domains)
        self.shadow = DomainQueues(n_domains)
        # SpRay's traversal score, Score[i] = sum_j (M - j) Counter[i][j] (M = D), kept up to
        # date as rays are queued and taken: Counter itself, (D, D), was 16 MB a tile at
        # 1,439 domains and every rescore multiplied all of it
        self.score = np.zeros(n_domains, np.int64)
        self._depth_weight = max(n_domains, 1)
        self._ranked_for: frozenset[int] | None = None  # resident set the schedule is ranked for
        self.spill: list[SoA] = []
        self.commit: list[SoA] = []
        self.retire: list[SoA] = []
        # Per shadow ray (by id): domain visits outstanding, and whether it is blocked.
        self._shadow_pending = GrowingArray(np.int32)
        self._shadow_blocked = GrowingArray(np.bool_)
        self._schedule: list[int] = []
        self._resident: frozenset[int] = frozenset()
        # The domain chosen by next_domain, with its filtered rays: (domain, radiance, shadow).
        self._staged: tuple[int, SoA | None, SoA | None] | None = None
        self._camera: RadianceRays | None = None
        self.counters = {
            "radiance_tests": 0, "shadow_tests": 0, "speculative_rays": 0,
            "wasted_rays": 0, "filtered_rays": 0, "rounds": 0, "windows": 0,
            "rays_in_flight_peak": 0, "shade_s": 0.0, "skipped_domains": 0,
            # resident domains served because the cache evicts them next: before a load, and
            # before a preloaded domain is first traced
            "served_before_evict": 0, "served_before_preloaded": 0,
        }

    # -- the driver's interface ---------------------------------------------------------------
    @property
    def shadow_pending(self) -> np.ndarray:
        """(shadow rays so far,) int32: each one's domain visits outstanding (a view)."""
        return self._shadow_pending.values

    @property
    def shadow_blocked(self) -> np.ndarray:
        """(shadow rays so far,) bool: whether each one is blocked (a view)."""
        return self._shadow_blocked.values

    def start(self, rays: RadianceRays) -> None:
        """Queue the tile's camera rays into every domain they enter."""
        self._camera = rays
        self._queue_radiance(self._with_history(rays))

    def next_domain(self, resident: frozenset[int] = frozenset(),
                    victim: Callable[[], int | None] | None = None,
                    preloaded: frozenset[int] = frozenset()) -> int | None:
        """The next domain of the current round's schedule whose rays survive the filter;
        between rounds, retire and reschedule; between windows, resume spilled rays. None when
        the tile is done.

        A domain's queues are filtered here, before it is returned (Listing 2, lines 15-18):
        one whose rays are all stale, beaten by a closer hit or already blocked is skipped
        without being loaded (counted in ``skipped_domains``); ``process`` traces what is left.

        With ``resident_first``, ``resident`` (domains in memory now) lets a new round start
        with them, and a resident domain that has received rays since it was processed is
        served again before anything new is loaded: its rays cost no load now, and might cost
        one next round. With ``serve_before_evict`` and a ``victim`` (the domain the cache
        would evict for a load now, None while there is room), a resident domain is served
        again only when it is about to be evicted: the rays that reached it while it stayed
        are traced in one batch instead of one batch per arrival. It is also served before
        the round's next domain when that one was preloaded and not taken yet
        (``preloaded``, of ``resident``; done loading or not, so that the order never
        depends on how fast loads run): while the load runs the render thread would only
        wait, and afterwards the victim has nothing left to serve, so the preloader may evict
        it for the load after at once and build that one while the new domain is traced.
        (Served only before the load after, the victim held the preloader idle for the whole
        of the new domain's trace: 0.8 of 5.6 s at a quarter of ``bench/ooc.py --large``'s
        domains cached.)
        """
        if self._staged is not None:
            return self._staged[0]  # chosen and filtered already, not processed yet
        self.parting = None
        self._resident = resident
        self._victim_of = victim
        lazy = self.resident_first and self.serve_before_evict and victim is not None
        while True:
            if self.resident_first and not lazy and self.counters["rounds"]:
                waiting = self.radiance.counts() + self.shadow.counts()
                again = [d for d in resident if waiting[d] and d not in self._schedule]
                for domain in sorted(again, key=lambda d: (-waiting[d], d)):
                    if self._filter(domain):
                        return domain
            while self._schedule:
                if (self.resident_first and self.rescore and len(self._schedule) > 1
                        and self._ranked_for != resident):
                    # ranked again only if a score or the resident set changed: ranking the
                    # same scores again gives the same order (a D^2 loop at thousands of
                    # domains, most of the schedule being domains with nothing queued)
                    self._schedule = traversal_order(self.score, resident, self._schedule)
                    self._ranked_for = resident
                domain = self._schedule[0]
                if lazy and (domain not in resident or domain in preloaded):
                    going = victim()
                    if going is not None and going != domain and self._filter(going):
                        self.parting = going
                        key = "served_before_preloaded" if domain in preloaded else "served_before_evict"
                        self.counters[key] += 1
                        return going  # its rays now, or a load for them later
                self._schedule.pop(0)
                if self._filter(domain):
                    return domain
            if self.counters["rounds"] and not self._end_round():
                if not self._end_window():
                    return None
            self._new_round()

    def likely_next(self, current: int) -> int | None:
        """A guess at the next domain, for the preloader: the first one after ``current`` in
        this round's schedule with a ray that would survive the filter now (the preloader
        ignores a resident one). With ``serve_before_evict``, None while the domain a load
        would evict still has such rays (``next_domain`` serves it first)."""
        if self.resident_first and self.serve_before_evict and self._victim_of is not None:
            going = self._victim_of()
            if going is not None and going != current and self._would_trace(going):
                return None
        return next((d for d in self._schedule if d != current and self._would_trace(d)), None)

    def next_load(self, exclude: set[int]) -> int | None:
        """A guess at the next domain to load, for reading its files ahead: the first in this
        round's schedule outside ``exclude`` (the resident domains, the current one and the
        preload's guess) with a ray that would survive the filter now."""
        return next((d for d in self._schedule if d not in exclude and self._would_trace(d)),
                    None)

    def demand(self) -> np.ndarray:
        """(D,) float64, how soon each domain is needed (higher: sooner), what eviction by
        demand keeps: the domains left in this round's schedule by their place in it (the
        schedule is the future Belady's rule looks at), then those with queued rays (the next
        round's), then the rest (0). Queued-ray counts would not do: speculative copies sit
        in every domain a path may enter."""
        queued = self.radiance.counts() + self.shadow.counts()
        soon = (queued > 0).astype(np.float64)
        if self._schedule:
            left = len(self._schedule)
            soon[self._schedule] = 2.0 + (left - np.arange(left)) / left
        return soon

    def process(self, domain: int, bvh) -> None:
        """Trace the domain's filtered rays (Listing 2, lines 20-22)."""
        if self._staged is not None and self._staged[0] != domain:
            raise RuntimeError(f"spec-ooc: process({domain}) while next_domain chose "
                               f"{self._staged[0]}")
        if self._staged is None:
            self._filter(domain)  # called without next_domain: filter now
        _, radiance, shadow = self._staged or (domain, None, None)
        self._staged = None
        spawned = None if radiance is None else self._process_radiance(domain, bvh, radiance)
        tested = None if shadow is None else self._refilter_shadow(shadow)
        # One occlusion query for the shadow rays just cast here and those queued here.
        parts = [] if spawned is None else [spawned[0]]
        if tested is not None and len(tested):
            parts.append(as_shadow(shadow.take(tested)))
        if parts:
            blocked = bvh.occluded(*(np.concatenate([getattr(p, f) for p in parts])
                                     for f in ("origin", "direction", "t_max")))
            self.counters["shadow_tests"] += len(blocked)
            n_new = 0 if spawned is None else len(spawned[0])
            if spawned is not None:
                self._spawn_shadow(domain, *spawned, blocked[:n_new])
            if tested is not None and len(tested):
                self.shadow_blocked[shadow["sid"][tested[blocked[n_new:]]]] = True
        if shadow is not None:
            self._commit_ready(shadow)
        in_flight = self.radiance.total() + self.shadow.total() + sum(map(len, self.spill))
        self.counters["rays_in_flight_peak"] = max(self.counters["rays_in_flight_peak"], in_flight)

    def _add_score(self, domain, weight) -> None:
        """Add ``weight`` to the score of ``domain`` (an id, or ids with a weight each)."""
        np.add.at(self.score, domain, weight)
        self._ranked_for = None  # the remaining schedule must be ranked again

    def _weights(self, rank: np.ndarray) -> int:
        """Sum of the score weights (M - j) of rays at positions ``rank`` along their paths."""
        return int(len(rank) * self._depth_weight - rank.astype(np.int64).sum())

    # -- filtering (Listing 3) ----------------------------------------------------------------
    def _filter(self, domain: int) -> bool:
        """Take the domain's queues, update the statistics, drop the rays that need no test
        here and stage the rest for ``process``. True if any ray is left to trace."""
        radiance = self.radiance.pop(domain)
        if radiance is not None:
            level = radiance["depth"].astype(np.int64) - self.window_start
            self._add_score(domain, -self._weights(radiance["rank"]))
            np.subtract.at(self.pending, (radiance["path"], level), 1)
            live, keep = self._radiance_predicate(radiance, level)
            self.counters["wasted_rays"] += int(np.count_nonzero(~live))
            self.counters["filtered_rays"] += int(np.count_nonzero(~keep))
            radiance = _kept(radiance, keep)
        shadow = self.shadow.pop(domain)
        if shadow is not None:
            sid = shadow["sid"]
            self._add_score(domain, -self._weights(shadow["rank"]))
            self.shadow_pending[sid] -= 1
            live, keep = self._shadow_predicate(shadow)
            self.counters["wasted_rays"] += int(np.count_nonzero(~live & ~self.shadow_blocked[sid]))
            self.counters["filtered_rays"] += int(np.count_nonzero(~keep))
            self.shadow_blocked[sid[~live]] = True  # stale: never needs another visit
            shadow = _kept(shadow, keep)
        if radiance is None and shadow is None:
            self.counters["skipped_domains"] += 1
            return False
        self._staged = (domain, radiance, shadow)
        return True

    def _radiance_predicate(self, rays: SoA, level: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(live, keep): a live history, and no hit found yet before the domain starts."""
        live = self._history_matches(rays, level)
        return live, live & (rays["entry"] < self.hbuf_t[rays["path"], level])

    def _shadow_predicate(self, rays: SoA) -> tuple[np.ndarray, np.ndarray]:
        """(live, keep): a live history (through the hit that cast it), and not blocked yet."""
        level = rays["depth"].astype(np.int64) - self.window_start
        live = self._history_matches(rays, level + 1)
        return live, live & ~self.shadow_blocked[rays["sid"]]

    def _would_trace(self, domain: int) -> bool:
        """Whether a ray queued for ``domain`` would survive the filter now (nothing changes):
        ``_radiance_predicate`` and ``_shadow_predicate``'s keep, in one compiled pass that
        stops at the first survivor. (``likely_next`` asks this of domain after domain: as
        numpy over views of every field it was most of spec-ooc's decision time, 0.9 ms a
        decision on 1,439 domains.)"""
        start = self.window_start
        for path, depth, hist_t, hist_d, entry in self.radiance.peek_fields(
                domain, ("path", "depth", "hist_t", "hist_d", "entry")):
            if _any_radiance_kept(path, depth, hist_t, hist_d, entry, self.hbuf_t, self.hbuf_d,
                                  start):
                return True
        for path, depth, hist_t, hist_d, sid in self.shadow.peek_fields(
                domain, ("path", "depth", "hist_t", "hist_d", "sid")):
            if _any_shadow_kept(path, depth, hist_t, hist_d, sid, self.shadow_blocked,
                                self.hbuf_t, self.hbuf_d, start):
                return True
        return False

    # -- rounds and windows -------------------------------------------------------------------
    def _new_round(self) -> None:
        """Schedule the round (Listing 2, line 12; see ``traversal_order``)."""
        self._schedule = traversal_order(self.score,
                                         self._resident if self.resident_first else frozenset())
        self._ranked_for = None
        self.counters["rounds"] += 1

    def _end_round(self) -> bool:
        """Retire, swap commit and retire queues; True while the window has work left."""
        self._retire()
        self.retire, self.commit = self.commit, []
        return bool(self.radiance.total() or self.shadow.total() or self.retire)

    def _end_window(self) -> bool:
        """The window's hits are final: record camera hits, resume spilled rays (Listing 2,
        lines 6-10). True if a new window starts."""
        if self.window_start == 0 and self._camera is not None:
            hits = ClosestHits(self.hbuf_t[:, 0], self.hbuf_d[:, 0], self.first_normal,
                               np.zeros(len(self.hbuf_t), np.int64), None).hits()
            # the paths whose camera rays were made (``launched_camera_rays``); the others
            # saw the sky when the tile started
            self.result.record_camera_hits(self.ctx, self._camera, hits.take(self._camera.path))
        self.counters["windows"] += 1
        spilled = SoA.concat(self.spill) if self.spill else None
        self.spill = []
        if spilled is None or len(spilled) == 0:
            return False
        valid = self._history_matches(spilled, self.window)
        self.counters["wasted_rays"] += int(np.count_nonzero(~valid))
        self.window_start += self.window
        self.hbuf_t[:] = np.inf
        self.hbuf_d[:] = NO_DOMAIN
        resumed = as_radiance(spilled.take(valid))
        self._queue_radiance(self._with_history(resumed))
        self._schedule = []
        return True

    # -- history ------------------------------------------------------------------------------
    def _with_history(self, rays: RadianceRays) -> SoA:
        n = len(rays)
        return _radiance(rays, np.full((n, self.window), np.inf, np.float32),
                         np.full((n, self.window), NO_DOMAIN, np.int32))

    def _history_matches(self, rays: SoA, upto: np.ndarray | int,
                         rows: np.ndarray | None = None) -> np.ndarray:
        """Whether each ray's ancestors at window depths ``< upto`` (an int or one per ray)
        match the history buffer; for the rays ``rows`` (m,) only when given."""
        path, hist_t, hist_d = rays["path"], rays["hist_t"], rays["hist_d"]
        if rows is not None:
            path, hist_t, hist_d = path[rows], hist_t[rows], hist_d[rows]
        out = np.empty(len(path), np.bool_)
        # (np.broadcast_to costs a few microseconds more, on every step of the schedule)
        upto = (np.full(len(path), upto, np.int64) if np.ndim(upto) == 0
                else np.asarray(upto, np.int64))
        _matches(path, hist_t, hist_d, self.hbuf_t, self.hbuf_d, upto, out)
        return out

    def _final(self, path: np.ndarray, upto: np.ndarray) -> np.ndarray:
        """Whether the buffer is final at window depths ``<= upto`` for each path."""
        used = np.arange(self.window)[None, :] <= upto[:, None]
        return np.all((self.pending[path] == 0) | ~used, axis=1)

    # -- radiance rays ------------------------------------------------------------------------
    def _queue_radiance(self, rays: SoA) -> None:
        """Speculatively queue rays into all domains they enter (Listing 2, line 3)."""
        if len(rays) == 0:
            return
        ray, domain, entry, rank = self.geometry.crossings(
            rays["origin"], rays["direction"], np.full(len(rays), np.inf, np.float32))
        copies = rays.take(ray)
        copies["entry"] = entry
        copies["rank"] = rank
        level = copies["depth"].astype(np.int64) - self.window_start
        np.add.at(self.pending, (copies["path"], level), 1)
        self._add_score(domain, self._depth_weight - rank.astype(np.int64))
        self.radiance.push(domain, copies)

    def _process_radiance(self, domain: int, bvh, rays: SoA
                          ) -> tuple[ShadowRays, np.ndarray, np.ndarray, np.ndarray] | None:
        """Trace filtered radiance rays (statistics and pending visits already updated).

        One Embree query for every depth in the batch, each ray bounded by its closest hit of
        now; then, shallow first, the hits are offered to the history buffer: a new closest
        hit at one depth makes the same path's deeper rays in this batch stale, and they are
        dropped before they offer theirs (their query was wasted, and counted as a test).
        Every winner of the batch is shaded in one call (Listing 4), whatever its depth: a
        path has at most one winner per batch, since a win makes its deeper rays stale.

        Returns
        -------
        The shadow rays the winners cast, untested, with their histories ((k, H + 1) t and
        domain) and their paths ((k,)): ``process`` tests them here with the queued ones.
        None when nothing won or nothing was cast.
        """
        level = rays["depth"].astype(np.int64) - self.window_start
        path = rays["path"]
        self.counters["radiance_tests"] += len(rays)
        r = bvh.intersect(rays["origin"], rays["direction"], self.hbuf_t[path, level])
        # The rays carry no hit record: the buffer holds (t, domain), the rest is scratch.
        n = len(rays)
        hits = ClosestHits(self.hbuf_t[path, level], self.hbuf_d[path, level],
                           np.zeros((n, 3), np.float32), np.zeros(n, np.int64),
                           np.zeros((n, 3)) if self.color_source is not None else None,
                           np.zeros((n, 3)), np.zeros(n))
        winners = []
        for depth in np.unique(level):
            rows = np.nonzero(level == depth)[0]
            live, keep = self._radiance_predicate_rows(rays, rows, int(depth))
            self.counters["wasted_rays"] += int(np.count_nonzero(~live))
            self.counters["filtered_rays"] += int(np.count_nonzero(~keep))
            rows = rows[keep]
            if len(rows) == 0:
                continue
            # the batch-wide record was read before this depth's paths could change: refresh
            hits.t[rows] = self.hbuf_t[path[rows], depth]
            hits.domain[rows] = self.hbuf_d[path[rows], depth]
            won = rows[hits.offer(rows, domain, bvh, {k: v[rows] for k, v in r.items()},
                                  self.color_source, self.scalar_range)]
            if len(won) == 0:
                continue
            # The closest hit so far: record it; deeper entries belonged to the hit that just
            # lost, so its descendants are stale now.
            won_path = path[won]
            self.hbuf_t[won_path, depth] = hits.t[won]
            self.hbuf_d[won_path, depth] = domain
            self.hbuf_t[won_path, depth + 1:] = np.inf
            self.hbuf_d[won_path, depth + 1:] = NO_DOMAIN
            if self.window_start == 0 and depth == 0:
                self.first_normal[won_path] = hits.ng[won]
            winners.append(won)
        if not winners:
            return None
        # Shade every winner speculatively (Listing 4).
        won = np.concatenate(winners)
        won_path, won_level = path[won], level[won]
        if len(np.unique(won_path)) != len(won):  # index_of names parents by path
            raise RuntimeError("spec-ooc: two winners of one path in one batch")
        hist_t, hist_d = rays["hist_t"][won], rays["hist_d"][won]
        hist_t[np.arange(len(won)), won_level] = hits.t[won]
        hist_d[np.arange(len(won)), won_level] = domain
        start = time.perf_counter()
        shadow, continuation = shade(self.ctx, as_radiance(rays.take(won)), hits.hits(won))
        self.counters["shade_s"] += time.perf_counter() - start
        self._spawn_radiance(continuation, hist_t, hist_d, won_path)
        return (shadow, hist_t, hist_d, won_path) if len(shadow) else None

    def _radiance_predicate_rows(self, rays: SoA, rows: np.ndarray, depth: int
                                 ) -> tuple[np.ndarray, np.ndarray]:
        """``_radiance_predicate`` for the rays ``rows`` (m,), all at window depth ``depth``."""
        live = self._history_matches(rays, depth, rows)
        return live, live & (rays["entry"][rows] < self.hbuf_t[rays["path"][rows], depth])

    def _spawn_radiance(self, rays: RadianceRays, hist_t, hist_d, parent_path) -> None:
        if len(rays) == 0:
            return
        parent = index_of(parent_path, rays.path)
        soa = _radiance(rays, hist_t[parent], hist_d[parent])
        self.counters["speculative_rays"] += len(soa)
        beyond = (rays.depth.astype(np.int64) - self.window_start) >= self.window
        if beyond.any():
            self.spill.append(soa.take(beyond))  # Listing 4: the spill queue
        self._queue_radiance(soa.take(~beyond))

    # -- shadow rays --------------------------------------------------------------------------
    def _spawn_shadow(self, domain: int, rays: ShadowRays, hist_t, hist_d, parent_path,
                      blocked: np.ndarray) -> None:
        """processSecondary: ``rays`` (k,) were tested against this domain (``blocked`` (k,));
        queue the others into the other domains they cross, commit those that cross none."""
        self.counters["speculative_rays"] += len(rays)
        rows = np.nonzero(~blocked)[0]
        self.counters["filtered_rays"] += len(rays) - len(rows)
        if len(rows) == 0:
            return
        rays = rays.take(rows)
        parent = index_of(parent_path, rays.path)
        sid = np.arange(len(self._shadow_pending), len(self._shadow_pending) + len(rays))
        soa = shadow_soa(rays, hist_t=hist_t[parent], hist_d=hist_d[parent], sid=sid)
        ray, dom, entry, rank = self.geometry.crossings(rays.origin, rays.direction, rays.t_max)
        other = dom != domain
        ray, dom, entry, rank = ray[other], dom[other], entry[other], rank[other]
        visits = np.bincount(ray, minlength=len(rays)).astype(np.int32)
        self._shadow_pending.append(visits)
        self._shadow_blocked.append(np.zeros(len(rays), bool))
        done = visits == 0
        if done.any():
            self.commit.append(_committed(soa.take(done)))
        if len(ray):
            copies = soa.take(ray)
            copies["entry"], copies["rank"] = entry, rank
            self._add_score(dom, self._depth_weight - rank.astype(np.int64))
            self.shadow.push(dom, copies)

    def _refilter_shadow(self, rays: SoA) -> np.ndarray:
        """Filter queued shadow rays again (statistics and pending visits already updated):
        this domain's radiance rays may have just found closer hits. Returns the rows (m,)
        still to test here."""
        sid = rays["sid"]
        live, keep = self._shadow_predicate(rays)
        self.counters["wasted_rays"] += int(np.count_nonzero(~live & ~self.shadow_blocked[sid]))
        self.counters["filtered_rays"] += int(np.count_nonzero(~keep))
        self.shadow_blocked[sid[~live]] = True
        return np.nonzero(keep)[0]

    def _commit_ready(self, rays: SoA) -> None:
        """Commit the queued shadow rays, tested here, that are unblocked and have visited
        every domain they cross."""
        sid = rays["sid"]
        ready = (self.shadow_pending[sid] == 0) & ~self.shadow_blocked[sid]
        if ready.any():
            self.commit.append(_committed(rays.take(ready)))

    def _retire(self) -> None:
        """Resolve the retire queue: final and matching histories bring their light.

        Chunk by chunk, as committed: joined, the queue was copied twice more at once (the
        peak of a fine store's render, issue 37). The light is summed per path in the rows'
        order over every chunk, then added, as one ``add_unoccluded`` of the joined queue."""
        if not self.retire:
            return
        retire, self.retire = self.retire, []
        light = np.zeros_like(self.result.radiance)
        waiting = False
        for i, rays in enumerate(retire):
            retire[i] = None  # freed once resolved
            level = rays["depth"].astype(np.int64) - self.window_start
            final = self._final(rays["path"], level)
            if not final.all():
                waiting = True
                self.commit.append(rays.take(~final))  # wait for another round
                rays, level = rays.take(final), level[final]
            if len(rays) == 0:
                continue
            valid = self._history_matches(rays, level + 1)
            self.counters["wasted_rays"] += int(np.count_nonzero(~valid))
            _sum_lit(light, rays["path"], rays["contribution"], valid)
        # With nothing queued every hit is final; waiting would loop forever.
        if waiting and not (self.radiance.total() or self.shadow.total()):
            raise RuntimeError("spec-ooc: shadow rays wait on hits no queued ray can change")
        self.result.radiance += light


def _committed(rays: SoA) -> SoA:
    """A committed shadow ray as the retire queue keeps it: what ``_retire`` reads (its path,
    depth, history and light), not its geometry, which no test needs any more."""
    return SoA._trusted({k: rays[k] for k in ("path", "depth", "contribution", "hist_t",
                                              "hist_d")})


@njit(nogil=True, cache=True)
def _sum_lit(light, path, contribution, lit):
    """``light[path[r]] += contribution[r]`` for the rows ``r`` with ``lit[r]``, in row order
    (``kernels.add_unoccluded``'s sums, kept over several calls)."""
    for r in range(path.shape[0]):
        if lit[r]:
            p = path[r]
            light[p, 0] += contribution[r, 0]
            light[p, 1] += contribution[r, 1]
            light[p, 2] += contribution[r, 2]


def _radiance(rays: RadianceRays, hist_t: np.ndarray, hist_d: np.ndarray) -> SoA:
    """Radiance rays as queued here: the integrator's fields and the history ((n, H + 1) t and
    domain of the hits they descend from). No hit record: the history buffer keeps it."""
    return SoA(**{f: getattr(rays, f) for f in RADIANCE_FIELDS}, hist_t=hist_t, hist_d=hist_d)


def _kept(rays: SoA, keep: np.ndarray) -> SoA | None:
    """The rows of ``rays`` where ``keep`` ((n,) bool) holds; None if none does."""
    if keep.all():
        return rays
    return rays.take(keep) if keep.any() else None


@njit(nogil=True, cache=True)
def _matches(path, hist_t, hist_d, hbuf_t, hbuf_d, upto, out):
    """out[i]: ray i's history ((n, W) t and domain) equals the buffer's ((P, W)) row path[i]
    at the depths below upto[i] ((n,) each). NaN never equals (as numpy's ==)."""
    for i in range(len(path)):
        out[i] = _history_equal(i, path[i], upto[i], hist_t, hist_d, hbuf_t, hbuf_d)


@njit(nogil=True, cache=True)
def _history_equal(i, p, upto, hist_t, hist_d, hbuf_t, hbuf_d) -> bool:
    """Ray i's history equals the buffer's row p at the depths below upto."""
    for j in range(min(upto, hist_t.shape[1])):
        if not (hist_t[i, j] == hbuf_t[p, j] and hist_d[i, j] == hbuf_d[p, j]):
            return False
    return True


@njit(nogil=True, cache=True)
def _any_radiance_kept(path, depth, hist_t, hist_d, entry, hbuf_t, hbuf_d, window_start):
    """Whether any of the radiance rays ((n,) path, depth and entry, (n, W) history) would
    be kept by ``_radiance_predicate``: entering before its path's hit at its level, with a
    live history."""
    for i in range(len(path)):
        p = path[i]
        level = np.int64(depth[i]) - window_start
        if entry[i] < hbuf_t[p, level] and _history_equal(i, p, level, hist_t, hist_d,
                                                          hbuf_t, hbuf_d):
            return True
    return False


@njit(nogil=True, cache=True)
def _any_shadow_kept(path, depth, hist_t, hist_d, sid, blocked, hbuf_t, hbuf_d, window_start):
    """Whether any of the shadow rays would be kept by ``_shadow_predicate``: not blocked
    yet (``blocked``: (S,) by shadow id), with a live history through the hit that cast it."""
    for i in range(len(path)):
        if blocked[sid[i]]:
            continue
        p = path[i]
        if _history_equal(i, p, np.int64(depth[i]) - window_start + 1, hist_t, hist_d,
                          hbuf_t, hbuf_d):
            return True
    return False


def traversal_order(score: np.ndarray, resident: frozenset[int] = frozenset(),
                    domains: list[int] | None = None) -> list[int]:
    """A round's schedule: domains by descending front-to-back traversal score (SpRay 4.1.2),
    ``score`` (N,): ``Score[i] = sum_j (M - j) * Counter[i][j]`` (``traversal_score``), lowest
    id on ties.

    Domains in ``resident`` go first (still by score among themselves). A fixed cyclic order is
    the worst case for an LRU cache smaller than the cycle (every access misses); starting each
    round with what the last one left resident turns those misses into hits (bench/ooc.py
    measures both orders). Empty ``resident`` gives the paper's order. ``domains`` (ids) ranks
    only those (the rest of a round, re-ranked by the scores of now); default: every domain.
    """
    ids = np.arange(len(score)) if domains is None else np.asarray(domains, np.int64)
    here = np.zeros(len(score), np.bool_)  # a mask, not np.isin: this runs every decision
    here[np.fromiter(resident, np.int64, len(resident))] = True
    mine = score[ids]
    low, high = (int(mine.min()), int(mine.max())) if len(ids) else (0, 0)
    if len(score) <= 1 << _ID_BITS and high - low < 1 << _SCORE_BITS:
        # the three keys in one integer (away, then -score, then id): one argsort, not a
        # three-key lexsort (a round re-ranks its rest every decision: 1,439 domains took
        # ~0.4 ms a rank)
        key = (((~here[ids]).astype(np.int64) << (_SCORE_BITS + _ID_BITS))
               | ((high - mine) << _ID_BITS) | ids)
        return ids[np.argsort(key)].tolist()
    return ids[np.lexsort((ids, -mine, ~here[ids]))].tolist()


#: Bits of ``traversal_order``'s packed key: domain ids below 2^20, score spans below 2^42.
_ID_BITS = 20
_SCORE_BITS = 42
