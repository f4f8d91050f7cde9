"""A node's side of domain decomposition: the rays of its domains traced through the domain
loop, its outboxes shipped through the ray post, batches from its peers delivered to their
tile (or held for a later one), and the round protocol of ``domain`` (each round ends with an
all-reduction over the butterfly of ranks, not through the coordinator; ``dynamic``'s rounds
are ``actors.dynamic_frame``'s)."""

from __future__ import annotations

import time

import numpy as np

from vastray.actors import protocol
from vastray.actors.domain_loop import (
    DomainLoop,
    ScheduleOrder,
)
from vastray.actors.job_options import DEFAULT_MAX_BATCH_RAYS
from vastray.actors.preloader import DomainPreloader
from vastray.actors.ray_post import RayPost
from vastray.schedule.soa import SoA


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
        each destination's rays as soon as they fill a batch (``max_batch``) and the rest
        when no local ray is left.

        The outbox is sent first because rays reach it outside a trace too: ``policy.start``
        puts the tile's camera rays bound for other nodes' domains there. A node whose share
        of a tile enters no domain of its own traces nothing, and unless it shipped them here
        those rays would never leave: no batch counted, the tile would end without them.

        Why not a batch per activation, as the asynchronous frames send: a round's peers
        take their rays only after its all-reduction, so sending them earlier hides only
        their transfer, and it cost a batch per (activation, peer, queue): on rm 128³ at
        8 nodes, 8,331 batches of 14 rays on average in 15 rounds, each a send, a receive
        and a decode of its own (about 0.5 ms of a node's CPU a batch, measured).
        """
        await self.ship(policy)
        await self.loop.run(ScheduleOrder(policy, self.preloader, resident_aware=False),
                            ship=lambda: self.ship(policy, full_only=True))
        await self.ship(policy)

    async def ship(self, policy, tile: int | None = None, full_only: bool = False) -> None:
        """Send the outbox as ray batches (counted per destination in ``post.sent_to``),
        labelled with ``tile`` (default: the current tile); ``full_only``: only the
        destinations whose rays fill a batch."""
        with self.loop.bookkeeping():
            batches = self.post.batches(
                policy.take_outbox(self.post.max_batch if full_only else 0))
        await self.post.ship(batches, {"tile": self.tile if tile is None else tile})

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
        with self.loop.bookkeeping():
            arrays = dict(message.arrays)
            domains = np.array(arrays.pop("domain"))
            rays = SoA(**{k: np.array(v) for k, v in arrays.items()})
            policy.receive(message.meta["queue"], domains, rays)
        return True

    async def rounds(self, policy, tree) -> None:
        """Bulk-synchronous rounds until a round moves no ray between nodes. A round ends with
        one all-reduction over the butterfly of ranks (``tree``, the tree-reduce actor): the sum
        of every node's batches sent per destination, from which each node takes how many to
        expect; a round in which nothing moved ends the tile on every node at once. No
        coordinator message: log2(P) exchange steps, not 2P messages through one process.
        """
        size = tree.size
        while True:
            self.stats["rounds"] += 1
            await self.drain(policy)
            sent = np.zeros(size, np.int64)
            for node, batches in self.post.take_sent_to().items():
                sent[int(node)] = batches
            start = time.perf_counter()
            total = (await tree.allreduce({"sent": sent}, {"sent": "sum"}))["sent"]
            self.stats["global_barriers"] = self.stats.get("global_barriers", 0) + 1
            if not total.any():
                return
            for _ in range(int(total[self.rank])):
                await self.receive_batch(policy)
            self.stats["wait_s"] += time.perf_counter() - start
