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
from vastray.schedule.soa import DomainQueues, SoA


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
    """

    name = "image"

    def __init__(self, ctx: PathContext, geometry: DomainGeometry, color_source: str | None,
                 scalar_range: tuple[float, float], owner: np.ndarray | None = None,
                 rank: int = 0, resident_first: bool = True, tally=None):
        self.resident_first = resident_first
        self.tally = tally
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
        waiting = self.radiance.counts() + self.shadow.counts()
        self.counters["rays_in_flight_peak"] = max(self.counters["rays_in_flight_peak"],
                                                   int(waiting.sum()))
        self._resident = resident
        if not waiting.any():
            return None
        if self.resident_first:
            here = [d for d in resident if waiting[d]]
            if here:
                return max(here, key=lambda d: (waiting[d], -d))
        return int(np.argmax(waiting))

    def likely_next(self, current: int) -> int | None:
        """A guess at the next domain, for the preloader: the one ``next_domain`` would pick
        if ``current`` sent no rays on (the second-fullest queue, or with ``resident_first``
        the fullest resident one). The real choice depends on the rays ``current`` sends on,
        so the guess can be wrong; a wrong guess costs a load and evicts a domain."""
        waiting = self.radiance.counts() + self.shadow.counts()
        waiting[current] = 0
        if not waiting.any():
            return None
        if self.resident_first:
            here = [d for d in self._resident if waiting[d]]
            if here:
                return max(here, key=lambda d: (waiting[d], -d))
        return int(np.argmax(waiting))

    def process(self, domain: int, bvh) -> None:
        """Trace every ray waiting for ``domain`` against its loaded BVH."""
        rays = self.radiance.pop(domain)
        shadows = self.shadow.pop(domain)
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
        nxt, entry = self.geometry.next_domain(rays["origin"], rays["direction"], rays["at_t"],
                                               rays["at_d"], limit)
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
        counted = (source >= 0) & (destination >= 0) & (source != destination)
        if counted.any():
            n = self.geometry.n_domains
            pairs = source[counted].astype(np.int64) * n + destination[counted]
            np.add.at(self.tally.sent.reshape(-1), pairs, 1)

    def receive(self, queue: str, domains: np.ndarray, rays: SoA) -> None:
        """Queue rays another node sent for this node's ``domains`` ((m,) each)."""
        (self.radiance if queue == "radiance" else self.shadow).push(domains, rays)

    def take_outbox(self) -> dict[tuple[str, int], list[tuple[np.ndarray, SoA]]]:
        """Rays to send, by (queue, destination node); the outbox is emptied."""
        out, self.outbox = self.outbox, {}
        return out

    def _advance_radiance(self, rays: SoA, spawned_in: np.ndarray | None = None) -> None:
        """Queue rays into their next domain; shade the ones whose hit is final."""
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
        hit = np.nonzero(hits.hit)[0]
        if len(hit) == 0:
            return
        start = time.perf_counter()
        shadow, continuation = shade(self.ctx, radiance.take(hit), hits.take(hit))
        self.counters["shade_s"] += time.perf_counter() - start
        hit_domain = None
        if self.tally is not None:  # each path has one final hit here: its domain by path
            hit_domain = np.full(len(self.ctx.pixel), -1, np.int64)
            hit_domain[radiance.path[hit]] = rays["hit_domain"][hit]
        self._launch_shadow(shadow, None if hit_domain is None else hit_domain[shadow.path])
        self._launch_radiance(continuation,
                              None if hit_domain is None else hit_domain[continuation.path])

    def _launch_radiance(self, rays: RadianceRays, spawned_in: np.ndarray | None = None) -> None:
        if len(rays):
            soa = radiance_soa(rays, self.color_source is not None, **start_cursor(len(rays)))
            self._advance_radiance(soa, spawned_in)

    # -- shadow rays --------------------------------------------------------------------------
    def _launch_shadow(self, rays: ShadowRays, spawned_in: np.ndarray | None = None) -> None:
        if len(rays):
            self._advance_shadow(shadow_soa(rays, **start_cursor(len(rays))), spawned_in)

    def _process_shadow(self, domain: int, bvh, rays: SoA) -> None:
        self.counters["shadow_tests"] += len(rays)
        blocked = bvh.occluded(rays["origin"], rays["direction"], rays["t_max"])
        if not blocked.all():
            self._advance_shadow(rays.take(~blocked))

    def _advance_shadow(self, rays: SoA, spawned_in: np.ndarray | None = None) -> None:
        """Queue unblocked shadow rays into their next domain; past the last, they bring light."""
        through = self._forward(rays, self.shadow, rays["t_max"], spawned_in)
        if through.any():
            add_unoccluded(self.result.radiance, as_shadow(rays), through)
