"""A node's side of domain decomposition: the rays of its domains traced through the domain
loop, its outboxes shipped through the ray post, batches from its peers delivered to their
tile (or held for a later one), and the round protocols of ``domain`` and ``dynamic``."""

from __future__ import annotations

import time

import numpy as np

from vastray.actors import protocol
from vastray.actors.domain_loop import DomainLoop, ListOrder, ScheduleOrder, traced_queries
from vastray.actors.job_options import DEFAULT_MAX_BATCH_RAYS
from vastray.actors.preloader import DomainPreloader
from vastray.actors.ray_post import RayPost
from vastray.schedule.soa import SoA, join_bound
from vastray.transport.codec import encode


class NodeWork:
    """The node side of the decomposition: trace local work (through the domain loop), ship
    outboxes (through the ray post), take deliveries."""

    def __init__(self, management, rank: int, stats: dict, preloader: DomainPreloader,
                 max_batch: int = DEFAULT_MAX_BATCH_RAYS, early: dict | None = None):
        self.management, self.rank, self.stats = management, rank, stats
        self.post = RayPost(management, rank, stats, max_batch)
        self.loop = DomainLoop(preloader, stats)
        self.tile = 0
        # Batches of a later tile (or frame), from nodes that finished this one first: held
        # back (and not counted) until this node starts that tile.
        self.early: dict[int, list] = {} if early is None else early

    @property
    def preloader(self) -> DomainPreloader:
        return self.loop.preloader

    def begin_tile(self, tile: int, policy) -> None:
        self.tile = tile
        for message in self.early.pop(tile, []):
            self.deliver(policy, message)

    def accept(self, policy, message) -> bool:
        """Deliver a batch of the current tile (True); hold back one of a later tile, or drop
        one that does not fit its tile (False)."""
        if message.meta.get("tile") == self.tile:
            return self.deliver(policy, message)
        self.early.setdefault(message.meta.get("tile"), []).append(message)
        return False

    async def receive_batch(self, policy) -> None:
        """Wait for the next batch of the current tile and deliver it."""
        while not self.accept(policy, await self.management.receive(protocol.RAYS,
                                                                    "ray batch")):
            pass

    async def drain(self, policy) -> None:
        """Send the outbox, then trace every local domain until no local ray waits, sending
        what each produced.

        The outbox is sent first because rays reach it outside a trace too: ``policy.start``
        puts the tile's camera rays bound for other nodes' domains there. A node whose share
        of a tile enters no domain of its own traces nothing, and unless it shipped them here
        those rays would never leave: no batch counted, the tile would end without them.
        """
        await self.ship(policy)
        await self.loop.run(ScheduleOrder(policy, self.preloader, resident_aware=False),
                            ship=lambda: self.ship(policy))

    async def ship(self, policy, tile: int | None = None) -> None:
        """Send the outbox as ray batches (counted per destination in ``post.sent_to``),
        labelled with ``tile`` (default: the current tile). The outbox is shipped after
        every domain traced, which bounds a ray's wait too."""
        await self.post.ship(policy.take_outbox(), {"tile": self.tile if tile is None else tile})

    def deliver(self, policy, message) -> bool:
        """Hand a batch to the tile's policy (True), or drop and count one whose path indices
        are not paths of the tile (False)."""
        try:
            protocol.check_ray_index(message, "path", len(policy.ctx.pixel))
        except protocol.ProtocolError as exc:
            self.management.rejections.add("malformed", str(exc))
            return False
        self.post.received(message)
        if not message.arrays:
            return True
        arrays = dict(message.arrays)
        domains = np.array(arrays.pop("domain"))
        rays = SoA(**{k: np.array(v) for k, v in arrays.items()})
        policy.receive(message.meta["queue"], domains, rays)
        return True

    async def rounds(self, policy, tile: int) -> None:
        """Bulk-synchronous rounds until a round moves no ray between nodes."""
        while True:
            self.stats["rounds"] += 1
            await self.drain(policy)
            sent = self.post.take_sent_to()
            await self.management.to_coordinator(encode(protocol.ROUND, {}, {
                "rank": self.rank, "tile": tile, "sent_to": {str(k): v for k, v in sent.items()}}))
            start = time.perf_counter()
            go = await self.management.receive(protocol.GO, "go-ahead for the next round")
            if go.meta["finished"]:
                return
            for _ in range(go.meta["expect"]):
                await self.receive_batch(policy)
            self.stats["wait_s"] += time.perf_counter() - start

    async def dynamic(self, policy, tile: int) -> None:
        """Ray-weighted rounds: report queues and resident domains, get this round's
        domains, swap rays, trace."""
        queues = {"radiance": policy.radiance, "shadow": policy.shadow}
        while True:
            await self.management.to_coordinator(encode(protocol.QUEUES, {}, {
                "rank": self.rank, "tile": tile, "loaded": sorted(self.preloader.resident()),
                **{name: {str(d): int(n) for d, n in enumerate(q.counts()) if n}
                   for name, q in queues.items()}}))
            start = time.perf_counter()
            plan = await self.management.receive(protocol.SCHEDULE, "this round's schedule")
            if plan.meta["finished"]:
                return
            assign = {int(d): int(p) for d, p in plan.meta["assign"].items()}
            # A batch goes only where rays go; the coordinator, which saw every node's
            # queues, says how many batches to expect. (One batch per peer and queue, empty
            # or not, made P^2 messages a round: 2 million at 1,024 nodes.)
            outgoing: dict[tuple[int, str], list] = {}
            for domain, node in assign.items():
                if node == self.rank:
                    continue
                for name, q in queues.items():
                    rays = q.pop(domain)
                    if rays is not None:
                        outgoing.setdefault((node, name), []).append(
                            (np.full(len(rays), domain), rays))
            for (node, name), parts in sorted(outgoing.items()):
                await self.post.send(node, name, {"tile": self.tile}, *join_bound(parts))
            for _ in range(plan.meta["expect"]):
                await self.receive_batch(policy)
            self.stats["wait_s"] += time.perf_counter() - start
            self.stats["rounds"] += 1
            mine = [d for d, p in assign.items() if p == self.rank]
            await self.loop.run(ListOrder(mine, lambda d, bvh: traced_queries(policy, d, bvh)))
