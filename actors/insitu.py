"""SpRay's speculative in situ schedule (Park et al., Listings 5-7) on the nodes: each node
loads the domains it owns (runs of the z-order curve, as in the paper, here of equal
triangles: ``ownership.insitu_owners``), and those it also holds (the domains the camera rays
cross most have more holders: ``ownership.insitu_holders``), and keeps them; per tile, it
carries out ``schedule.spec_insitu.InSituSchedule`` one bounce per iteration: it sends the
speculative copies of its rays to the holders of the domains they cross (over two hops of a
grid of nodes, ``schedule.relay``), takes the copies for its own domains, and joins the
all-reduction over the tree of nodes (t-buffer MIN, o-buffer OR) whose result resolves the
iteration.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from vastray.actors import protocol
from vastray.actors.domain_loop import counted_bookkeeping
from vastray.actors.job_options import JobOptions
from vastray.actors.node_state import NodeState, frame_load_stats
from vastray.actors.ray_post import RayPost, traffic_counters
from vastray.actors.render_setup import RenderSetup
from vastray.preflight import domain_footprints
from vastray.render.driver import path_context
from vastray.render.film import Film
from vastray.render.integrators import PathResult
from vastray.scene.embree.launch import cpu_time
from vastray.schedule.ownership import Holders, insitu_holders, insitu_owners, interleaved_paths
from vastray.schedule.relay import relay_of, routes
from vastray.schedule.soa import SoA, join_bound
from vastray.schedule.spec_insitu import COPY_FIELDS, MISS_KEY, InSituSchedule, camera_crossings


async def render_spec_insitu(management, tree, options: JobOptions, rank: int, size: int,
                             store, config, settings, on_tile=None,
                             state: NodeState | None = None) -> tuple[Film, dict]:
    """This node's partial film of a spec-insitu render (summed over nodes afterwards);
    ``on_tile(paths)`` hears of the paths this node started, after each tile. ``state``
    keeps the node's preloader (its domains stay loaded) from one frame to the next."""
    setup = RenderSetup.of(store, config, settings)
    lo, hi = store.domain_boxes()
    owner = insitu_owners(lo, hi, store.domain_triangles(), size)
    holders = Holders.owned(owner)
    if size > 1:  # more holders for the domains the camera rays cross most, as every node sees
        weights = camera_crossings(setup.geometry, setup.camera, setup.shading, settings,
                                   setup.ao_distance, len(owner))
        holders = insitu_holders(owner, weights, size,
                                 domain_footprints(store.domains, setup.fast_builds))
    local = [int(d) for d in holders.held_by(rank) if store.domains[d].n_triangles]
    own_state = state is None
    state = NodeState() if state is None else state
    preloader = state.preloader_for(store, max(len(local), 1), setup.keep, options, rank,
                                    setup.fast_builds)
    before = preloader.stats()
    # In situ the node's data stays loaded: the loop only loads it (each domain's rays are
    # traced in the iterations below, all domains at once, not activation by activation).
    bvhs = await state.domain_loop(preloader, {}).load_all(local)
    film = Film(settings.width, settings.height)
    total = setup.total_paths
    tile = max(1, min(options.max_samples_in_flight or total, total))
    stats = {**traffic_counters(), "shade_s": 0.0, "speculative_rays": 0, "wasted_rays": 0,
             "intersection_cache_hits": 0, "iterations": 0, "tbuffer_paths": 0,
             "rays_relayed": 0, "domains_also_held": int(np.count_nonzero(
                 owner[local] != rank)) if local else 0}
    runner = _InSitu(management, tree, rank, size, holders, bvhs, setup.geometry,
                     setup.color_source, setup.scalar_range, stats, state.traced,
                     state.decided)
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
    """Carries out one node's ``InSituSchedule`` per tile: sends its speculative copies,
    takes the copies for its domains, joins the all-reductions."""

    def __init__(self, management, tree, rank, size, holders: Holders, bvhs, geometry,
                 color_source, scalar_range, stats, traced, decided):
        self.management, self.tree, self.rank, self.size = management, tree, rank, size
        self.holders = holders
        self.bvhs, self.geometry = bvhs, geometry
        self.color_source, self.scalar_range, self.stats = color_source, scalar_range, stats
        self.post = RayPost(management, rank, stats)
        self.traced = traced  # hears of the queries each iteration traced (``NodeState``)
        self.decided = decided  # hears of the CPU time spent deciding (``NodeState``)
        self._uncharged_s = 0.0  # bookkeeping CPU not yet charged (``_bookkeeping``)

    async def tile(self, ctx, camera, mine: np.ndarray, tile: int) -> PathResult:
        schedule = InSituSchedule(ctx, camera, mine, self.holders.owner, self.rank, self.bvhs,
                                  self.geometry, self.color_source, self.scalar_range,
                                  self.stats)
        active = np.ones(schedule.n_paths, bool)  # paths the buffers cover this iteration
        for depth in range(schedule.iterations()):
            self.stats["iterations"] += 1
            rad_in, shadow_in = await self._exchange(schedule, tile, depth)
            cpu = cpu_time()
            keys, obuf = schedule.trace_locally(rad_in, shadow_in)
            await self.traced(*schedule.take_queries(), cpu_time() - cpu)
            # All-reduce: t-buffer MIN, o-buffer OR, over the active paths only
            global_keys, occluded = await self._reduce_buffers(keys, obuf, active)
            cpu = cpu_time()
            schedule.resolve(global_keys, occluded)
            # a path has rays next iteration only if it hit something in this one: every node
            # holds the MIN, so every node drops the same paths from the next buffers
            active = global_keys != MISS_KEY
            await self.decided(cpu_time() - cpu)
        return schedule.result

    async def _reduce_buffers(self, keys: np.ndarray, obuf: np.ndarray, active: np.ndarray
                              ) -> tuple[np.ndarray, np.ndarray]:
        """The t-buffer's MIN and the o-buffer's OR over the nodes, for the ``active`` paths.

        ``keys`` (n,) uint64 and ``obuf`` (n, slots) bool are this node's, ``active`` (n,)
        bool the same on every node: the paths whose last iteration found a hit somewhere.
        Any other path has no ray in this iteration on any node, so its key is the miss and
        its bits are clear everywhere, and leaving it out of the reduction changes nothing
        (Listing 5 reduces the whole buffers; once most paths have left the data, as in a
        frame mostly background or deep bounces, that is most of the bytes). Returns (n,)
        keys and (n, slots) bits, the inactive paths' the miss and clear."""
        rows = np.flatnonzero(active)
        self.stats["tbuffer_paths"] += len(rows)
        part = obuf[rows]
        reduced = await self.tree.allreduce(
            {"t": keys[rows], "o": np.packbits(part, axis=None)}, {"t": "min", "o": "or"})
        cpu = cpu_time()
        global_keys = np.full(len(keys), MISS_KEY, np.uint64)
        global_keys[rows] = reduced["t"]
        occluded = np.zeros(obuf.shape, bool)
        occluded[rows] = np.unpackbits(reduced["o"], count=part.size).reshape(part.shape) > 0
        await self.decided(cpu_time() - cpu)
        return global_keys, occluded

    async def _exchange(self, schedule: InSituSchedule, tile: int, depth: int):
        """Send the schedule's speculative copies to the holders of their domains (a path's
        copy in a domain of k holders to holder ``path mod k``: ``Holders.destination``) over
        two hops (``schedule.relay``: to the node of this node's row in the holder's column,
        which forwards them down its column), relay the copies that come here for others;
        returns the copies for this node's domains, its own and the peers'.

        Every pair of the routes carries one batch per queue and hop, empty or not, so each
        node knows how many batches to wait for without asking the others: 2 (w - 1) pairs
        of a node on a grid of w = ceil(sqrt P) columns (sent straight, a batch per peer and
        queue made P^2 messages an iteration, and only batches where rays went needed their
        counts summed over the tree first).
        """
        incoming = {"radiance": [], "shadow": []}
        relayed = {"radiance": [], "shadow": []}  # (to, domains, copies) this node forwards
        cpu = cpu_time()
        speculative = schedule.speculative_copies()
        await self.decided(cpu_time() - cpu)
        with self._bookkeeping():  # the copies cut by where they go first
            first_hop = {}
            for name, copies in speculative.items():
                dom = copies.domain
                if not len(dom):
                    continue
                to = self.holders.destination(dom, copies.rays["path"][copies.ray])
                via = relay_of(self.size, self.rank, to)
                fields = COPY_FIELDS[name]
                mine = np.flatnonzero(to == self.rank)
                if len(mine):
                    incoming[name].append((dom[mine], copies.take(mine, fields)))
                forward = np.flatnonzero((via == self.rank) & (to != self.rank))
                if len(forward):
                    relayed[name].append((to[forward], dom[forward],
                                          copies.take(forward, fields)))
                away = np.flatnonzero(via != self.rank)
                if not len(away):
                    continue
                order = away[np.argsort(via[away], kind="stable")]
                nodes, first = np.unique(via[order], return_index=True)
                for node, rows in zip(nodes, np.split(order, first[1:]), strict=True):
                    batch = copies.take(rows, fields)
                    batch["to"] = to[rows]
                    first_hop[int(node), name] = (dom[rows], batch)
        await self._charge_bookkeeping()
        first_hops, second_hops = routes(self.size)
        await self._send_hop(first_hops.to(self.rank), first_hop, tile, depth, 1)
        expect = {1: 2 * first_hops.count_from(self.rank),
                  2: 2 * second_hops.count_from(self.rank)}
        received = {1: 0, 2: 0}
        while received[1] < expect[1] or received[2] < expect[2]:
            if received[1] == expect[1] and relayed is not None:
                await self._send_hop(second_hops.to(self.rank), self._second_hop(relayed),
                                     tile, depth, 2)
                relayed = None
                continue
            message = await self.management.receive(protocol.RAYS, "ray batch")
            try:
                hop = check_copies(message, tile, depth, self.holders, self.rank, self.size,
                                   schedule.n_paths, schedule.slots, schedule.is_local)
            except protocol.ProtocolError as exc:
                self.management.rejections.add("malformed", str(exc))
                continue
            received[hop] += 1
            self.post.received(message)
            if message.arrays:
                with self._bookkeeping():  # the batch copied out of its message
                    arrays = {k: np.array(v) for k, v in message.arrays.items()}
                    dom, to = arrays.pop("domain"), arrays.pop("to", None)
                    queue = message.meta["queue"]
                    if to is None:
                        incoming[queue].append((dom, SoA(**arrays)))
                    else:
                        here = to == self.rank
                        rays = SoA(**arrays)
                        if here.all():
                            incoming[queue].append((dom, rays))
                        else:
                            incoming[queue].append((dom[here], rays.take(np.flatnonzero(here))))
                            on = np.flatnonzero(~here)
                            self.stats["rays_relayed"] += len(on)
                            relayed[queue].append((to[on], dom[on], rays.take(on)))
        if relayed is not None:  # a node that receives no first hop (one node, or P = 2)
            await self._send_hop(second_hops.to(self.rank), self._second_hop(relayed),
                                 tile, depth, 2)
        with self._bookkeeping():
            joined = join_bound(incoming["radiance"]), join_bound(incoming["shadow"])
        await self._charge_bookkeeping()
        return joined

    def _second_hop(self, relayed: dict) -> dict:
        """The copies this node forwards, as one batch per destination and queue."""
        batches = {}
        with self._bookkeeping():
            for name, parts in relayed.items():
                if not parts:
                    continue
                to = np.concatenate([p[0] for p in parts])
                dom, rays = join_bound([(p[1], p[2]) for p in parts])
                order = np.argsort(to, kind="stable")
                nodes, first = np.unique(to[order], return_index=True)
                for node, rows in zip(nodes, np.split(order, first[1:]), strict=True):
                    batches[int(node), name] = (dom[rows], rays.take(rows))
        return batches

    async def _send_hop(self, nodes: list[int], batches: dict, tile: int, depth: int,
                        hop: int) -> None:
        """A batch of each queue to each of ``nodes`` (empty where ``batches``, keyed by
        (node, queue), has none for it)."""
        await self._charge_bookkeeping()
        for node in nodes:
            for name in ("radiance", "shadow"):
                dom, rays = batches.get((node, name), (None, None))
                await self.post.send(node, name, {"tile": tile, "depth": depth, "hop": hop},
                                     dom, rays)

    @contextmanager
    def _bookkeeping(self) -> Iterator[None]:
        """Count the CPU of the enclosed code (no await inside: the event loop's other tasks
        would count too) as ``bookkeeping_cpu_s``: moving the speculative copies between
        arrays and messages, outside the traces and the schedule's decisions. Uncounted, the
        simulator (which runs this code) charged none of it (issue 38, as ``DomainLoop``'s
        ``bookkeeping``)."""
        with counted_bookkeeping(self.stats, self._leave_uncharged):
            yield

    def _leave_uncharged(self, cpu_seconds: float) -> None:
        self._uncharged_s += cpu_seconds

    async def _charge_bookkeeping(self) -> None:
        """Charge the bookkeeping counted since the last charge, as a decision (the
        simulator's clock; a real node has spent it already)."""
        spent, self._uncharged_s = self._uncharged_s, 0.0
        await self.decided(spent)


