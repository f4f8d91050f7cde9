"""SpRay's speculative in situ schedule (Park et al., Listings 5-7), the decisions of one node
for one tile, one bounce per iteration (``actors/insitu.py`` carries them out: it sends the
copies, joins the all-reductions and hands their results back).

In every iteration a node:

1. queues its rays speculatively into *every* domain they cross before their best known hit
   (``speculative_copies``): copies for other nodes' domains go to their holders;
2. traces the radiance copies it holds against its own domains (a local closest hit per path)
   and tests the shadow copies for occlusion, setting bits of the **o-buffer**; shades its
   local closest hits *speculatively* and traces their shadow and continuation rays against
   its own domains right away, keeping the results in the **intersection cache**
   (``trace_locally``);
3. after the all-reductions (**t-buffer** MIN of (t, domain) keys, o-buffer OR) retires the
   shadow rays of the previous iteration that no node found occluded (its **retire queue**)
   and resolves the cache: children of hits that won the MIN are kept (their cached local
   results come along as a head start, the **cache queue**), the others are wasted
   (``resolve``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from vastray.render.integrators import (
    PathContext,
    PathResult,
    RadianceRays,
    ShadowRays,
    camera_rays,
    shade,
)
from vastray.render.tracer import NO_DOMAIN, ClosestHits
from vastray.schedule.paths import RADIANCE_FIELDS, SHADOW_FIELDS
from vastray.schedule.soa import SoA, index_of


def hit_keys(t: np.ndarray, domain: np.ndarray) -> np.ndarray:
    """(t, domain) as one uint64 whose order is the lexicographic order (t >= 0 or inf)."""
    bits = np.asarray(t, np.float32).view(np.uint32).astype(np.uint64)
    return (bits << np.uint64(32)) | np.asarray(domain, np.int64).astype(np.uint32).astype(np.uint64)


#: A path's t-buffer key where no node found a hit (``hit_keys`` of an infinite t).
MISS_KEY = hit_keys(np.full(1, np.inf, np.float32), np.full(1, NO_DOMAIN))[0]


def shadow_slots(path: np.ndarray) -> np.ndarray:
    """Position of each shadow ray among the rays of its path (rows of one path contiguous or
    not; order kept)."""
    order = np.argsort(path, kind="stable")
    sorted_path = path[order]
    first = np.searchsorted(sorted_path, sorted_path, side="left")
    slot = np.empty(len(path), np.int64)
    slot[order] = np.arange(len(path)) - first
    return slot


#: The fields a copy carries, by queue: a radiance copy is traced and, where its hit is the
#: receiver's closest, shaded (``RADIANCE_FIELDS``); a shadow copy is tested and its o-buffer
#: bit set (the ray batches' shadow fields, which ``protocol`` requires, and its slot). A
#: radiance ray's cached candidate hit stays with its holder: sent along until session 51,
#: it was about half of a radiance copy's bytes.
COPY_FIELDS = {"radiance": RADIANCE_FIELDS, "shadow": (*SHADOW_FIELDS, "slot")}


@dataclass(frozen=True)
class Copies:
    """Rays queued speculatively into domains, without copying them yet: copy i is ray
    ``ray[i]`` of ``rays`` queued into domain ``domain[i]`` (``rays`` None: no copies)."""

    domain: np.ndarray  # (m,) int
    ray: np.ndarray  # (m,) int rows of ``rays``
    rays: SoA | None

    def take(self, rows: np.ndarray, fields: tuple[str, ...] | None = None) -> SoA:
        """The copies ``rows`` as rays (one gather from the source rays), of ``fields``
        only where given."""
        index = self.ray[rows]
        if fields is None:
            return self.rays.take(index)
        return SoA(**{f: self.rays[f][index] for f in fields})


#: Camera rays ``camera_crossings`` follows, at most: a grid over the image, one a pixel
#: where the image has fewer pixels (about 5 ms of box walks on 1,439 domains).
CROSSING_PROBES = 4096


def camera_crossings(geometry, camera, shading, settings, ao_distance: float,
                     n_domains: int) -> np.ndarray:
    """(D,) int64 how many of up to ``CROSSING_PROBES`` camera rays (sample 0 of pixels
    evenly spread over the image) cross each domain where it is occupied: what every node
    computes alike before a frame, to give the domains crossed most more holders
    (``ownership.insitu_holders``)."""
    pixels = settings.width * settings.height
    pixel = np.unique(np.linspace(0, pixels - 1, min(CROSSING_PROBES, pixels)).astype(np.uint32))
    ctx = PathContext(shading, settings, pixel, np.zeros(len(pixel), np.uint32), ao_distance)
    rays = camera_rays(camera, ctx)
    _, domain, _, _ = geometry.crossings(rays.origin, rays.direction,
                                         np.full(len(pixel), np.inf, np.float32))
    return np.bincount(domain, minlength=n_domains).astype(np.int64)


class InSituSchedule:
    """One node's speculative in-situ schedule of one tile.

    Parameters
    ----------
    ctx : the tile's paths.
    camera : the camera (this node's share of the camera rays starts the first iteration).
    mine : (n,) bool, the paths whose camera rays this node makes.
    owner : (D,) owning rank of each domain; ``rank`` this node's.
    bvhs : this node's domains, loaded, by id.
    geometry, color_source, scalar_range : domain boxes and what hit records interpolate.
    stats : the node's report counters (``shade_s``, ``speculative_rays``, ``wasted_rays``,
        ``intersection_cache_hits`` are added to).
    """

    def __init__(self, ctx, camera, mine: np.ndarray, owner: np.ndarray, rank: int, bvhs: dict,
                 geometry, color_source, scalar_range, stats: dict):
        self.ctx, self.mine, self.owner, self.rank, self.bvhs = ctx, mine, owner, rank, bvhs
        self.geometry, self.color_source, self.scalar_range = geometry, color_source, scalar_range
        self.stats = stats
        self.is_local = np.zeros(len(owner), bool)
        self.is_local[list(bvhs)] = True
        self.n_paths = len(ctx.pixel)
        self.slots = _slot_count(ctx)
        self.result = PathResult.empty(self.n_paths)
        # Rays this node launches next iteration: camera rays of its share to start with.
        cam = camera_rays(camera, ctx).take(np.nonzero(mine)[0])
        self.rays = _with_candidate(cam, local_done=False, color=color_source is not None)
        self.shadows: SoA | None = None  # valid shadow rays to test remotely, then retire
        self.depth = 0
        self._local = None  # this iteration's (best, ray_of_path, obuf, children)
        #: ray queries made since ``take_queries``, per domain: closest hits, occlusions
        self._queries: tuple[dict[int, int], dict[int, int]] = ({}, {})

    def take_queries(self) -> tuple[dict[int, int], dict[int, int]]:
        """(domain -> closest-hit queries, domain -> occlusion queries) made since the last
        call (what the simulator charges an iteration's trace)."""
        queries, self._queries = self._queries, ({}, {})
        return queries

    def _intersect(self, domain: int, origin, direction, t_max):
        tally = self._queries[0]
        tally[domain] = tally.get(domain, 0) + len(origin)
        return self.bvhs[domain].intersect(origin, direction, t_max)

    def _occluded(self, domain: int, origin, direction, t_max) -> np.ndarray:
        tally = self._queries[1]
        tally[domain] = tally.get(domain, 0) + len(origin)
        return self.bvhs[domain].occluded(origin, direction, t_max)

    def iterations(self) -> int:
        """Iterations of the tile: one per bounce, and one more for the last shadow rays."""
        settings = self.ctx.settings
        return settings.bounces + 2 if settings.integrator == "pt" else 2

    def speculative_copies(self) -> dict[str, Copies]:
        """Every ray queued into every domain it crosses (before its cached hit), as
        {"radiance" | "shadow": ``Copies``}: a radiance ray already traced
        against this node's domains is not queued into them again, and a shadow ray made here
        was tested against them when it was made."""
        copies = {}
        rays, shadows = self.rays, self.shadows
        ray = dom = np.zeros(0, np.int64)
        if len(rays):
            ray, dom, _, _ = self.geometry.crossings(rays["origin"], rays["direction"],
                                                     rays["cand_t"])
            keep = ~(rays["local_done"][ray] & self.is_local[dom])
            ray, dom = ray[keep], dom[keep]
        copies["radiance"] = Copies(dom, ray, rays)
        ray = dom = np.zeros(0, np.int64)
        if shadows is not None and len(shadows):
            ray, dom, _, _ = self.geometry.crossings(shadows["origin"], shadows["direction"],
                                                     shadows["t_max"], among=~self.is_local)
        copies["shadow"] = Copies(dom, ray, shadows)
        return copies

    def trace_locally(self, rad_in, shadow_in) -> tuple[np.ndarray, np.ndarray]:
        """Trace the copies for this node's domains (``rad_in``, ``shadow_in``: (domains,
        copies) or None) and shade the local closest hits speculatively; returns what the
        all-reductions take: (n,) t-buffer keys (``hit_keys``) and the (n, slots) o-buffer."""
        best, ray_of_path = self._trace_radiance(self.rays, rad_in, self.n_paths)
        obuf = np.zeros((self.n_paths, self.slots), bool)
        self._trace_shadow(shadow_in, obuf)
        if self.shadows is not None and len(self.shadows):
            obuf[self.shadows["path"], self.shadows["slot"]] |= self.shadows["blocked_here"]
        # Speculative shading of local closest hits, children traced locally (icache).
        hit_paths = np.nonzero(np.isfinite(best.t))[0]
        children = self._shade_locally(self.ctx, best, ray_of_path, hit_paths)
        self._local = (best, ray_of_path, children)
        return hit_keys(best.t, best.domain), obuf

    def resolve(self, global_keys: np.ndarray, occluded: np.ndarray) -> None:
        """Take the all-reductions' results ((n,) keys after the MIN, (n, slots) bool after
        the OR): retire the shadow rays nobody found occluded and keep the children of the
        hits that won; the next iteration launches those."""
        best, ray_of_path, children = self._local
        shadows = self.shadows
        if shadows is not None and len(shadows):
            lit = ~occluded[shadows["path"], shadows["slot"]]
            np.add.at(self.result.radiance, shadows["path"][lit], shadows["contribution"][lit])
        won = hit_keys(best.t, best.domain) == global_keys
        if self.depth == 0:
            self._record_camera(self.ctx, self.result, best, ray_of_path, won, global_keys,
                                self.mine)
        self.rays, self.shadows = self._resolve(children, won)
        self.depth += 1
        self._local = None

    # -- tracing ------------------------------------------------------------------------------
    def _trace_radiance(self, rays: SoA, rad_in, n_paths: int):
        """Local closest hit per path: cached candidates, then this node's domains."""
        best = ClosestHits.empty(n_paths, self.color_source is not None)
        ray_of_path = {}
        if len(rays):
            # Candidates from the intersection cache (traced here last iteration).
            has = np.isfinite(rays["cand_t"])
            p = rays["path"][has]
            best.t[p], best.domain[p] = rays["cand_t"][has], rays["cand_d"][has]
            best.ng[p], best.material[p] = rays["cand_ng"][has], rays["cand_material"][has]
            best.point[p], best.error[p] = rays["cand_point"][has], rays["cand_error"][has]
            if best.color is not None:
                best.color[p] = rays["cand_color"][has]
            ray_of_path["own"] = rays
        if rad_in is not None:
            dom, copies = rad_in
            ray_of_path["in"] = copies
            for d, rows in by_domain(dom):
                path = copies["path"][rows]
                r = self._intersect(int(d), copies["origin"][rows], copies["direction"][rows],
                                    best.t[path])
                best.offer(path, int(d), self.bvhs[int(d)], r, self.color_source,
                           self.scalar_range)
        return best, ray_of_path

    def _trace_shadow(self, shadow_in, obuf: np.ndarray) -> None:
        if shadow_in is None:
            return
        dom, copies = shadow_in
        for d, rows in by_domain(dom):
            blocked = self._occluded(int(d), copies["origin"][rows], copies["direction"][rows],
                                     copies["t_max"][rows])
            obuf[copies["path"][rows][blocked], copies["slot"][rows][blocked]] = True

    def _shade_locally(self, ctx, best: ClosestHits, ray_of_path: dict, hit_paths: np.ndarray):
        if len(hit_paths) == 0:
            return None
        rays = _radiance_for(ray_of_path, hit_paths)
        start = time.perf_counter()
        shadow, cont = shade(ctx, rays, best.hits(hit_paths))
        self.stats["shade_s"] += time.perf_counter() - start
        self.stats["speculative_rays"] += len(shadow) + len(cont)
        # Intersection cache: children meet this node's domains now.
        blocked_here = self._occluded_locally(shadow)
        cand = self._closest_locally(cont)
        return shadow, blocked_here, cont, cand

    def _occluded_locally(self, shadow: ShadowRays) -> np.ndarray:
        blocked = np.zeros(len(shadow), bool)
        if len(shadow) == 0:
            return blocked
        ray, dom, _, _ = self.geometry.crossings(shadow.origin, shadow.direction, shadow.t_max,
                                                 among=self.is_local)
        for d, pairs in by_domain(dom):
            rows = np.unique(ray[pairs])
            rows = rows[~blocked[rows]]
            if len(rows):
                blocked[rows] |= self._occluded(int(d), shadow.origin[rows],
                                                shadow.direction[rows], shadow.t_max[rows])
        return blocked

    def _closest_locally(self, cont: RadianceRays) -> ClosestHits:
        cand = ClosestHits.empty(len(cont), self.color_source is not None)
        if len(cont) == 0:
            return cand
        ray, dom, _, _ = self.geometry.crossings(cont.origin, cont.direction,
                                                 np.full(len(cont), np.inf, np.float32),
                                                 among=self.is_local)
        for d, pairs in by_domain(dom):
            rows = ray[pairs]
            r = self._intersect(int(d), cont.origin[rows], cont.direction[rows], cand.t[rows])
            cand.offer(rows, int(d), self.bvhs[int(d)], r, self.color_source, self.scalar_range)
        return cand

    # -- resolution ---------------------------------------------------------------------------
    def _record_camera(self, ctx, result, best, ray_of_path, won, global_keys, mine) -> None:
        """First hits and camera emission, once, by the node that owns the winning hit (or,
        for rays that hit nothing anywhere, by the node that made the camera ray)."""
        miss = global_keys == MISS_KEY
        winners = np.nonzero(won & np.isfinite(best.t))[0]
        if len(winners):
            result.record_camera_hits(ctx, _radiance_for(ray_of_path, winners),
                                      best.hits(winners))
        missed = np.nonzero(miss & mine)[0]
        if len(missed) and "own" in ray_of_path:
            rays = _radiance_for({"own": ray_of_path["own"]}, missed)
            result.record_camera_hits(ctx, rays, ClosestHits.empty(len(missed), False).hits())

    def _resolve(self, children, won: np.ndarray):
        color = self.color_source is not None
        if children is None:
            return _with_candidate(_no_radiance(), False, color), None
        shadow, blocked_here, cont, cand = children
        keep_shadow = won[shadow.path] & ~blocked_here
        keep_cont = won[cont.path]
        self.stats["wasted_rays"] += int((~won[shadow.path]).sum() + (~keep_cont).sum())
        # Results of the intersection cache that a winning hit's children reuse: shadow rays
        # already found blocked here, continuation rays already holding a local hit.
        self.stats["intersection_cache_hits"] += int(
            (won[shadow.path] & blocked_here).sum() + np.isfinite(cand.t[keep_cont]).sum())
        s = shadow.take(np.nonzero(keep_shadow)[0])
        shadows = SoA(**{f: getattr(s, f) for f in SHADOW_FIELDS},
                      slot=shadow_slots(shadow.path)[keep_shadow],
                      blocked_here=np.zeros(len(s), bool))
        rows = np.nonzero(keep_cont)[0]
        rays = _with_candidate(cont.take(rows), True, color, cand, rows)
        return rays, shadows


def by_domain(domain: np.ndarray):
    """Yield ``(d, rows)`` for each distinct ``d`` of ``domain`` ((m,) ints), ascending:
    ``rows`` are the positions where ``domain == d``, ascending. One sort, not one scan of all
    m entries per domain."""
    order = np.argsort(domain, kind="stable")
    values, first, counts = np.unique(domain[order], return_index=True, return_counts=True)
    for d, start, count in zip(values.tolist(), first.tolist(), counts.tolist(), strict=True):
        yield d, order[start:start + count]


def _slot_count(ctx) -> int:
    settings = ctx.settings
    if settings.integrator == "ao":
        return max(settings.shadow_samples, 1)
    return max(1, sum(settings.shadow_samples if light.stochastic else 1
                      for light in ctx.shading.lights))


def _with_candidate(rays: RadianceRays, local_done: bool, color: bool,
                    cand: ClosestHits | None = None, rows: np.ndarray | None = None) -> SoA:
    n = len(rays)
    c = ClosestHits.empty(n, color) if cand is None else ClosestHits(
        cand.t[rows], cand.domain[rows], cand.ng[rows], cand.material[rows],
        None if cand.color is None else cand.color[rows], cand.point[rows], cand.error[rows])
    fields = {f: getattr(rays, f) for f in RADIANCE_FIELDS}
    fields.update(cand_t=c.t, cand_d=c.domain, cand_ng=c.ng, cand_material=c.material,
                  cand_point=c.point, cand_error=c.error,
                  local_done=np.full(n, local_done))
    if color:
        fields["cand_color"] = c.color
    return SoA(**fields)


def _no_radiance() -> RadianceRays:
    return RadianceRays(np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros((0, 3), np.float32),
                        np.zeros((0, 3), np.float32), np.zeros((0, 3)))


def _radiance_for(ray_of_path: dict, paths: np.ndarray) -> RadianceRays:
    """The radiance ray of each of ``paths`` (from this node's own rays or received copies)."""
    sources = [s for s in (ray_of_path.get("own"), ray_of_path.get("in")) if s is not None]
    table = SoA.concat([SoA(**{f: s[f] for f in RADIANCE_FIELDS}) for s in sources])
    index = index_of(table["path"], paths)
    return RadianceRays(*(table[f][index] for f in RADIANCE_FIELDS))
