"""``simulate``: one render of a store on P virtual nodes in virtual time.

Each virtual node runs the nodes' own code for its scheduler (``actors.decomposition``,
``actors.insitu``, and for the sort-first ``image`` and ``spec-ooc`` the tile loop of
``actors.sort_first`` that ``actors.local`` runs, on virtual time), unit by unit (the passes of
each frame, as a job's units; out of core a sort-first node sweeps a frame's passes together,
as ``actors.node.units_together`` groups them), with its film summed up the tree after each
unit by the real tree-reduce actor. Rays are traced for real, so the image is the render's own
and the traffic between domains the true one; only time is the cost model's.
"""

from __future__ import annotations

import asyncio
import os
import time
from dataclasses import dataclass, field, replace

import numpy as np

from vastray.actors.decomposition import render_owned_domains
from vastray.actors.insitu import render_spec_insitu
from vastray.actors.job_options import JobOptions, default_tile
from vastray.actors.node import (
    SETTING_COUNTERS,
    UnitPasses,
    accumulate_counters,
    frame_inputs,
    units_together,
)
from vastray.actors.ray_post import traffic_counters
from vastray.actors.render_setup import RenderSetup
from vastray.actors.sort_first import PassSpans, SortFirstTiles, tile_cache_capacity
from vastray.actors.tree_reduce import TreeReduceActor
from vastray.render.driver import shading_inputs
from vastray.render.film import Film
from vastray.render.integrators import RenderSettings
from vastray.render.progressive import DEFAULT_MAX_PASS_SPP, pass_bounds
from vastray.render.scene_config import SceneConfig
from vastray.scene.errors import InputError
from vastray.scene.store import Store
from vastray.schedule import registry
from vastray.schedule.registry import SIMULATE_CHOICES, Simulation
from vastray.sim.cache import Domains
from vastray.sim.clock import run_virtual
from vastray.sim.cluster import Cluster
from vastray.sim.costs import CostModel
from vastray.sim.meter import start_node_task
from vastray.sim.node import SimManagement, SimNodeState

#: The schedulers the simulator runs (every distributed one; ``schedule.registry``'s, each
#: with its ``simulation``).
SIM_SCHEDULERS = SIMULATE_CHOICES


@dataclass
class SimResult:
    """What a simulated render reports.

    Attributes
    ----------
    scheduler, nodes : what was simulated.
    seconds : virtual seconds of the render (the busiest node's rendering, as a real run's
        ``busy_max``; the film reductions after each unit are not in it, as they are not in
        ``busy_max``).
    unit_seconds : (units,) virtual seconds of each unit (pass or frame pass; passes swept
        together: the sweep's in its first pass, none in the others).
    reduce_seconds : virtual seconds of the film reductions.
    compute_seconds : (P + 1,) virtual seconds each node (and the coordinator, last) computed.
    counters : the nodes' counters summed (loads, rays sent, batches, ...).
    node_counters : (P,) each node's counters.
    own_seconds : (P,) CPU seconds each node's own code took beyond the work charged apart
        (``sim.meter``; zeros where ``CostModel.node_cpu_scale`` is 0: not measured).
    messages, bytes : messages and bytes on the simulated network.
    film : the image's film (rank 0's after the last reduction; an animation's last frame's).
    wall_s : real seconds the simulation took.
    """

    scheduler: str
    nodes: int
    seconds: float
    unit_seconds: list
    reduce_seconds: float
    compute_seconds: np.ndarray
    counters: dict
    messages: int
    bytes: int
    film: Film
    wall_s: float
    costs: CostModel = field(repr=False, default=None)
    node_counters: list = field(repr=False, default_factory=list)
    own_seconds: np.ndarray = field(repr=False, default=None)

    def as_dict(self) -> dict:
        """The result for a JSON report (the film left out)."""
        return {"scheduler": self.scheduler, "nodes": self.nodes,
                "seconds": round(self.seconds, 6),
                "unit_seconds": [round(s, 6) for s in self.unit_seconds],
                "reduce_seconds": round(self.reduce_seconds, 6),
                "messages": self.messages, "bytes": self.bytes,
                "counters": self.counters, "wall_s": round(self.wall_s, 3),
                "costs": None if self.costs is None else self.costs.as_dict()}


def node_options(options: JobOptions, nodes: int) -> JobOptions:
    """The options a node of a job on ``nodes`` nodes runs with, as the coordinator completes
    them: ``default_tile``'s tile where none is set, one query thread."""
    return replace(options, max_samples_in_flight=options.max_samples_in_flight
                   or default_tile(options.scheduler, nodes), threads=1)


