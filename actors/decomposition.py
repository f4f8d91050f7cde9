"""Domain decomposition across nodes: each node owns some domains and traces only the rays
waiting for them; rays bound for another node's domain travel there as ray batches.

Two schedulers share this runtime (Navrátil's static domain schedule and the Galaxy-style
asynchronous baseline of the temporal-coherence paper):

- ``domain``: bulk-synchronous rounds. Every node drains its queues, sends what it produced,
  and tells the coordinator how many batches it sent to whom; the coordinator answers each
  node with how many batches to expect before the next round; a round in which nobody sent
  anything ends the tile.
- ``async``: no global rounds and no barrier inside a frame (Galaxy). Each node injects the
  camera rays of its share of the next tile whenever fewer than ``tile`` rays wait in its
  queues (credit-based flow control), traces the fullest local domain, ships what it
  produced, and takes whatever arrives, for any tile at once. A tile's path state is made on
  demand and retired into the film once none of its rays waits here (partial path radiance
  adds up in the float64 film). Only when a node has injected all its tiles and is idle does
  it report (batches sent, batches received); the coordinator declares the frame done when
  every node is idle, the sums match, and a second probe wave returns the very same counts
  (Mattern's four-counter termination): one termination detection per frame.

- ``dynamic``: Navrátil's ray-weighted rounds (Figs. 5-6). Each round every node reports which
  domains it holds rays for and which domain it has loaded; the coordinator keeps loaded
  domains where they are wanted and hands the most-wanted unloaded domains to nodes whose
  domain is no longer needed; rays for a scheduled domain then move to its node, which traces
  them. Rays start where their camera rays were made (an image-plane start).

Within a node the rays follow the ``image`` schedule (``schedule.image``), so every ray visits
the same domains in the same order as on one node: the image is the reference image.
"""

from __future__ import annotations

import asyncio
import time
import zlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from vastray.actors import protocol
from vastray.actors.domain_loop import DomainLoop, ListOrder, ScheduleOrder, traced_queries
from vastray.actors.job_options import DEFAULT_MAX_BATCH_RAYS, JobOptions
from vastray.actors.local import RenderSetup
from vastray.actors.preloader import DomainPreloader
from vastray.actors.ray_post import RayPost, traffic_counters
from vastray.render.driver import path_context
from vastray.render.film import Film
from vastray.render.integrators import camera_rays
from vastray.scene.bvh import query_pool
from vastray.schedule.galaxy import GalaxyPolicy
from vastray.schedule.image import ImageSchedule
from vastray.schedule.ownership import interleaved_paths, round_robin_owners
from vastray.schedule.soa import SoA
from vastray.transport.codec import encode

if TYPE_CHECKING:  # loaded only by the schedulers that use them
    from vastray.scene.bvh import DomainBVH
    from vastray.schedule.portals import Portals
    from vastray.schedule.temporal import FrameStats

MODES = ("domain", "async", "dynamic", "temporal")


@dataclass
class NodeState:
    """What a node keeps from one frame of an animation to the next: its domain preloader (the
    domains it holds stay resident), its query threads, ray batches that arrived for a later
    frame, and the frame's position in the job (``ordinal``), which labels its tiles."""

    preloader: DomainPreloader | None = None
    pool: object = None
    ordinal: int = 0
    #: the first tile label of the next frame or pass (its tiles take the labels after).
    tile_base: int = 0
    #: the animation frame being rendered (0 for a single image): recording frames of
    #: portals are those divisible by the portal interval.
    frame: int = 0
    #: tile label -> ray batches received for a tile this node has not reached yet.
    early: dict = field(default_factory=dict)
    #: the temporal scheduler's statistics of the last frame, summed over the nodes.
    temporal_stats: FrameStats | None = None
    #: the simplified model, loaded once and never evicted.
    simplified_bvh: DomainBVH | None = None
    #: the virtual portals recorded in the last recording frame.
    portals: Portals | None = None

    def preloader_for(self, store, capacity: int, keep, options: JobOptions, rank: int
                      ) -> DomainPreloader:
        """The node's preloader, made on the first frame (its threads, preloading switch and
        emulated storage bandwidth from ``options``, the bandwidth of ``rank``)."""
        if self.preloader is None:
            self.pool = query_pool(options.threads)
            self.preloader = DomainPreloader(
                store, capacity, keep, pool=self.pool,
                load_bandwidth=options.load_bytes_per_second(rank), preload=options.preload)
        return self.preloader

    def threads(self) -> int:
        return self.pool._max_workers if self.pool is not None else 1

    def close(self) -> None:
        if self.preloader is not None:
            self.preloader.close()
        if self.pool is not None:
            self.pool.shutdown()


