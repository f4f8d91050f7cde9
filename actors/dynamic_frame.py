"""``dynamic``'s frame: Navrátil's ray-weighted rounds (Figs. 5-6) over a frame's tiles, the
next tile taken in while the last one's rays thin out.

Each round every node all-reduces over the butterfly of ranks (the tree-reduce actor) three
vectors: the rays waiting per domain over its tiles in flight (summed), the lowest rank holding
each domain (MIN) and the rays waiting per tile in flight (summed). From the same totals every
node computes the same round (``schedule.dynamic.RayWeightedRounds``): which node traces each
wanted domain; rays swap so every scheduled domain's rays are on its node, which traces them.
A node knows how many rays it will receive without asking: every ray waiting for a domain the
plan gives it, less its own. No coordinator message, one all-reduction a round.

**Tiles in flight.** Each tile used to run its rounds to the end alone, and its last rounds,
a few rays each, cost a whole all-reduction (log2 P exchange steps) while the next tile
waited: at 2^20 paths on 1,024 virtual nodes the replay counted 235 rounds for 16 tiles, and
``dynamic``'s speed-up peaked at 256 nodes. Now, once the all-reduced rays waiting fall under
an eighth of a tile's paths and none waits for a domain no node holds (``takes_next_tile``),
and fewer than ``MAX_TILES`` tiles are in flight, every node takes in the next tile at the end
of that round: it makes the camera rays of its share (every P-th
path) and queues them where they were made (an image-plane start); they are counted in the
next all-reduction and move from then on. The decision is made from the all-reduced totals,
so every node makes it in the same round, and a tile's batches never reach a node that has
not taken it in (they are sent after the next all-reduction, which every node enters after
taking the tile in). Taken in before the round's swap, its rays moved uncounted: a receiver
stopped at the count it expected, and a tile retired with rays on the wire (a test's image
lost light). A tile retires into the film once none of its rays waits anywhere (its
all-reduced count is 0), in tile order, so the film adds tiles in the order one process does.

Memory: a node holds at most ``MAX_TILES`` tiles' path state, and the rays waiting stay under
about a tile and an eighth (the next tile comes in under an eighth of one).
"""

from __future__ import annotations

import time

import numpy as np

from vastray.actors import protocol
from vastray.actors.domain_loop import ListOrder, Queries, traced_tiles, waiting_rays
from vastray.render.film import Film
from vastray.render.integrators import launched_camera_rays
from vastray.scene.embree.launch import cpu_time
from vastray.schedule.dynamic import RayWeightedRounds, image_plane_start
from vastray.schedule.image import ImageSchedule
from vastray.schedule.ownership import interleaved_paths
from vastray.schedule.soa import SoA, join_bound

#: Tiles a node holds path state for at once: the one finishing and the next.
MAX_TILES = 2
#: The next tile comes in once fewer than a tile's paths over this many rays wait, over all
#: nodes (``takes_next_tile``).
TAKE_IN_BELOW = 8