def simulate(store: Store, options: JobOptions, nodes: int, costs: CostModel,
             settings: RenderSettings, config: SceneConfig | None = None,
             frames: int | None = None, max_pass_spp: int | None = DEFAULT_MAX_PASS_SPP,
             domains: Domains | None = None) -> SimResult:
    """Simulate one render (or animation of ``frames`` frames) on ``nodes`` virtual nodes.

    Parameters
    ----------
    store : the domains.
    options : the job's options; ``options.scheduler`` is one of ``SIM_SCHEDULERS``.
    nodes : P.
    costs : the cost model (its ``cores``: the nodes share that many cores; None: one each).
    settings, config : the render's settings and scene.
    frames : an animation's frame count (None: one image).
    max_pass_spp : the passes' largest size (as ``vastray render --max-pass-spp``); None:
        each frame in one pass (as ``render_distributed`` without a progression).
    domains : the store's domains built in memory (made here if None; pass one to reuse it
        over several simulations).
    """
    sched = registry.find(options.scheduler)
    if sched is None or sched.simulation is None:
        raise ValueError(f"the simulator runs {', '.join(SIM_SCHEDULERS)}, not "
                         f"{options.scheduler!r}")
    if nodes < 1:
        raise ValueError("the simulator needs at least 1 node")
    _check_memory(options.scheduler, nodes, len(store.domains))
    config = SceneConfig() if config is None else config
    options = node_options(options, nodes)
    _check_path_memory(options, nodes, settings.paths)
    own = domains is None
    if own:
        domains = Domains(store, shading_inputs(store, config, settings.integrator)[1])
    units = [(frame, first, stop) for frame in (range(frames) if frames else [None])
             for first, stop in ([(0, settings.spp)] if max_pass_spp is None
                                 else pass_bounds(settings.spp, max_pass_spp))]
    start = time.perf_counter()
    try:
        if costs.trace_scale:
            _warm_up(store, options, settings, config, domains)
        outcome, _ = run_virtual(_render(store, options, nodes, costs, settings, config,
                                         units, domains))
    finally:
        if own:
            domains.close()
    per_node, unit_seconds, cluster, film = outcome
    node_counters = [c for _, _, c in per_node]
    return SimResult(options.scheduler, nodes, max(busy for busy, _, _ in per_node),
                     unit_seconds, max(r for _, r, _ in per_node), cluster.compute_s,
                     _summed(node_counters), cluster.messages, cluster.bytes,
                     film, time.perf_counter() - start, costs, node_counters,
                     np.array([cluster.meter.measured[rank] for rank in range(nodes)]))


#: (scheduler, integrator) whose code paths this process has run once (``_warm_up``).
_WARMED: set[tuple[str, str]] = set()
#: The warm-up render: a few pixels, one sample.
WARM_UP_PIXELS = (8, 8)


def _warm_up(store, options: JobOptions, settings: RenderSettings, config, domains) -> None:
    """Run the scheduler's code once, uncharged, on a few pixels of one node: where traces are
    charged at the CPU time they take here (``CostModel.trace_scale``), this process's own
    first use (compiled kernels loaded from numba's cache) must not be charged to the first
    virtual node that traces (a node's first use is ``warmup_s``, charged apart)."""
    key = (options.scheduler, settings.integrator)
    if key in _WARMED:
        return
    width, height = WARM_UP_PIXELS
    tiny = replace(settings, width=width, height=height, spp=1)
    run_virtual(_render(store, options, 1, CostModel(), tiny, config, [(None, 0, 1)], domains))
    _WARMED.add(key)


def _check_memory(scheduler: str, nodes: int, n_domains: int) -> None:
    """Refuse (``InputError``) a simulation whose nodes' state cannot fit in this machine's
    memory: every virtual node lives in this process, and the frame statistics of a scheduler
    that keeps them (``temporal``) hold (D, D) transmission counts, about four copies of them
    during the tree reduce."""
    sched = registry.spec(scheduler)
    if not sched.frame_statistics:
        return
    _refuse_beyond_memory(4 * 8 * n_domains ** 2 * nodes,
                          f"{sched.name} on {nodes} virtual nodes of {n_domains} domains",
                          "the nodes' frame statistics ((D, D) per node)",
                          "simulate fewer nodes or a store of fewer domains")