def simplified_routing(store, setup, options: JobOptions, state: NodeState):
    """This frame's routing to the simplified model (``options.simplified``: a policy of
    ``schedule.simplified``), or None. The model is loaded once per node and never evicted;
    the portals recorded in the last recording frame are kept in ``state.portals``.

    ``options.portal_accuracy`` (portal policy) makes the run an instrumented one, for ACC:
    every frame is traced as a recording frame with a crossing log, and the crossings are
    classified with the portals a timed run would predict the frame with; only the frames a
    timed run records replace those portals (``finish_simplified``)."""
    policy = options.simplified
    if policy is None:
        return None
    from vastray.scene.bvh import DomainBVH
    from vastray.schedule.portals import CrossingLog, Portals, records_portals
    from vastray.schedule.simplified import SimplifiedRouting

    if state.simplified_bvh is None and policy != "none":
        state.simplified_bvh = DomainBVH(len(store.domains), store.load_simplified(), setup.keep,
                                         state.pool)
    lo, hi = store.domain_boxes()
    interval = options.portal_interval
    recording = policy == "portal" and records_portals(state.frame, interval,
                                                       state.portals is not None)
    measuring = policy == "portal" and options.portal_accuracy
    portals = None
    if policy == "portal":
        portals = (Portals(len(store.domains), options.portal_resolution)
                   if recording or measuring else state.portals)
    routing = SimplifiedRouting(state.simplified_bvh, len(store.domains), policy, lo,
                                hi, portals=portals, recording=recording or measuring,
                                threshold=float(options.portal_threshold))
    if measuring:
        routing.log = CrossingLog(setup.total_paths)
        routing.reference = state.portals
        routing.keeps_portals = recording
    return routing


async def finish_simplified(routing, tree, state: NodeState, stats: dict, rank: int = 0
                            ) -> None:
    """After a frame: merge a recording frame's portals over the nodes (MAX, by the
    tree-reduce actor) for the frames that follow, and report the routing's counters.

    An instrumented frame (``routing.log``) merges its crossing log in the same all-reduce,
    and node 0 reports, for every node (the counts are global), the crossings classified
    with the portals a timed run would predict the frame with (``acc_*``, on the frames a
    timed run predicts, not on its recording frames) and with the portals recorded in this
    very frame (``replay_*``: no false lows, since cells keep maxima)."""
    if routing is None:
        return
    stats.update(routing.counters)
    stats["portal_recording"] = int(routing.recording and routing.keeps_portals)
    if routing.portals is not None:
        stats["portal_resolution"] = routing.portals.resolution
    if routing.recording:
        from vastray.schedule.portals import CrossingLog, Portals, prediction_accuracy

        arrays, ops = routing.portals.to_arrays(), dict(Portals.REDUCE)
        if routing.log is not None:
            arrays.update(routing.log.to_arrays())
            ops.update(CrossingLog.REDUCE)
        merged = await tree.allreduce(arrays, ops) if tree is not None else arrays
        recorded = Portals.from_arrays(merged)
        if routing.keeps_portals:
            state.portals = recorded
        if routing.log is not None and rank == 0:
            cells, actual = CrossingLog.from_arrays(merged).crossings()
            stats.update(prediction_accuracy(recorded.predict(cells), actual,
                                             routing.threshold).counters("replay_"))
            if routing.reference is not None and not routing.keeps_portals:
                stats.update(prediction_accuracy(routing.reference.predict(cells), actual,
                                                 routing.threshold).counters("acc_"))


