"""The baseline schedule (SpRay Listing 1, Navrátil's LoadAnyOnce): rays wait in the queue of
the next domain on their path; the domain with the most waiting rays is processed next.

A radiance ray moves front to back through the domains its path enters before its closest hit
so far; the hit is final when no unvisited domain starts before it, and only then is it shaded.
A shadow ray moves the same way until something blocks it or it has crossed every domain
before its light, and then brings its light to its path. Nothing is speculative, so nothing is
wasted, but each domain may be loaded many times as new rays keep arriving.
"""

from __future__ import annotations

import time
from collections.abc import Iterable

import numpy as np

from vastray.render.integrators import (
    PathContext,
    PathResult,
    RadianceRays,
    ShadowRays,
    add_unoccluded,
    shade,
)
from vastray.schedule.geometry import DomainGeometry
from vastray.schedule.paths import (
    as_radiance,
    as_shadow,
    closest_hits,
    radiance_soa,
    shadow_soa,
    start_cursor,
)
from vastray.schedule.portals import luminance
from vastray.schedule.soa import DomainQueues, SoA, index_of


def fullest(waiting: np.ndarray, first: Iterable[int] = ()) -> int:
    """The domain with the most ``waiting`` ((D,) counts) rays, ties -> the lower id; taken
    among ``first`` (e.g. the domains in memory) when one of those has any."""
    here = [d for d in first if waiting[d]]
    if here:
        return max(here, key=lambda d: (waiting[d], -d))
    return int(np.argmax(waiting))


