"""``async`` on one node: the whole frame without a barrier (Galaxy, as the temporal-coherence
paper's baseline runs it). The node injects the camera rays of its share of the next tile
whenever its credit allows (``schedule.galaxy``), activates the domain Galaxy's policy
chooses through the domain loop, ships what that produced, takes whatever arrives, for any
tile at once, and retires a tile into the film once none of its rays waits here. The frame
ends by the termination detection over the tree of ranks (``actors.tree_termination``), in
which a node takes part once it has injected every tile and is idle.
The temporal frame (``actors/temporal.py``) is this frame with the temporal paper's choices.
"""

from __future__ import annotations

import asyncio
import time

import numpy as np

from vastray.actors import protocol
from vastray.actors.domain_loop import Queries, traced_tiles
from vastray.actors.node_work import NodeWork
from vastray.actors.tree_termination import TreeTermination
from vastray.render.film import Film
from vastray.render.integrators import launched_camera_rays
from vastray.schedule.galaxy import GalaxyPolicy
from vastray.schedule.image import ImageSchedule
from vastray.schedule.ownership import interleaved_paths
from vastray.transport.codec import encode


class AsyncFrame:
    """``async`` on one node: the whole frame without a barrier (see the module docstring).

    Parameters
    ----------
    node : the node's sender/receiver and counters.
    setup, settings : what paths and policies are made from.
    owner : (D,) owning rank of each domain.
    tile : paths per tile; also the credit, the most rays waiting here before the next
        tile's camera rays are injected.
    film : this node's partial film, fed as tiles retire.
    on_tile : hears of the paths this node injects.
    base : label of the frame's first tile (labels are unique over the frames of a job; a
        batch labelled outside this frame's is held for its frame).
    status_label : this frame's number in the termination detection.
    simple : routing to the node's simplified model (``simplified_routing``), or None.
    resident_first : trace a cached domain with waiting rays before loading another, the
        fullest first (as the out-of-core schedules' ``resident_first``); False is Galaxy's
        order, the fullest queue whatever it costs to load.
    """

    def __init__(self, node: NodeWork, setup, settings, owner: np.ndarray, rank: int, size: int,
                 tile: int, film: Film, on_tile=None, base: int = 0, status_label: int = 0,
                 simple=None, resident_first: bool = True):
        self.node, self.setup, self.settings = node, setup, settings
        self.galaxy = GalaxyPolicy(tile, resident_first)
        self.preloader = node.preloader
        self.simple = simple
        self.owner, self.rank, self.size = owner, rank, size
        self.tile, self.film, self.on_tile = tile, film, on_tile
        self.base, self.status_label = base, status_label
        self.n_tiles = -(-setup.total_paths // tile)
        self.policies: dict[int, ImageSchedule] = {}
        self.next_tile = 0
        self.shade_s = 0.0
        self.made = 0  # policies made (a tile's may be made again when late rays arrive)
        # What the last ``next_domain`` chose: the domain to load meanwhile, and the rays
        # waiting for the active one.
        self._upcoming: int | None = None
        self._rays = 0

    def policy(self, tile: int) -> ImageSchedule:
        """The tile's policy, made on demand (rays carry their state; the policy only the
        tile's path keys and the partial radiance gathered here)."""
        if tile not in self.policies:
            self.policies[tile] = self.setup.tile_schedule(
                self.settings, tile * self.tile, self.tile, self.owner, self.rank, self.simple)
            self.made += 1
        return self.policies[tile]

    def my_paths(self, policy) -> np.ndarray:
        """Rows of the tile's paths whose camera rays this node makes: every P-th."""
        return np.nonzero(interleaved_paths(len(policy.ctx.pixel), self.rank, self.size))[0]

    def traced(self, domain: int, rays: int, seconds: float) -> None:
        """Hears that an activation of ``domain`` processed ``rays`` rays in ``seconds``: the
        wait for its load (what preloading did not hide) and the tracing and shading."""

    def waiting(self) -> np.ndarray:
        """(D,) rays waiting here per domain, over every tile."""
        total = np.zeros(len(self.owner), np.int64)
        for policy in self.policies.values():
            total += policy.radiance.counts() + policy.shadow.counts()
        return total

    def inject(self) -> None:
        """Queue the camera rays of this node's share of the next tile."""
        tile = self.next_tile
        self.next_tile += 1
        policy = self.policy(tile)
        mine = self.my_paths(policy)
        self.film.count_samples(policy.ctx.pixel[mine])
        self.node.loop.start_tile(policy, launched_camera_rays(self.setup.camera, policy.ctx,
                                                                policy.result, mine))
        if self.on_tile is not None:
            self.on_tile(len(mine))

    def accept(self, message) -> bool:
        """Deliver a batch of this frame (True), or hold one of a later frame (False)."""
        tile = int(message.meta["tile"]) - self.base
        if 0 <= tile < self.n_tiles:
            return self.node.deliver(self.policy(tile), message)
        # a later frame's batch, from a node that went on first
        self.node.early.setdefault(int(message.meta["tile"]), []).append(message)
        return False

    def take_early(self) -> None:
        """Deliver the batches of this frame that arrived during an earlier one."""
        for label in [t for t in self.node.early if 0 <= t - self.base < self.n_tiles]:
            for message in self.node.early.pop(label):
                self.accept(message)

    def choose(self, waiting: np.ndarray) -> tuple[int, int | None]:
        """The domain to trace now and the one to load meanwhile (``GalaxyPolicy.choose``)."""
        return self.galaxy.choose(waiting, self.preloader.resident())

    # -- the domain loop's order (``domain_loop.DomainOrder``) -------------------------------
    def next_domain(self) -> int | None:
        waiting = self.waiting()
        if not waiting.any():
            return None
        domain, self._upcoming = self.choose(waiting)
        self._rays = int(waiting[domain])
        return domain

    def likely_next(self, current: int) -> int | None:
        return self._upcoming

    def rays(self, domain: int) -> int | None:
        """The rays waiting for ``domain`` when ``next_domain`` chose it, over every tile; None
        (every trace on the worker thread) with peers: without rounds a peer waits for the
        batches this node's loop routes, and a trace on the loop's thread holds them back
        (2 nodes on rm 128³: 2.6-2.8 s with every trace handed off, 4.0 s with the small ones
        on the loop)."""
        return self._rays if self.size == 1 else None

    def trace(self, domain: int, bvh) -> Queries:
        """Trace the domain's rays of every tile that has rays for it."""
        return traced_tiles(self.policies.values(), domain, bvh)

    async def step(self) -> bool:
        """Trace the chosen local domain for every tile that has rays for it, then ship;
        False when no ray waits here."""
        activation = await self.node.loop.step(self, ship=self.ship)
        if activation is None:
            return False
        # S_PROC's time: the wait for the load (what preloading did not hide) and the trace.
        self.traced(activation.domain, self._rays, activation.wait_s + activation.trace_s)
        return True

    async def ship(self) -> None:
        for tile, policy in list(self.policies.items()):
            if policy.outbox:
                await self.node.ship(policy, self.base + tile)

    def retire_idle(self) -> None:
        """Fold every tile with nothing waiting here into the film and drop its state."""
        for tile in [t for t, p in self.policies.items()
                     if not p.outbox and not (p.radiance.counts().any()
                                              or p.shadow.counts().any())]:
            policy = self.policies.pop(tile)
            self.film.add_partial(policy.ctx.pixel, policy.ctx.sample, policy.result)
            self.shade_s += policy.counters["shade_s"]

    async def run(self) -> None:
        """Render the frame until the tree's termination detection ends it
        (``actors.tree_termination``: no message to the coordinator)."""
        management = self.node.management
        inbox = management.mailbox(protocol.RAYS)
        boxes = {protocol.WAVE: management.mailbox(protocol.WAVE),
                 protocol.WAVE_REPLY: management.mailbox(protocol.WAVE_REPLY)}
        ending = TreeTermination(self.rank, self.size, self.status_label)
        self.take_early()
        while True:
            while not inbox.empty():
                self.accept(inbox.get_nowait())
            for box in boxes.values():  # waves pass on down the tree even while busy
                while not box.empty() and not ending.finished:
                    await self._hear(ending, box.get_nowait())
            if ending.finished:
                break
            if self.next_tile < self.n_tiles and self.galaxy.admits_tile(self.waiting()):
                self.inject()
                await self.ship()  # camera rays bound for other nodes leave at once
            if await self.step() or not inbox.empty():
                continue
            self.retire_idle()
            if self.next_tile < self.n_tiles:
                continue
            await self._send(ending.passive(self.node.stats["batches_sent"],
                                            self.node.stats["batches_received"]))
            if ending.finished:
                break
            await self._wait(inbox, boxes, ending)
        if self.policies or self.next_tile < self.n_tiles:
            raise RuntimeError("the frame ended with rays still waiting here")
        self.node.stats["termination_waves"] = ending.waves
        # the frame's end is the one point where every node waits for all the others
        self.node.stats["global_barriers"] = self.node.stats.get("global_barriers", 0) + 1

    async def _wait(self, inbox, boxes: dict, ending: TreeTermination) -> None:
        """Wait, passive, for a ray batch or a termination message, and take it."""
        management = self.node.management
        start = time.perf_counter()
        getters = {asyncio.ensure_future(box.get()): kind
                   for kind, box in [(protocol.RAYS, inbox), *boxes.items()]}
        try:
            done = await management.wait_any(list(getters), "ray batch or termination message")
        finally:
            for task in getters:
                if not task.done():
                    task.cancel()
        self.node.stats["wait_s"] += time.perf_counter() - start
        for task in sorted(done, key=lambda t: getters[t] != protocol.RAYS):
            if getters[task] == protocol.RAYS:
                self.accept(task.result())
            else:
                await self._hear(ending, task.result())

    async def _hear(self, ending: TreeTermination, message) -> None:
        """Take a wave (from the parent) or a reply (from a child) of this frame's detection;
        one of another frame's is dropped and counted."""
        if int(message.meta["label"]) != self.status_label:
            self.node.management.rejections.add(
                "stale", f"{message.kind} of frame {message.meta['label']} in frame "
                         f"{self.status_label}")
        elif message.kind == protocol.WAVE:
            await self._send(ending.on_wave(message.meta))
        else:
            ending.on_reply(message.meta)

    async def _send(self, sends: list) -> None:
        for rank, kind, meta in sends:
            await self.node.management.to_peer(rank, encode(kind, {}, meta))
