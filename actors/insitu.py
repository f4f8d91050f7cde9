"""SpRay's speculative in situ schedule (Park et al., Listings 5-7), one bounce per iteration.

Domains stay on the nodes that own them (assigned along the z-order curve, as in the paper).
In every iteration each node:

1. queues its rays speculatively into *every* domain they cross before their best known hit,
   and sends the copies to the domains' owners (one radiance and one shadow batch per peer);
2. traces the radiance copies it received against its own domains (a local closest hit per
   path), and tests the shadow copies for occlusion, setting bits of the **o-buffer**;
3. shades its local closest hits *speculatively* and traces their shadow and continuation
   rays against its own domains right away, keeping the results in the **intersection cache**;
4. joins two all-reductions over the tree of nodes: **t-buffer** MIN of (t, domain) keys, which
   makes every path's closest hit global, and o-buffer bitwise OR;
5. retires the shadow rays of the previous iteration (its **retire queue**) that no node found
   occluded, and resolves the cache: children of hits that won the MIN are kept (their cached
   local results come along as a head start, the **cache queue**), the others are wasted.
"""

from __future__ import annotations

import time

import numpy as np

from vastray.actors import protocol
from vastray.actors.decomposition import NodeState, frame_load_stats
from vastray.actors.domain_loop import DomainLoop
from vastray.actors.job_options import JobOptions
from vastray.actors.local import RenderSetup
from vastray.actors.ray_post import RayPost, traffic_counters
from vastray.render.driver import path_context
from vastray.render.film import Film
from vastray.render.integrators import PathResult, RadianceRays, ShadowRays, camera_rays, shade
from vastray.render.tracer import NO_DOMAIN, ClosestHits
from vastray.schedule.ownership import interleaved_paths, zorder_owners
from vastray.schedule.paths import RADIANCE_FIELDS, SHADOW_FIELDS
from vastray.schedule.soa import SoA


def hit_keys(t: np.ndarray, domain: np.ndarray) -> np.ndarray:
    """(t, domain) as one uint64 whose order is the lexicographic order (t >= 0 or inf)."""
    bits = np.asarray(t, np.float32).view(np.uint32).astype(np.uint64)
    return (bits << np.uint64(32)) | np.asarray(domain, np.int64).astype(np.uint32).astype(np.uint64)


def shadow_slots(path: np.ndarray) -> np.ndarray:
    """Position of each shadow ray among the rays of its path (rows of one path contiguous or
    not; order kept)."""
    order = np.argsort(path, kind="stable")
    sorted_path = path[order]
    first = np.searchsorted(sorted_path, sorted_path, side="left")
    slot = np.empty(len(path), np.int64)
    slot[order] = np.arange(len(path)) - first
    return slot


async def render_spec_insitu(management, tree, options: JobOptions, rank: int, size: int,
                             store, config, settings, on_tile=None,
                             state: NodeState | None = None) -> tuple[Film, dict]:
    """This node's partial film of a spec-insitu render (summed over nodes afterwards);
    ``on_tile(paths)`` hears of the paths this node started, after each tile. ``state``
    keeps the node's preloader (its domains stay loaded) from one frame to the next."""
    setup = RenderSetup.of(store, config, settings)
    lo, hi = store.domain_boxes()
    owner = zorder_owners(lo, hi, size)
    local = [int(d) for d in np.nonzero(owner == rank)[0] if store.domains[d].n_triangles]
    own_state = state is None
    state = NodeState() if state is None else state
    preloader = state.preloader_for(store, max(len(local), 1), setup.keep, options, rank)
    before = preloader.stats()
    # In situ the node's data stays loaded: the loop only loads it (each domain's rays are
    # traced in the iterations below, all domains at once, not activation by activation).
    bvhs = await DomainLoop(preloader, {}).load_all(local)
    film = Film(settings.width, settings.height)
    total = setup.total_paths
    tile = max(1, min(options.max_samples_in_flight or total, total))
    stats = {**traffic_counters(), "shade_s": 0.0, "speculative_rays": 0, "wasted_rays": 0,
             "intersection_cache_hits": 0, "iterations": 0}
    runner = _InSitu(management, tree, rank, size, owner, local, bvhs, setup.geometry,
                     setup.color_source, setup.scalar_range, stats)
    for index, first in enumerate(range(0, total, tile)):
        ctx = path_context(setup.shading, settings, first, min(first + tile, total),
                           setup.ao_distance)
        mine = interleaved_paths(len(ctx.pixel), rank, size)
        result = await runner.tile(ctx, setup.camera, mine, index)
        film.add_paths(ctx.pixel, ctx.sample, result, counted=mine)
        if on_tile is not None:
            on_tile(int(np.count_nonzero(mine)))
    stats["threads"] = state.threads()
    stats.update(frame_load_stats(before, preloader.stats()))
    stats["load_bandwidth_mb_s"] = preloader.load_bandwidth_mb_s()
    if own_state:
        state.close()
    return film, stats