def _refuse_beyond_memory(need: float, run: str, state: str, advice: str) -> None:
    """Raise ``InputError`` where ``need`` bytes exceed half this machine's memory."""
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if need > memory / 2:
        raise InputError(None, f"{run} needs about {need / 2 ** 30:.0f} GiB for {state} and "
                               f"this machine has {memory / 2 ** 30:.0f} GiB: {advice}")


#: Bytes of path state a domain-decomposition node keeps for each path of a tile (48
#: measured with ``tracemalloc`` on a 262,144-path tile, with room for the schedule's own).
PATH_STATE_BYTES = 64


def _check_path_memory(options: JobOptions, nodes: int, paths: int) -> None:
    """Refuse (``InputError``) a simulation whose virtual nodes' path state cannot fit in
    this machine's memory: every domain-decomposition node keeps state for each path of a
    tile, and every virtual node lives in this process (the default tile grows with the
    nodes, ``job_options.default_tile``)."""
    if not registry.spec(options.scheduler).runtime.nodes_only:
        return
    tile = min(options.max_samples_in_flight or paths, paths)
    _refuse_beyond_memory(PATH_STATE_BYTES * tile * nodes,
                          f"{options.scheduler} on {nodes} virtual nodes with tiles of "
                          f"{tile:,} paths",
                          "the nodes' path state (each keeps every path of a tile)",
                          "set a smaller --max-samples-in-flight, or simulate fewer nodes")


async def _render(store, options, size, costs, settings, config, units, domains):
    cluster = Cluster(size, costs,
                      costs.first_touch_s(paths_in_flight(options, size, settings, units)))
    unit_ends: list[list[float]] = [[] for _ in units]
    loop = asyncio.get_running_loop()
    if costs.node_cpu_scale:  # each node's own code measured as it runs (``sim.meter``)
        loop.set_task_factory(cluster.meter.task_factory)
    # No coordinator runs: it takes part in no round and no termination (the nodes' tree
    # does both); what it does once per job (start, films) is outside the simulated span.
    with cluster.meter.collections_apart():
        per_node = await asyncio.gather(*(
            start_node_task(loop, rank, _node(cluster, rank, store, options, settings, config,
                                              units, domains, unit_ends))
            for rank in range(size)))
    marks = [0.0] + [max(ends) for ends in unit_ends]
    film = per_node[0][3]
    return ([p[:3] for p in per_node], list(np.diff(marks)), cluster, film)


