"""Domain decomposition across nodes: each node owns some domains and traces only the rays
waiting for them; rays bound for another node's domain travel there as ray batches.

Two schedulers share this runtime (Navrátil's static domain schedule and the Galaxy-style
asynchronous baseline of the temporal-coherence paper):

- ``domain``: bulk-synchronous rounds. Every node drains its queues, sends what it produced,
  and all-reduces over the butterfly of ranks how many batches it sent to whom; each node then
  waits for the batches sent to it; a round in which nobody sent anything ends the tile.
- ``async``: no global rounds and no barrier inside a frame (Galaxy). Each node injects the
  camera rays of its share of the next tile whenever fewer than ``tile`` rays wait in its
  queues (credit-based flow control), traces the fullest local domain, ships what it
  produced, and takes whatever arrives, for any tile at once. A tile's path state is made on
  demand and retired into the film once none of its rays waits here (partial path radiance
  adds up in the float64 film). The frame ends by Mattern's four-counter termination
  detection over the tree of ranks (``actors.tree_termination``): waves go down the tree and
  the batches sent and received come back up, summed, from nodes that have injected all
  their tiles and are idle; two waves with the same balanced sums end the frame. One
  detection per frame, none of it through the coordinator.

- ``dynamic``: Navrátil's ray-weighted rounds (Figs. 5-6). Each round the nodes all-reduce
  over the tree the rays waiting per domain and which node holds each domain, and each
  computes the same schedule: keep loaded domains where they are wanted, hand the most-wanted
  unloaded domains to nodes whose domains are no longer needed; rays for a scheduled domain
  then move to its node, which traces them. Rays start where their camera rays were made (an
  image-plane start). The next tile comes in while the last one's rays thin out, so a tile's
  last rounds are not paid alone (``actors.dynamic_frame``). Neither round involves the
  coordinator.

Within a node the rays follow the ``image`` schedule (``schedule.image``), so every ray visits
the same domains in the same order as on one node: the image is the reference image.
"""

from __future__ import annotations

import time
import zlib

import numpy as np

from vastray.actors.async_frame import AsyncFrame
from vastray.actors.dynamic_frame import DynamicFrame
from vastray.actors.job_options import JobOptions
from vastray.actors.node_state import NodeState, frame_load_stats
from vastray.actors.ray_post import traffic_counters
from vastray.actors.render_setup import RenderSetup
from vastray.actors.simplified_frames import finish_simplified, simplified_routing
from vastray.render.film import Film
from vastray.render.integrators import launched_camera_rays
from vastray.schedule import registry
from vastray.schedule.ownership import interleaved_paths, round_robin_owners
from vastray.schedule.registry import Decomposition


async def render_owned_domains(management, options: JobOptions, rank: int, size: int, store,
                               config, settings, on_tile=None, state: NodeState | None = None,
                               tree=None) -> tuple[Film, dict]:
    """Render this node's part of every tile under domain decomposition; returns the node's
    partial film (to be summed over nodes) and its counters. ``on_tile(paths)`` hears of the
    paths this node started, after each tile. ``state`` carries the preloader and held
    messages from one frame to the next (default: a fresh one, closed at the end)."""
    sched = registry.spec(options.scheduler)
    mode = sched.decomposition  # how this scheduler's frames move rays between nodes
    if mode is None:
        raise ValueError(f"--scheduler {sched.name} is not a domain-decomposition scheduler")
    own_state = state is None
    state = NodeState() if state is None else state
    setup = RenderSetup.of(store, config, settings)
    owner = round_robin_owners(len(store.domains), size)
    owned = int(np.count_nonzero(owner == rank))
    if mode is Decomposition.PLANNED:  # groups change from frame to frame: room for the largest
        owned = -(-len(store.domains) // size) + 1
    preloader = state.preloader_for(store, options.cache or max(owned, 1), setup.keep, options,
                                    rank, setup.fast_builds)
    before = preloader.stats()
    film = Film(settings.width, settings.height)
    total = setup.total_paths
    tile = max(1, min(options.max_samples_in_flight or total, total))
    n_tiles = -(-total // tile)
    stats = {**traffic_counters(), "shade_s": 0.0, "trace_s": 0.0, "wait_s": 0.0, "rounds": 0}
    node = state.node_work(management, rank, stats, preloader, options.max_batch_rays)
    base = state.tile_base  # tile labels are unique over the frames and passes of a job
    state.tile_base += n_tiles
    routing = simplified_routing(store, setup, options, state)
    try:
        if mode is Decomposition.ASYNC:
            frame = AsyncFrame(node, setup, settings, owner, rank, size, tile, film, on_tile,
                                base=base, status_label=state.ordinal, simple=routing,
                                resident_first=options.resident_first)
            await frame.run()
        elif mode is Decomposition.PLANNED:
            frame = await _temporal_frame(node, setup, settings, store, options, rank, size, tile,
                                          film, on_tile, base, state, preloader, tree, stats,
                                          routing)
        if not mode.rounds:
            stats["shade_s"] += frame.shade_s
            stats["tiles_made"] = frame.made
            await finish_simplified(routing, tree, state, stats, rank, options.portal_memory)
        elif mode is Decomposition.RAY_WEIGHTED:
            frame = DynamicFrame(node, setup, settings, owner, rank, size, tile, film, on_tile,
                                 base=base)
            await frame.run(tree)
            stats["shade_s"] += frame.shade_s
        for index, first in enumerate(range(0, total, tile)
                                      if mode is Decomposition.ROUNDS else ()):
            policy = setup.tile_schedule(settings, first, tile, owner, rank)
            ctx = policy.ctx
            mine = interleaved_paths(len(ctx.pixel), rank, size)
            node.begin_tile(base + index, policy)
            node.loop.start_tile(policy, launched_camera_rays(setup.camera, ctx, policy.result,
                                                              np.nonzero(mine)[0]))
            await node.rounds(policy, tree)
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
    stats["activations"] = len(node.loop.sequence)
    stats.update(frame_load_stats(before, preloader.stats()))
    stats["load_bandwidth_mb_s"] = preloader.load_bandwidth_mb_s()
    stats["cache_capacity"] = preloader.capacity
    stats["cache_bytes"] = preloader.cache.max_bytes
    held = preloader.stats()
    stats["peak_resident_domains"] = held["peak_resident_domains"]
    stats["peak_resident_bytes"] = held["peak_resident_bytes"]
    return film, stats


async def _temporal_frame(node, setup, settings, store, options: JobOptions, rank, size, tile,
                          film, on_tile, base, state: NodeState, preloader, tree, stats: dict,
                          routing=None):
    """One frame of ``temporal``: plan from the last frame's statistics, render, and sum this
    frame's statistics over the nodes for the next (kept in ``state.temporal_stats``)."""
    from vastray.actors.temporal import TemporalFrame, frame_assignment, summed_stats

    previous = state.temporal_stats
    sched = registry.spec(options.scheduler)
    # the effective ones, reported
    stats["assignment"] = options.assignment or sched.default_assignment
    stats["priority"] = options.priority or sched.default_priority
    # the capacity is the job's (``--cache``, else a group's worth): every node decides alike
    assignment = frame_assignment(stats["assignment"], store, setup.camera,
                                  settings.width, settings.height, size, previous,
                                  preloader.capacity)
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