class ImageSchedule:
    """Out-of-core baseline scheduling of one tile of paths.

    Parameters
    ----------
    ctx : the tile's paths (keys, shading, settings).
    geometry : domain boxes.
    color_source, scalar_range : what hit records interpolate (see ``ClosestHits.offer``).
    owner, rank : for domain decomposition across nodes, the (D,) node owning each domain and
        this node's rank: rays bound for another node's domain go to ``outbox`` instead of a
        local queue. Default: this node owns every domain.
    resident_first : serve a domain already in memory (``next_domain``'s ``resident``) before
        loading one, the same rule ``SpeculativeSchedule`` has; False is Listing 1 as written
        (the fullest queue, wherever it is). Default True: the strongest honest baseline.
    tally : where to count the temporal-coherence paper's ray statistics (§4.1), or None (the
        default: nothing counted). An object with ``sent`` ((D, D) int64: rays forwarded from
        domain A to domain B != A, a new ray counting from the domain of the hit that spawned
        it) and ``received`` ((D,) int64: rays each domain processed).
    simple : routing to the node's simplified model (``schedule.simplified``), or None (the
        default: every ray is traced on the fine domains).
    """

    name = "image"
    #: While a render is recorded for the simulator's replay (``vastray.sim.crossings``), the
    #: recorder: each launched ray gets a segment id (field ``seg``) from its ``launched``, and
    #: every traced batch goes to its ``traced``. None (the default): nothing recorded.
    crossing_log = None

    def __init__(self, ctx: PathContext, geometry: DomainGeometry, color_source: str | None,
                 scalar_range: tuple[float, float], owner: np.ndarray | None = None,
                 rank: int = 0, resident_first: bool = True, tally=None, simple=None):
        self.resident_first = resident_first
        self.tally = tally
        self.simple = simple
        self._resident: frozenset[int] = frozenset()
        self.owner = np.zeros(geometry.n_domains, np.int64) if owner is None else owner
        self.rank = rank
        #: (queue name, destination node) -> [(domains (m,), rays SoA)] waiting to be sent.
        self.outbox: dict[tuple[str, int], list[tuple[np.ndarray, SoA]]] = {}
        self.ctx = ctx
        self.geometry = geometry
        self.color_source = color_source
        self.scalar_range = scalar_range
        self.radiance = DomainQueues(geometry.n_domains)
        self.shadow = DomainQueues(geometry.n_domains)
        self.result = PathResult.empty(len(ctx.pixel))
        self.counters = {"radiance_tests": 0, "shadow_tests": 0, "rays_in_flight_peak": 0,
                         "shade_s": 0.0}

    @property
    def _portals(self) -> bool:
        return self.simple is not None and self.simple.uses_portals

    # -- the driver's interface ---------------------------------------------------------------
    def start(self, rays: RadianceRays) -> None:
        """Queue the tile's camera rays."""
        self._launch_radiance(rays)

    def next_domain(self, resident: frozenset[int] = frozenset()) -> int | None:
        """The domain with the most waiting rays (lowest id on ties); None when done.

        With ``resident_first``, a domain in ``resident`` (in memory now) with waiting rays
        goes before any other, the fullest first: its rays cost no load now and might cost one
        later. Without it, ``resident`` is ignored (SpRay Listing 1).
        """
        waiting = self.demand()
        self.counters["rays_in_flight_peak"] = max(self.counters["rays_in_flight_peak"],
                                                   int(waiting.sum()))
        self._resident = resident
        if not waiting.any():
            return None
        return fullest(waiting, resident if self.resident_first else ())

    def likely_next(self, current: int) -> int | None:
        """A guess at the next domain, for the preloader: the one ``next_domain`` would pick
        if ``current`` sent no rays on (the second-fullest queue, or with ``resident_first``
        the fullest resident one). The real choice depends on the rays ``current`` sends on,
        so the guess can be wrong; a wrong guess costs a load and evicts a domain."""
        waiting = self.demand()
        waiting[current] = 0
        if not waiting.any():
            return None
        return fullest(waiting, self._resident if self.resident_first else ())

    def demand(self) -> np.ndarray:
        """(D,) int64 rays waiting for each domain (a fresh array): what ``next_domain`` picks
        the fullest of, and what eviction by demand keeps (the domain with the fewest is
        needed last: Belady's victim)."""
        return self.radiance.counts() + self.shadow.counts()

    def process(self, domain: int, bvh) -> None:
        """Trace every ray waiting for ``domain`` against its loaded BVH."""
        rays = self.radiance.pop(domain)
        shadows = self.shadow.pop(domain)
        if self.crossing_log is not None:
            for batch in (rays, shadows):
                if batch is not None:
                    self.crossing_log.traced(domain, batch["seg"])
        if self.tally is not None:
            self.tally.received[domain] += sum(len(r) for r in (rays, shadows) if r is not None)
        if rays is not None:
            self._process_radiance(domain, bvh, rays)
        if shadows is not None:
            self._process_shadow(domain, bvh, shadows)

    # -- radiance rays ------------------------------------------------------------------------
    def _process_radiance(self, domain: int, bvh, rays: SoA) -> None:
        self.counters["radiance_tests"] += len(rays)
        r = bvh.intersect(rays["origin"], rays["direction"], rays["hit_t"])
        closest_hits(rays).offer(np.arange(len(rays)), domain, bvh, r, self.color_source,
                                 self.scalar_range)
        self._advance_radiance(rays)

    def _forward(self, rays: SoA, queues: DomainQueues, limit: np.ndarray,
                 spawned_in: np.ndarray | None = None) -> np.ndarray:
        """Queue each ray into the next domain on its path that starts before ``limit``.

        ``spawned_in`` ((n,) int) is, for new rays, the domain of the hit that spawned each
        (-1 for camera rays): where the tally counts them sent from.

        Returns
        -------
        (n,) bool, the rays with no such domain left.
        """
        # Occupancy masks skip domains a ray cannot hit, except with portals: a ray's portal
        # is decided between the domains it visits (``_cross_portals``), boxes included
        nxt, entry = self.geometry.next_domain(rays["origin"], rays["direction"], rays["at_t"],
                                               rays["at_d"], limit, masks=not self._portals)
        moving = nxt >= 0
        if self.tally is not None:
            self._count_sent(rays["at_d"] if spawned_in is None else spawned_in, nxt)
        if moving.any():
            movers = rays.take(moving)
            movers["at_t"], movers["at_d"] = entry[moving], nxt[moving]
            destination = self.owner[nxt[moving]]
            local = destination == self.rank
            if local.all():
                queues.push(nxt[moving], movers)
            else:
                queues.push(nxt[moving][local], movers.take(local))
                name = "radiance" if queues is self.radiance else "shadow"
                for node in np.unique(destination[~local]):
                    rows = np.nonzero(destination == node)[0]
                    self.outbox.setdefault((name, int(node)), []).append(
                        (nxt[moving][rows], movers.take(rows)))
        return ~moving

    def _count_sent(self, source: np.ndarray, destination: np.ndarray) -> None:
        """Add rays moving from domain ``source`` to another ``destination`` to s(A, B)."""
        n = self.geometry.n_domains
        counted = (source >= 0) & (source < n) & (destination >= 0) & (source != destination)
        if counted.any():
            pairs = source[counted].astype(np.int64) * n + destination[counted]
            np.add.at(self.tally.sent.reshape(-1), pairs, 1)

    def receive(self, queue: str, domains: np.ndarray, rays: SoA) -> None:
        """Queue rays another node sent for this node's ``domains`` ((m,) each)."""
        (self.radiance if queue == "radiance" else self.shadow).push(domains, rays)

    def take_outbox(self, min_rays: int = 0
                    ) -> dict[tuple[str, int], list[tuple[np.ndarray, SoA]]]:
        """Rays to send, by (queue, destination node): those of every destination holding at
        least ``min_rays`` rays (0: all of them), taken out of the outbox; the others stay."""
        if min_rays <= 0:
            out, self.outbox = self.outbox, {}
            return out
        out = {key: parts for key, parts in self.outbox.items()
               if sum(len(domains) for domains, _ in parts) >= min_rays}
        for key in out:
            del self.outbox[key]
        return out

    def _advance_radiance(self, rays: SoA, spawned_in: np.ndarray | None = None) -> None:
        """Queue rays into their next domain; shade the ones whose hit is final."""
        if self.simple is not None and self.simple.uses_portals:
            rays, spawned_in = self._cross_portals(rays, spawned_in)
            if len(rays) == 0:
                return
        final = self._forward(rays, self.radiance, rays["hit_t"], spawned_in)
        if final.any():
            self._finalize(rays.take(final))

    def _finalize(self, rays: SoA) -> None:
        """Closest hits are final: record camera hits, shade, launch the rays they spawn."""
        hits = closest_hits(rays).hits()
        radiance = as_radiance(rays)
        camera = radiance.depth == 0
        if camera.any():
            rows = np.nonzero(camera)[0]
            self.result.record_camera_hits(self.ctx, radiance.take(rows), hits.take(rows))
        recording = self.simple is not None and self.simple.records
        if recording:  # crossed portals start dark: a miss or a shadowed hit records 0
            self._record_crossings(rays)
        hit = np.nonzero(hits.hit)[0]
        if len(hit) == 0:
            return
        start = time.perf_counter()
        shadow, continuation = shade(self.ctx, radiance, hits, hit)
        self.counters["shade_s"] += time.perf_counter() - start
        shadow_rows = continuation_rows = None
        logged = self.crossing_log is not None
        if self.tally is not None or self.simple is not None or logged:
            # each path has one final hit here: the hit row of every spawned ray, by its path
            # (a search over the hits, not a lookup table over every path of the tile: this
            # runs once per activation)
            rows = index_of(radiance.path[hit], np.concatenate([shadow.path,
                                                                continuation.path]))
            shadow_rows, continuation_rows = rows[:len(shadow)], rows[len(shadow):]
        hit_domain = None if shadow_rows is None else rays["hit_domain"][hit]
        portal = self._portal_fields(rays, hit, shadow, shadow_rows) if recording else None
        parent = rays["seg"][hit] if logged else None
        self._launch_shadow(shadow, None if hit_domain is None else hit_domain[shadow_rows],
                            portal, None if parent is None else parent[shadow_rows])
        self._launch_radiance(continuation, None if hit_domain is None
                              else hit_domain[continuation_rows],
                              None if parent is None else parent[continuation_rows])

    def _launch_radiance(self, rays: RadianceRays, spawned_in: np.ndarray | None = None,
                         parent: np.ndarray | None = None) -> None:
        """Queue new radiance rays (``parent``: each one's spawning segment, for a recorder)."""
        if not len(rays):
            return
        extra = start_cursor(len(rays))
        if self.simple is not None:
            extra.update(portal_t=np.full(len(rays), np.inf, np.float32),
                         portal_from=np.full(len(rays), -1, np.int32),
                         portal_cell=np.full(len(rays), -1, np.int64))
        soa = radiance_soa(rays, self.color_source is not None, **extra)
        if self.crossing_log is not None:
            soa["seg"] = self.crossing_log.launched(self, soa, parent)
        if self.simple is None:
            self._advance_radiance(soa, spawned_in)
            return
        simple = self.simple.simplified_at_start(rays.depth, spawned_in)
        if simple.any():
            self._trace_simplified(soa.take(simple), np.zeros(int(simple.sum())))
        if simple.all():
            return
        soa = soa.take(~simple)
        spawned_in = None if spawned_in is None else spawned_in[~simple]
        if self.simple.uses_portals and spawned_in is not None:
            first = np.nonzero(soa["depth"] == 1)[0]
            soa["portal_from"][first] = spawned_in[first]
            soa["portal_t"][first] = self.simple.portal_exit(
                soa["origin"][first], soa["direction"][first], spawned_in[first])
        self._advance_radiance(soa, spawned_in)

    # -- the simplified model -----------------------------------------------------------------
    def _cross_portals(self, rays: SoA, spawned_in: np.ndarray | None
                       ) -> tuple[SoA, np.ndarray | None]:
        """Depth-1 rays about to leave their spawning domain with no hit before its portal:
        record where they crossed (recording frame), or send those the portal predicts dark
        on through the simplified model. Returns the rays that stay fine."""
        pending = np.nonzero(np.isfinite(rays["portal_t"])
                             & (rays["hit_t"] > rays["portal_t"]))[0]
        if len(pending) == 0:
            return rays, spawned_in
        nxt, entry = self.geometry.next_domain(
            rays["origin"][pending], rays["direction"][pending], rays["at_t"][pending],
            rays["at_d"][pending], rays["hit_t"][pending], masks=False)
        crossing = pending[(nxt < 0) | (entry >= rays["portal_t"][pending])]
        if len(crossing) == 0:
            return rays, spawned_in
        simple = self.simple
        t_exit = rays["portal_t"][crossing].astype(np.float64)[:, None]
        points = rays["origin"][crossing] + t_exit * rays["direction"][crossing]
        cells = simple.portals.cells(rays["portal_from"][crossing], points,
                                     rays["direction"][crossing], simple.lo, simple.hi)
        simple.counters["portal_crossings"] += len(crossing)
        rays["portal_t"][crossing] = np.inf  # crossed: the decision is made once
        if simple.recording:
            rays["portal_cell"][crossing] = cells
            return rays, spawned_in
        low = simple.portals.predict(cells) <= simple.threshold
        if simple.fresh is not None:  # accumulating: the rays traced fine record
            rays["portal_cell"][crossing[~low]] = cells[~low]
        if not low.any():
            return rays, spawned_in
        simple.counters["predicted_low"] += int(low.sum())
        diverted = crossing[low]
        self._trace_simplified(rays.take(diverted), t_exit[low, 0])
        keep = np.ones(len(rays), bool)
        keep[diverted] = False
        return rays.take(keep), None if spawned_in is None else spawned_in[keep]

    def _trace_simplified(self, rays: SoA, t_start: np.ndarray) -> None:
        """Trace radiance rays on the simplified model from ``t_start``; their hits are final
        (a fine hit already found before the portal stays if it is nearer)."""
        simple = self.simple
        simple.counters["simplified_rays"] += len(rays)
        r = simple.trace(rays["origin"], rays["direction"], t_start, rays["hit_t"])
        closest_hits(rays).offer(np.arange(len(rays)), simple.domain, simple.bvh, r,
                                 self.color_source, self.scalar_range)
        self._finalize(rays)

    def _record_crossings(self, rays: SoA) -> None:
        """Recording (or accumulating) frame: every final ray that crossed its portal (and, if
        accumulating, was traced fine) records 0 in its cell (dark until the light its hit
        receives says otherwise)."""
        cells = rays["portal_cell"]
        crossed = cells >= 0
        if crossed.any():
            self.simple.record_into.record(cells[crossed],
                                           np.zeros(int(crossed.sum()), np.float32))
            self.simple.counters["portal_records"] += int(crossed.sum())
            if self.simple.log is not None:  # an instrumented frame: which path crossed where
                self.simple.log.crossed(self._path_ids(rays["path"][crossed]), cells[crossed])

    def _path_ids(self, path: np.ndarray) -> np.ndarray:
        """(m,) int64 pass-wide ids ``pixel * n + sample - s0`` of rows ``path`` of the tile,
        for the pass of samples ``s0 <= sample < s0 + n``."""
        ctx = self.ctx
        s0, s1 = ctx.settings.samples
        return (ctx.pixel[path].astype(np.int64) * (s1 - s0)
                + ctx.sample[path].astype(np.int64) - s0)

    def _portal_fields(self, rays: SoA, hit: np.ndarray, shadow: ShadowRays,
                       rows: np.ndarray) -> dict[str, np.ndarray]:
        """Recording frame: the shadow rays of a hit whose ray crossed a portal carry the cell
        and the light each would bring back, ``k * contribution / beta`` in luminance for the
        ``k`` shadow rays of the hit (the per-cell maximum keeps the brightest estimate);
        ``rows`` ((s,)) is each shadow ray's row in ``hit``."""
        beta = rays["beta"][hit][rows]
        _, per_path, counts = np.unique(shadow.path, return_inverse=True, return_counts=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            per_beta = np.where(beta > 0, shadow.contribution / beta, 0.0)
        value = (luminance(per_beta) * counts[per_path]).astype(np.float32)
        return {"portal_cell": rays["portal_cell"][hit][rows], "portal_value": value}

    # -- shadow rays --------------------------------------------------------------------------
    def _launch_shadow(self, rays: ShadowRays, spawned_in: np.ndarray | None = None,
                       portal: dict | None = None, parent: np.ndarray | None = None) -> None:
        if not len(rays):
            return
        extra = start_cursor(len(rays))
        if self.simple is not None:
            extra.update(portal or {"portal_cell": np.full(len(rays), -1, np.int64),
                                    "portal_value": np.zeros(len(rays), np.float32)})
        soa = shadow_soa(rays, **extra)
        if self.crossing_log is not None:
            soa["seg"] = self.crossing_log.launched(self, soa, parent)
        if self.simple is not None and spawned_in is not None:
            simple = spawned_in == self.simple.domain
            if simple.any():  # from a hit on the simplified model: traced there, here
                self.simple.counters["simplified_shadow_rays"] += int(simple.sum())
                local = soa.take(simple)
                blocked = self.simple.occluded(local["origin"], local["direction"],
                                               local["t_max"])
                self._bring_light(local, ~blocked)
                if simple.all():
                    return
                soa, spawned_in = soa.take(~simple), spawned_in[~simple]
        self._advance_shadow(soa, spawned_in)

    def _bring_light(self, rays: SoA, lit: np.ndarray) -> None:
        """Unblocked shadow rays add their light to their paths (and, in a recording frame,
        to their portal cell)."""
        if not lit.any():
            return
        add_unoccluded(self.result.radiance, as_shadow(rays), lit)
        if self.simple is not None and self.simple.records:
            cells = rays["portal_cell"]
            record = lit & (cells >= 0)
            if record.any():
                self.simple.record_into.record(cells[record], rays["portal_value"][record])
                if self.simple.log is not None:
                    self.simple.log.lit(self._path_ids(rays["path"][record]),
                                        rays["portal_value"][record])

    def _process_shadow(self, domain: int, bvh, rays: SoA) -> None:
        self.counters["shadow_tests"] += len(rays)
        blocked = bvh.occluded(rays["origin"], rays["direction"], rays["t_max"])
        if not blocked.all():
            self._advance_shadow(rays.take(~blocked))

    def _advance_shadow(self, rays: SoA, spawned_in: np.ndarray | None = None) -> None:
        """Queue unblocked shadow rays into their next domain; past the last, they bring light."""
        through = self._forward(rays, self.shadow, rays["t_max"], spawned_in)
        self._bring_light(rays, through)