def paths_in_flight(options: JobOptions, size: int, settings: RenderSettings,
                    units: list) -> int:
    """Paths a node of ``size`` holds at once (what its first touch of memory is charged
    for, ``CostModel.first_touch_s``): its share of the largest unit's paths, at most a tile
    (``max_samples_in_flight``: a sort-first node's own, a domain-decomposition job's as a
    whole, of which each node starts its share)."""
    largest = max(settings.window(*unit[1:]).paths for unit in units)
    tile = min(options.max_samples_in_flight or largest, largest)
    if registry.spec(options.scheduler).runtime.nodes_only:
        return -(-tile // size)
    return min(tile, -(-largest // size))


async def _node(cluster: Cluster, rank: int, store, options, settings, config, units, domains,
                unit_ends):
    """One virtual node's job (``actors.node``'s unit loop): each unit rendered (or, as
    ``units_together`` groups them, several passes in one sweep), then each unit's film summed
    up the tree."""
    size = cluster.size
    management = SimManagement(cluster, rank)
    tree = TreeReduceActor(management, rank, size)
    state = SimNodeState(cluster=cluster, rank=rank, domains=domains)
    busy = reduce = 0.0
    totals: dict = {}
    film = None  # the frame's passes merged (rank 0's the whole image)
    ordinal = 0
    while ordinal < len(units):
        frame = units[ordinal][0]
        if ordinal == 0 or frame != units[ordinal - 1][0]:
            film = Film(settings.width, settings.height)
        frame_settings, frame_config = frame_inputs(settings, config, store, frame)
        # no stopping rule and no reference in a simulation: passes apart only in core
        group = units_together(units, ordinal, options, False, len(store.domains),
                               settings.width * settings.height)
        windows = [units[unit][1:] for unit in group]
        state.ordinal, state.frame = ordinal, frame or 0
        await cluster.flush(rank)  # the last unit's film reduction: not this unit's span
        start = cluster.now()
        if not cluster.costs.node_cpu_scale:  # else measured as the node makes them
            paths = sum(frame_settings.window(*window).paths for window in windows)
            await cluster.compute(rank, cluster.costs.camera_ray_s * paths / size)
        if len(group) > 1:
            parts, counters = await _sort_first_passes(options, rank, size, store,
                                                       frame_config, frame_settings, windows,
                                                       state)
        else:
            part, counters = await _share(cluster, management, tree, options, rank, size,
                                          store, frame_config,
                                          frame_settings.window(*windows[0]), state)
            parts = [part]
        await cluster.flush(rank)
        busy += cluster.now() - start
        for unit in group:  # a sweep's time is its first pass's
            unit_ends[unit].append(cluster.now())
        for unit, part in zip(group, parts, strict=True):
            reduced = cluster.now()
            film.merge(await tree.reduce_film(part, settings.width, settings.height, unit))
            reduce += cluster.now() - reduced
        accumulate_counters(totals, counters)
        ordinal = group[-1] + 1
    return busy, reduce, totals, film


async def _share(cluster, management, tree, options, rank, size, store, config, settings,
                 state):
    """This node's partial film of one unit and its counters (``actors.node.render_share``
    with the sort-first schedulers on virtual time), as the scheduler's ``simulation`` says."""
    runner = SIMULATION_RUNNERS[registry.spec(options.scheduler).simulation]
    return await runner(cluster, management, tree, options, rank, size, store, config,
                        settings, state)


async def _in_situ_share(cluster, management, tree, options, rank, size, store, config,
                         settings, state):
    return await render_spec_insitu(management, tree, options, rank, size, store, config,
                                    settings, state=state)


async def _domains_share(cluster, management, tree, options, rank, size, store, config,
                         settings, state):
    return await render_owned_domains(management, options, rank, size, store, config,
                                      settings, state=state, tree=tree)


async def _sort_first_share(cluster, management, tree, options, rank, size, store, config,
                            settings, state):
    """``actors.local.render_out_of_core`` with ``share=(rank, size)`` on virtual time: this
    node's tiles of one pass, by the same ``SortFirstTiles``."""
    tiles, stats = _sort_first_tiles(options, rank, size, store, config, settings, state)
    film = await tiles.render_pass(settings)
    return film, _with_loads(stats, tiles)


async def _sort_first_passes(options, rank, size, store, config, settings, windows, state):
    """``actors.node.render_passes_together`` on virtual time: this node's partial film of each
    pass in ``windows`` (sample ranges of one frame), in one sweep of tiles."""
    tiles, stats = _sort_first_tiles(options, rank, size, store, config, settings, state)
    passes = UnitPasses(windows)
    await tiles.render_passes(PassSpans(passes, settings))
    return passes.films, _with_loads(stats, tiles)


def _sort_first_tiles(options, rank, size, store, config, settings, state):
    """The node's ``SortFirstTiles`` through its cache (kept from unit to unit, as a node's
    ``NodeState`` keeps it) on a ``VirtualDomainLoop``, and the counters it adds to."""
    setup = RenderSetup.of(store, config, settings)
    preloader = state.preloader_for(store, tile_cache_capacity(options, store), setup.keep,
                                    options, rank, setup.fast_builds)
    stats = {**traffic_counters(), "shade_s": 0.0}
    return SortFirstTiles(options, setup, state.tile_loop(preloader, stats), (rank, size)), stats


def _with_loads(stats: dict, tiles: SortFirstTiles) -> dict:
    """``stats`` with the loads the node's cache made since ``tiles`` was made, and its
    activations (as ``render_out_of_core`` reports them)."""
    cache = tiles.cache_stats()
    stats.update(loads=cache.loads, preloads=cache.preloads, bytes_loaded=cache.bytes_loaded,
                 activations=len(tiles.loop.sequence))
    return stats


#: The runner of each ``Simulation`` (``_share`` dispatches on the scheduler's).
SIMULATION_RUNNERS = {Simulation.SORT_FIRST: _sort_first_share, Simulation.DOMAINS: _domains_share,
                      Simulation.IN_SITU: _in_situ_share}


def _summed(parts: list[dict]) -> dict:
    """The nodes' counters over the job: counts summed, peaks the largest, settings one
    node's."""
    total: dict = {}
    for part in parts:
        for key, value in part.items():
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                continue
            if key.startswith("peak"):
                total[key] = max(total.get(key, value), value)
            elif key in SETTING_COUNTERS:
                total.setdefault(key, value)
            else:
                total[key] = total.get(key, 0) + value
    return {k: round(v, 6) if isinstance(v, float) else v for k, v in total.items()}