def takes_next_tile(wanted: np.ndarray, holder: np.ndarray, size: int, tile: int) -> bool:
    """Whether a round takes the next tile in (where one is left and fewer than ``MAX_TILES``
    are in flight), from its all-reduced totals: (D,) ``wanted``, the rays waiting per domain,
    and (D,) ``holder``, the lowest rank holding each (``size``: none). Under
    1 / ``TAKE_IN_BELOW`` of a tile's rays waiting, and none for a domain no node holds.

    Why so few: a wanted domain no node holds gets a node only where some node has no wanted
    domain of its own or its kept rays leave room under the round's busiest
    (``RayWeightedRounds``'s rule 3), and a new tile's rays keep the nodes' domains wanted,
    so the old tile's rays for such domains can wait until the new tile drains (measured
    with the paper's rule 3, idle nodes only, before session 50).
    Taken in under a whole tile's rays, the replayed frame of ``bench/simulate.py --quick``
    (2^18 paths, 1,439 domains) took 2.63 -> 5.25 s on 64 nodes and 1.60 -> 2.08 s on 256
    (180 -> 347 and 86 -> 100 all-reductions) while 1,024 nodes gained (1.33 -> 1.12 s);
    under an eighth, no node count lost more than 0.6 % and 1,024 nodes gained 6 % (2^18)
    and 19 % (2^20). Rays waiting for an unheld domain as the tile would come in starve the
    same way (on 4 x 3 x 2 domains and 2 nodes, 96 all-reductions one tile at a time, 122 with
    the tile always taken in under a tile's rays, 88 with this check)."""
    if int(wanted.sum()) >= max(1, tile // TAKE_IN_BELOW):
        return False
    return not bool(wanted[holder >= size].any())


class DynamicFrame:
    """One frame of ray-weighted rounds on one node (see the module docstring).

    Parameters
    ----------
    node : this node's ``NodeWork`` (domain loop, ray post, held batches).
    setup, settings : what paths and policies are made from.
    owner : (D,) the static owner of each domain (the policies' default; rays start where
        they are made).
    rank, size : this node and the nodes.
    tile : paths per tile (the next one comes in under an eighth of it waiting, over all
        nodes: ``takes_next_tile``).
    film : this node's partial film, fed as tiles retire.
    on_tile : hears of the paths this node started, as each tile retires.
    base : label of the frame's first tile (labels are unique over the frames of a job).
    """

    def __init__(self, node, setup, settings, owner: np.ndarray, rank: int, size: int,
                 tile: int, film: Film, on_tile=None, base: int = 0):
        self.node, self.setup, self.settings = node, setup, settings
        self.owner, self.rank, self.size = owner, rank, size
        self.tile, self.film, self.on_tile, self.base = tile, film, on_tile, base
        self.n_domains = len(owner)
        self.n_tiles = -(-setup.total_paths // tile)
        #: tile index -> (its policy, (n,) bool: the paths this node started), in tile order
        self.live: dict[int, tuple[ImageSchedule, np.ndarray]] = {}
        self.next_tile = 0
        self.shade_s = 0.0
        #: rays of batches held back for a tile not yet taken in, delivered as it came in:
        #: the next receive expects them among its own
        self._delivered_early = 0

    def take_in(self) -> None:
        """Make the next tile's policy and queue the camera rays of this node's share."""
        index, self.next_tile = self.next_tile, self.next_tile + 1
        policy = self.setup.tile_schedule(self.settings, index * self.tile, self.tile,
                                          self.owner, self.rank)
        policy.owner = image_plane_start(self.n_domains, self.rank)
        mine = interleaved_paths(len(policy.ctx.pixel), self.rank, self.size)
        self.live[index] = (policy, mine)
        stats = self.node.stats
        stats["most_tiles_in_flight"] = max(stats.get("most_tiles_in_flight", 0), len(self.live))
        for message in self.node.early.pop(self.base + index, []):
            self._delivered_early += self._deliver(index, message)
        self.node.loop.start_tile(policy, launched_camera_rays(
            self.setup.camera, policy.ctx, policy.result, np.nonzero(mine)[0]))

    def _deliver(self, index: int, message) -> int:
        """Hand a batch to tile ``index``'s policy; the rays it brought (0 if dropped)."""
        policy = self.live[index][0]
        if self.node.deliver(policy, message) and message.arrays:
            return len(message.arrays["domain"])
        return 0

    def accept(self, message) -> int:
        """Deliver a batch of a tile in flight; hold back one of a tile not taken in yet (a
        later frame's). The rays it brought now."""
        index = message.meta.get("tile", -1) - self.base
        if index in self.live:
            return self._deliver(index, message)
        self.node.early.setdefault(message.meta.get("tile"), []).append(message)
        return 0

    async def receive(self, rays: int) -> None:
        """Deliver batches until ``rays`` rays (less those delivered early) have come."""
        rays, self._delivered_early = rays - self._delivered_early, 0
        while rays > 0:
            rays -= self.accept(await self.node.management.receive(protocol.RAYS, "ray batch"))

    def retire(self, waiting_per_tile: np.ndarray) -> None:
        """Fold the tiles in flight that no node has a ray of (``waiting_per_tile``: (T,)
        all-reduced, in tile order) into the film, from the first one on, in order."""
        for index, count in zip(list(self.live), waiting_per_tile, strict=True):
            if count:
                return
            policy, mine = self.live.pop(index)
            if policy.outbox:  # rays never sent: their paths would silently lose light
                raise RuntimeError(f"tile {index} ended with rays still to send")
            self.film.add_paths(policy.ctx.pixel, policy.ctx.sample, policy.result,
                                counted=mine)
            self.shade_s += policy.counters["shade_s"]
            if self.on_tile is not None:
                self.on_tile(int(np.count_nonzero(mine)))

    def trace(self, domain: int, bvh) -> Queries:
        """Trace the domain's rays of every tile in flight that has rays for it, in tile
        order."""
        return traced_tiles((policy for policy, _ in self.live.values()), domain, bvh)

    def rays(self, domain: int) -> int:
        return sum(waiting_rays(policy, domain) for policy, _ in self.live.values())

    def _outgoing(self, queues: dict, assign: dict[int, int]
                  ) -> list[tuple[tuple[int, str], tuple[np.ndarray, SoA]]]:
        """The rays a round's plan (``assign``: domain -> node) sends away, taken out of
        ``queues`` (queue name -> ``DomainQueues``): ((node, queue name), (domains (m,),
        rays (m,))) per destination and queue, in order."""
        outgoing: dict[tuple[int, str], list] = {}
        for domain, node in assign.items():
            if node == self.rank:
                continue
            for name, q in queues.items():
                rays = q.pop(domain)
                if rays is not None:
                    outgoing.setdefault((node, name), []).append(
                        (np.full(len(rays), domain), rays))
        return [(key, join_bound(parts)) for key, parts in sorted(outgoing.items())]

    async def run(self, tree) -> None:
        """The frame's rounds, until every tile has retired."""
        node, size, stats = self.node, self.size, self.node.stats
        schedule = RayWeightedRounds()
        self.take_in()
        while True:
            with node.loop.bookkeeping():
                per_tile = [policy.radiance.counts().astype(np.int64)
                            + policy.shadow.counts().astype(np.int64)
                            for policy, _ in self.live.values()]
                wanted = sum(per_tile, np.zeros(self.n_domains, np.int64))
                holder = np.full(self.n_domains, size, np.int64)
                holder[sorted(node.preloader.resident())] = self.rank
                tiles = np.array([w.sum() for w in per_tile], np.int64)
            start = time.perf_counter()
            totals = await tree.allreduce({"wanted": wanted, "holder": holder, "tiles": tiles},
                                          {"wanted": "sum", "holder": "min", "tiles": "sum"})
            stats["global_barriers"] = stats.get("global_barriers", 0) + 1
            self.retire(totals["tiles"])
            # the same decision on every node; the tile comes in after this round's swap, so
            # only rays counted in its all-reduction move in it
            take = (self.next_tile < self.n_tiles and len(self.live) < MAX_TILES
                    and takes_next_tile(totals["wanted"], totals["holder"], size, self.tile))
            cpu = cpu_time()
            plan = schedule.from_totals(totals["wanted"], totals["holder"], size)
            await node.loop.decided(cpu_time() - cpu)
            if plan.finished:  # no ray waits anywhere: every tile in flight has retired
                if not take:
                    return
                self.take_in()
                continue
            if len(self.live) > 1:
                stats["rounds_with_tiles_overlapping"] = (
                    stats.get("rounds_with_tiles_overlapping", 0) + 1)
            for index, (policy, _) in list(self.live.items()):
                with node.loop.bookkeeping():
                    outgoing = self._outgoing({"radiance": policy.radiance,
                                               "shadow": policy.shadow}, plan.assign)
                for (peer, name), (domains, rays) in outgoing:
                    await node.post.send(peer, name, {"tile": self.base + index}, domains, rays)
            mine = np.array([d for d, p in plan.assign.items() if p == self.rank], np.int64)
            await self.receive(int(totals["wanted"][mine].sum() - wanted[mine].sum()))
            stats["wait_s"] += time.perf_counter() - start
            stats["rounds"] += 1
            await node.loop.run(ListOrder(mine.tolist(), self.trace, rays=self.rays))
            if take:
                self.take_in()  # its camera rays wait here for the next round's counts