async def render_owned_domains(management, options: JobOptions, rank: int, size: int, store,
                               config, settings, on_tile=None, state: NodeState | None = None,
                               tree=None) -> tuple[Film, dict]:
    """Render this node's part of every tile under domain decomposition; returns the node's
    partial film (to be summed over nodes) and its counters. ``on_tile(paths)`` hears of the
    paths this node started, after each tile. ``state`` carries the preloader and held
    messages from one frame to the next (default: a fresh one, closed at the end)."""
    mode = options.scheduler
    own_state = state is None
    state = NodeState() if state is None else state
    setup = RenderSetup.of(store, config, settings)
    owner = round_robin_owners(len(store.domains), size)
    owned = int(np.count_nonzero(owner == rank))
    if mode == "temporal":  # groups change from frame to frame: room for the largest
        owned = -(-len(store.domains) // size) + 1
    preloader = state.preloader_for(store, options.cache or max(owned, 1), setup.keep, options,
                                    rank)
    before = preloader.stats()
    film = Film(settings.width, settings.height)
    total = setup.total_paths
    tile = max(1, min(options.max_samples_in_flight or total, total))
    n_tiles = -(-total // tile)
    stats = {**traffic_counters(), "shade_s": 0.0, "trace_s": 0.0, "wait_s": 0.0, "rounds": 0}
    node = _Node(management, rank, stats, preloader, options.max_batch_rays, early=state.early)
    base = state.tile_base  # tile labels are unique over the frames and passes of a job
    state.tile_base += n_tiles
    routing = simplified_routing(store, setup, options, state)
    try:
        if mode == "async":
            frame = _AsyncFrame(node, setup, settings, owner, rank, size, tile, film, on_tile,
                                base=base, status_label=state.ordinal, simple=routing,
                                resident_first=options.resident_first)
            await frame.run()
        elif mode == "temporal":
            frame = await _temporal_frame(node, setup, settings, store, options, rank, size, tile,
                                          film, on_tile, base, state, preloader, tree, stats,
                                          routing)
        if mode in ("async", "temporal"):
            stats["shade_s"] += frame.shade_s
            stats["tiles_made"] = frame.made
            await finish_simplified(routing, tree, state, stats, rank)
        for index, first in enumerate(range(0, total, tile) if mode in ("domain", "dynamic")
                                      else ()):
            ctx = path_context(setup.shading, settings, first, min(first + tile, total),
                               setup.ao_distance)
            policy = ImageSchedule(ctx, setup.geometry, setup.color_source, setup.scalar_range,
                                   owner=owner, rank=rank)
            mine = interleaved_paths(len(ctx.pixel), rank, size)
            if mode == "dynamic":  # rays stay where they are made until a round moves them
                policy.owner = np.full(len(store.domains), rank)
            node.begin_tile(base + index, policy)
            policy.start(camera_rays(setup.camera, ctx).take(np.nonzero(mine)[0]))
            if mode == "domain":
                await node.rounds(policy, base + index)
            else:
                await node.dynamic(policy, base + index)
            if policy.outbox:  # rays never sent: their paths would silently lose light
                raise RuntimeError(f"tile {index} ended with rays still to send")
            film.add_paths(ctx.pixel, ctx.sample, policy.result, counted=mine)
            stats["shade_s"] += policy.counters["shade_s"]
            if on_tile is not None:
                on_tile(int(np.count_nonzero(mine)))
    finally:
        if own_state:
            state.close()
    stats["threads"] = state.threads()
    stats.update(frame_load_stats(before, preloader.stats()))
    stats["load_bandwidth_mb_s"] = preloader.load_bandwidth_mb_s()
    stats["cache_capacity"] = preloader.capacity
    stats["peak_resident_domains"] = preloader.stats()["peak_resident_domains"]
    return film, stats


async def _temporal_frame(node, setup, settings, store, options: JobOptions, rank, size, tile,
                          film, on_tile, base, state: NodeState, preloader, tree, stats: dict,
                          routing=None):
    """One frame of ``temporal``: plan from the last frame's statistics, render, and sum this
    frame's statistics over the nodes for the next (kept in ``state.memory``)."""
    from vastray.actors.temporal import TemporalFrame, frame_assignment, summed_stats

    previous = state.temporal_stats
    stats["assignment"] = options.assignment or "temporal"  # the effective ones, reported
    stats["priority"] = options.priority or "cost-rate"
    assignment = frame_assignment(stats["assignment"], store, setup.camera,
                                  settings.width, settings.height, size, previous)
    frame = TemporalFrame(node, setup, settings, assignment, rank, size, tile, film, store,
                          stats["priority"], previous, on_tile, base=base,
                          status_label=state.ordinal, simple=routing)
    await frame.run()
    start = time.perf_counter()
    summed = state.temporal_stats = await summed_stats(tree, frame.stats)
    # The same on every node and for any node count, cache or priority (a lossless frame's
    # ray statistics depend on the scene, camera and seed only): the tests compare these.
    stats["ray_stats_digest"] = zlib.crc32(np.ascontiguousarray(summed.sent).tobytes()
                                           + np.ascontiguousarray(summed.received).tobytes())
    stats["ray_transmissions"] = int(summed.sent.sum())
    stats["stats_reduce_s"] = round(time.perf_counter() - start, 4)
    stats["local_domains"] = int(frame.local.sum())
    stats["nonlocal_loads"] = frame.nonlocal_loads
    stats["proc_s"] = round(float(frame.stats.proc_s.sum()), 4)  # this node's, for S_PROC
    stats["assignment_digest"] = int(np.abs(assignment.owner * np.arange(
        1, len(assignment.owner) + 1)).sum())
    return frame


#: Load counters a frame reports: what the preloader did during the frame.
_LOAD_COUNTERS = ("loads", "preloads", "load_s", "load_wait_s", "bytes_loaded", "load_throttle_s")


def frame_load_stats(before: dict, after: dict) -> dict:
    """The preloader's counters over one frame (its totals run over the whole job)."""
    return {k: (round(after[k] - before[k], 4) if isinstance(after[k], float)
                else after[k] - before[k]) for k in _LOAD_COUNTERS}


class _Node:
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
        while True:
            waiting = policy.radiance.counts() + policy.shadow.counts()
            await self.management.to_coordinator(encode(protocol.QUEUES, {}, {
                "rank": self.rank, "tile": tile, "loaded": sorted(self.preloader.resident()),
                "queues": {str(d): int(n) for d, n in enumerate(waiting) if n}}))
            start = time.perf_counter()
            plan = await self.management.receive(protocol.SCHEDULE, "this round's schedule")
            if plan.meta["finished"]:
                return
            assign = {int(d): int(p) for d, p in plan.meta["assign"].items()}
            # Every node sends every other node exactly one radiance and one shadow batch
            # (possibly empty), so each knows what to wait for without another barrier.
            for node in range(plan.meta["size"]):
                if node == self.rank:
                    continue
                for name, queues in (("radiance", policy.radiance), ("shadow", policy.shadow)):
                    parts = [(d, queues.pop(d)) for d, p in assign.items() if p == node]
                    parts = [(np.full(len(r), d), r) for d, r in parts if r is not None]
                    await self.post.send(node, name, {"tile": self.tile},
                                         *_joined(parts))
            for _ in range(2 * (plan.meta["size"] - 1)):
                await self.receive_batch(policy)
            self.stats["wait_s"] += time.perf_counter() - start
            self.stats["rounds"] += 1
            mine = [d for d, p in assign.items() if p == self.rank]
            await self.loop.run(ListOrder(mine, lambda d, bvh: traced_queries(policy, d, bvh)))

    async def _status(self, tile: int, probe: int | None) -> None:
        await self.management.to_coordinator(encode(protocol.STATUS, {}, {
            "rank": self.rank, "tile": tile, "probe": probe,
            "sent": self.stats["batches_sent"], "received": self.stats["batches_received"]}))


def _joined(parts: list[tuple[np.ndarray, SoA]]) -> tuple[np.ndarray, SoA] | tuple[()]:
    """(domains, rays) of ``parts`` joined, or () for none (an empty batch)."""
    if not parts:
        return ()
    return np.concatenate([d for d, _ in parts]), SoA.concat([r for _, r in parts])


class _AsyncFrame:
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

    def __init__(self, node: _Node, setup, settings, owner: np.ndarray, rank: int, size: int,
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
            first = tile * self.tile
            ctx = path_context(self.setup.shading, self.settings, first,
                               min(first + self.tile, self.setup.total_paths),
                               self.setup.ao_distance)
            self.policies[tile] = ImageSchedule(ctx, self.setup.geometry,
                                                self.setup.color_source,
                                                self.setup.scalar_range, owner=self.owner,
                                                rank=self.rank, simple=self.simple)
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
        policy.start(camera_rays(self.setup.camera, policy.ctx).take(mine))
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

    def trace(self, domain: int, bvh) -> int:
        """Trace the domain's rays of every tile that has rays for it."""
        return sum(traced_queries(policy, domain, bvh) for policy in self.policies.values()
                   if policy.radiance.count(domain) or policy.shadow.count(domain))

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
        management = self.node.management
        inbox = management.mailbox(protocol.RAYS)
        control = management.mailbox(protocol.PROBE)
        self.take_early()
        while True:
            while not inbox.empty():
                self.accept(inbox.get_nowait())
            if self.next_tile < self.n_tiles and self.galaxy.admits_tile(self.waiting()):
                self.inject()
                await self.ship()  # camera rays bound for other nodes leave at once
            if await self.step() or not inbox.empty():
                continue
            self.retire_idle()
            if self.next_tile < self.n_tiles:
                continue
            await self.node._status(self.status_label, probe=None)
            start = time.perf_counter()
            getters = {asyncio.ensure_future(inbox.get()): "rays",
                       asyncio.ensure_future(control.get()): "control"}
            done, pending = await asyncio.wait(getters, timeout=management.timeout,
                                               return_when=asyncio.FIRST_COMPLETED)
            for task in pending:
                task.cancel()
            self.node.stats["wait_s"] += time.perf_counter() - start
            if not done:
                raise TimeoutError("no ray batch or control message while idle")
            finished = False
            for task in sorted(done, key=lambda t: getters[t] != "rays"):
                message = task.result()
                if getters[task] == "rays":
                    self.accept(message)
                elif message.meta.get("finished"):
                    finished = True
                else:
                    await self.node._status(self.status_label, probe=message.meta["probe"])
            if finished:
                if self.policies:
                    raise RuntimeError("the frame ended with rays still waiting here")
                return