def check_copies(message, tile: int, depth: int, holders: Holders, rank: int, size: int,
                 n_paths: int, slots: int, is_local: np.ndarray) -> int:
    """The hop (1 or 2) of a batch of copies for node ``rank`` of ``size`` in iteration
    ``depth`` of ``tile``, ``holders`` the domains' (``Holders.destination`` names the node
    each copy is for), ``is_local`` (D,) bool those this node holds; raises
    ``protocol.ProtocolError`` unless it is of this iteration, from a peer, its indices fit
    the tile (``n_paths`` paths, ``slots`` shadow slots a path), and its rays are for this
    node's domains or, on a first hop, for peers this node relays to from its sender (a
    copy forwarded anywhere else would never arrive: the routes fix every batch)."""
    meta = message.meta
    hop, sender = meta.get("hop"), meta.get("rank")
    if hop not in (1, 2):
        raise protocol.ProtocolError(f"rays: hop must be 1 or 2, not {hop!r}")
    if meta.get("tile") != tile or meta.get("depth") != depth:
        raise protocol.ProtocolError(f"rays of tile {meta.get('tile')!r} iteration "
                                     f"{meta.get('depth')!r} in tile {tile} iteration {depth}")
    if type(sender) is not int or not 0 <= sender < size or sender == rank:
        raise protocol.ProtocolError(f"rays from {sender!r}, not a peer of {size} nodes")
    protocol.check_ray_index(message, "path", n_paths)
    protocol.check_ray_index(message, "slot", slots)
    protocol.check_ray_index(message, "to", size)
    domain = message.arrays.get("domain")
    if domain is None or not len(domain):
        return hop
    if int(domain.max()) >= len(is_local):
        raise protocol.ProtocolError("rays: domain id beyond the store's")
    to, path = message.arrays.get("to"), message.arrays.get("path")
    if (to is None) != (hop == 2):
        raise protocol.ProtocolError("rays: a first hop, and it alone, names its rays' 'to'")
    if path is None:
        raise protocol.ProtocolError("rays: copies need their 'path'")
    destination = np.full(len(domain), rank) if to is None else to
    if not np.array_equal(holders.destination(domain, path), destination):
        raise protocol.ProtocolError("rays for a domain their destination does not hold")
    if to is not None and not (relay_of(size, sender, to) == rank).all():
        raise protocol.ProtocolError(f"rays from node {sender} that node {rank} does not "
                                     "relay")
    if not is_local[domain[destination == rank]].all():
        raise protocol.ProtocolError("rays for a domain this node does not hold")
    return hop