class _InSitu:
    def __init__(self, management, tree, rank, size, owner, local, bvhs, geometry, color_source,
                 scalar_range, stats):
        self.management, self.tree, self.rank, self.size = management, tree, rank, size
        self.owner, self.local, self.bvhs, self.geometry = owner, local, bvhs, geometry
        self.color_source, self.scalar_range, self.stats = color_source, scalar_range, stats
        self.post = RayPost(management, rank, stats)
        self.is_local = np.zeros(len(owner), bool)
        self.is_local[local] = True

    async def tile(self, ctx, camera, mine: np.ndarray, tile: int) -> PathResult:
        n_paths = len(ctx.pixel)
        result = PathResult.empty(n_paths)
        slots = _slot_count(ctx)
        # Rays this node launches next iteration: camera rays of its share to start with.
        cam = camera_rays(camera, ctx).take(np.nonzero(mine)[0])
        rays = _with_candidate(cam, local_done=False, color=self.color_source is not None)
        shadows: SoA | None = None        # valid shadow rays to test remotely, then retire
        for depth in range(ctx.settings.bounces + 2 if ctx.settings.integrator == "pt" else 2):
            self.stats["iterations"] += 1
            rad_in, shadow_in = await self._exchange(rays, shadows, tile, depth, n_paths, slots)
            best, ray_of_path = self._trace_radiance(rays, rad_in, n_paths)
            obuf = np.zeros((n_paths, slots), bool)
            self._trace_shadow(shadow_in, obuf)
            if shadows is not None and len(shadows):
                obuf[shadows["path"], shadows["slot"]] |= shadows["blocked_here"]
            # Speculative shading of local closest hits, children traced locally (icache).
            hit_paths = np.nonzero(np.isfinite(best.t))[0]
            children = self._shade_locally(ctx, best, ray_of_path, hit_paths)
            # All-reduce: t-buffer MIN, o-buffer OR.
            reduced = await self.tree.allreduce(
                {"t": hit_keys(best.t, best.domain), "o": np.packbits(obuf, axis=None)},
                {"t": "min", "o": "or"})
            global_keys = reduced["t"]
            occluded = np.unpackbits(reduced["o"], count=obuf.size).reshape(obuf.shape) > 0
            # Retire the shadow rays tested this iteration that nobody found occluded.
            if shadows is not None and len(shadows):
                lit = ~occluded[shadows["path"], shadows["slot"]]
                np.add.at(result.radiance, shadows["path"][lit], shadows["contribution"][lit])
            # Resolve: keep the children of hits that won globally.
            won = hit_keys(best.t, best.domain) == global_keys
            if depth == 0:
                self._record_camera(ctx, result, best, ray_of_path, won, global_keys, mine)
            rays, shadows = self._resolve(children, won)
        return result

    # -- exchange -----------------------------------------------------------------------------
    async def _exchange(self, rays: SoA, shadows: SoA | None, tile: int, depth: int,
                        n_paths: int, slots: int):
        """Queue every ray into the domains it crosses (before its cached hit); local copies
        stay, the others go to their owners; returns the copies for this node's domains."""
        parts = {"radiance": [], "shadow": []}
        if len(rays):
            ray, dom, _, _ = self.geometry.crossings(rays["origin"], rays["direction"],
                                                     rays["cand_t"])
            skip = rays["local_done"][ray] & self.is_local[dom]
            parts["radiance"] = (ray[~skip], dom[~skip])
        if shadows is not None and len(shadows):
            ray, dom, _, _ = self.geometry.crossings(shadows["origin"], shadows["direction"],
                                                     shadows["t_max"])
            keep = ~self.is_local[dom]  # local domains were tested when the rays were made
            parts["shadow"] = (ray[keep], dom[keep])
        incoming = {"radiance": [], "shadow": []}
        for name, source in (("radiance", rays), ("shadow", shadows)):
            if not parts[name]:
                ray, dom = np.zeros(0, np.int64), np.zeros(0, np.int64)
            else:
                ray, dom = parts[name]
            dest = self.owner[dom]
            mine = dest == self.rank
            if mine.any():
                incoming[name].append((dom[mine], source.take(ray[mine])))
            for node in range(self.size):
                if node == self.rank:
                    continue
                rows = dest == node  # one batch per peer and queue, empty or not
                batch = (dom[rows], source.take(ray[rows])) if rows.any() else ()
                await self.post.send(node, name, {"tile": tile, "depth": depth}, *batch)
        received = 0
        while received < 2 * (self.size - 1):
            message = await self.management.receive(protocol.RAYS, "ray batch")
            try:  # indices into this tile's paths and shadow slots
                protocol.check_ray_index(message, "path", n_paths)
                protocol.check_ray_index(message, "slot", slots)
                domain = message.arrays.get("domain")
                if domain is not None and not self.is_local[domain].all():
                    raise protocol.ProtocolError("rays for a domain this node does not hold")
            except protocol.ProtocolError as exc:
                self.management.rejections.add("malformed", str(exc))
                continue
            received += 1
            self.post.received(message)
            if message.arrays:
                arrays = {k: np.array(v) for k, v in message.arrays.items()}
                dom = arrays.pop("domain")
                incoming[message.meta["queue"]].append((dom, SoA(**arrays)))
        return _joined(incoming["radiance"]), _joined(incoming["shadow"])

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
                r = self.bvhs[int(d)].intersect(copies["origin"][rows], copies["direction"][rows],
                                               best.t[path])
                best.offer(path, int(d), self.bvhs[int(d)], r, self.color_source,
                           self.scalar_range)
        return best, ray_of_path

    def _trace_shadow(self, shadow_in, obuf: np.ndarray) -> None:
        if shadow_in is None:
            return
        dom, copies = shadow_in
        for d, rows in by_domain(dom):
            blocked = self.bvhs[int(d)].occluded(copies["origin"][rows], copies["direction"][rows],
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
        ray, dom, _, _ = self.geometry.crossings(shadow.origin, shadow.direction, shadow.t_max)
        here = self.is_local[dom]
        ray = ray[here]
        for d, pairs in by_domain(dom[here]):
            rows = np.unique(ray[pairs])
            rows = rows[~blocked[rows]]
            if len(rows):
                blocked[rows] |= self.bvhs[int(d)].occluded(shadow.origin[rows],
                                                            shadow.direction[rows],
                                                            shadow.t_max[rows])
        return blocked

    def _closest_locally(self, cont: RadianceRays) -> ClosestHits:
        cand = ClosestHits.empty(len(cont), self.color_source is not None)
        if len(cont) == 0:
            return cand
        ray, dom, _, _ = self.geometry.crossings(cont.origin, cont.direction,
                                                 np.full(len(cont), np.inf, np.float32))
        here = self.is_local[dom]
        ray = ray[here]
        for d, pairs in by_domain(dom[here]):
            rows = ray[pairs]
            r = self.bvhs[int(d)].intersect(cont.origin[rows], cont.direction[rows], cand.t[rows])
            cand.offer(rows, int(d), self.bvhs[int(d)], r, self.color_source, self.scalar_range)
        return cand

    # -- resolution ---------------------------------------------------------------------------
    def _record_camera(self, ctx, result, best, ray_of_path, won, global_keys, mine) -> None:
        """First hits and camera emission, once, by the node that owns the winning hit (or,
        for rays that hit nothing anywhere, by the node that made the camera ray)."""
        miss = global_keys == hit_keys(np.full(1, np.inf, np.float32), np.full(1, NO_DOMAIN))
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


def _joined(parts: list):
    if not parts:
        return None
    return (np.concatenate([d for d, _ in parts]), SoA.concat([r for _, r in parts]))


def _radiance_for(ray_of_path: dict, paths: np.ndarray) -> RadianceRays:
    """The radiance ray of each of ``paths`` (from this node's own rays or received copies)."""
    sources = [s for s in (ray_of_path.get("own"), ray_of_path.get("in")) if s is not None]
    table = SoA.concat([SoA(**{f: s[f] for f in RADIANCE_FIELDS}) for s in sources])
    order = np.argsort(table["path"], kind="stable")
    index = order[np.searchsorted(table["path"][order], paths)]
    return RadianceRays(*(table[f][index] for f in RADIANCE_FIELDS))
