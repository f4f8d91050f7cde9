"""``vastray calibrate``: measure the simulator's cost constants (``costs.CostModel``) on the
machine it runs on, with the project's own components, never mocks.

- loads: ``DomainCache.load`` of every domain, from the page cache (or, ``cold_reads``, each
  read a read of the disk, its pages dropped after), its read timed apart from its BVH build;
- tracing: the ``image`` schedule (``ImageSchedule``) over one tile of path-tracing paths with
  every domain resident, each ``process`` call timed with its radiance and shadow queries,
  and the camera rays it starts from; then each call handed to a worker thread as a node's
  loop does, for what the hand-off costs (``offload_s``);
- the wire: two processes (``multiprocessing``'s spawn) exchanging real ray batches over
  ZeroMQ (a DEALER to the peer's ROUTER, as nodes do) in the project's wire codec; then the
  same batches between two of the nodes' own management actors (``time_node_messages``),
  whose CPU beyond the raw wire is what a node pays to receive one (``receive_s``);
- warm processes (``vastray.sim.warmup``): the machine's throughput with 1 to 4 x cores
  processes rendering side by side, in interleaved rounds, from their CPU seconds;
- what a fresh node pays in proportion to its paths: two sizes of renders in fresh processes
  and their page faults (``vastray.sim.first_touch``: ``page_fault_s``,
  ``fresh_pages_per_path``);
- what a node pays once: real ``async``, ``image`` and ``spec-insitu`` renders of a few
  pixels on ``node_cost.SETUP_NODES`` node processes against the simulator's predictions of
  them (``vastray.sim.node_cost``): the least of the three is every fresh process's first
  use (``warmup_s``), the rest each runtime's own set-up.

Each measurement has a time budget (``Effort``), so a run takes about as long on a large store
as on a small one; ``quick`` has smaller budgets (a test, a first look).
"""

from __future__ import annotations

import asyncio
import datetime
import math
import multiprocessing
import os
import platform
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import uvloop
import zmq

from vastray.actors import protocol
from vastray.actors.domain_loop import traced_queries
from vastray.actors.render_setup import RenderSetup
from vastray.render.driver import path_context
from vastray.render.integrators import RenderSettings, camera_rays, launched_camera_rays
from vastray.render.scene_config import SceneConfig
from vastray.report import package_version
from vastray.scene.bvh import DomainBVH
from vastray.scene.cache import DomainCache
from vastray.scene.store import DomainArrays, Store
from vastray.schedule.image import ImageSchedule
from vastray.schedule.paths import radiance_soa, start_cursor
from vastray.sim import first_touch
from vastray.sim.costs import CostModel
from vastray.sim.node_cost import SETUP_NODES, setup_cost
from vastray.sim.steal import others_running
from vastray.sim.warmup import (
    WarmProcesses,
    beside_others,
    interpolated,
    measure_rounds,
    process_costs,
    throughput_counts,
    throughput_of,
)
from vastray.transport.codec import Message, decode, encode, frames_nbytes

#: ``progress(fraction, text)``: fraction in [0, 1] of the calibration done, and what runs now.
Progress = Callable[[float, str], None]

#: Rays in the batches the wire is measured with (0: the empty batch some protocols send).
WIRE_RAYS = (0, 1_000, 10_000, 100_000)
#: What a peer that died before its hello most likely means.
SPAWN_HINT = (" (it is started with multiprocessing's spawn method: a script calling "
              "calibrate() needs its main code under `if __name__ == \"__main__\":`)")
#: Seconds the peer process has to start and say hello, and to answer one batch.
PEER_START_TIMEOUT_S = 60.0
PEER_REPLY_TIMEOUT_S = 20.0


class CalibrationError(RuntimeError):
    """A measurement could not be made (the peer process did not start or answer)."""


@dataclass(frozen=True)
class Effort:
    """How much each measurement may take.

    Attributes
    ----------
    load_s : seconds of cold domain loads (at least ``min_loads`` are made).
    trace_s : seconds of repeated tiles (at least ``min_tiles``).
    spp : samples per pixel of the tile (64 x 48 pixels).
    wire_s : seconds of ping-pong per batch size (at least ``min_pings`` each).
    """

    load_s: float
    min_loads: int
    trace_s: float
    min_tiles: int
    spp: int
    wire_s: float
    min_pings: int


FULL = Effort(load_s=5.0, min_loads=8, trace_s=12.0, min_tiles=3, spp=4, wire_s=2.5,
              min_pings=10)
QUICK = Effort(load_s=1.0, min_loads=4, trace_s=2.0, min_tiles=2, spp=2, wire_s=0.4,
               min_pings=4)

#: Share of the run each stage takes (for ``progress``), in the order they run.
STAGES = {"setup": 0.02, "loads": 0.07, "tracing": 0.18, "wire": 0.17, "warmup": 0.19,
          "first touch": 0.04, "node": 0.33}


def node_settings(settings: RenderSettings) -> RenderSettings:
    """The measuring processes' render (``vastray.sim.warmup``): the tile's settings at twice the
    width and height (a render of its own, not the traced tile again)."""
    return replace(settings, width=2 * settings.width, height=2 * settings.height)


def setup_settings(settings: RenderSettings) -> RenderSettings:
    """The real renders that measure what a node pays once (``setup_cost``): 16 x 12
    pixels at one sample, so their time beyond the simulator's charge for their work is the
    fixed cost and not also what the model misses in proportion to work (a render of the
    tile's size charged that share to every node as a constant: 0.37 s where 8 fresh nodes
    side by side on a scan paid about 0.2 s each, measured)."""
    return replace(settings, width=16, height=12, spp=1)


def calibration_settings(quick: bool = False, **overrides) -> RenderSettings:
    """The render settings of the calibration tile: 64 x 48 path-traced pixels at ``spp``
    (``Effort.spp``), the other settings the render defaults for a store (``overrides``
    replace them, e.g. the built-in scene's ``bounces`` and ``shadow_samples``)."""
    effort = QUICK if quick else FULL
    return replace(RenderSettings(width=64, height=48, spp=effort.spp, integrator="pt"),
                   **overrides)


def calibrate(store_path: str | os.PathLike, *, quick: bool = False,
              progress: Progress | None = None, config: SceneConfig | None = None,
              settings: RenderSettings | None = None, cold_reads: bool = False) -> CostModel:
    """Measure every constant of the cost model on this machine.

    Parameters
    ----------
    store_path : a domain store; its domains are loaded and traced.
    quick : smaller time budgets (``QUICK``: about a third of the default ``FULL``'s time).
    progress : called as ``progress(fraction, text)`` as the stages run.
    config : camera, lights and materials (default: those a render of a store has without a
        scene file).
    settings : the tile's render settings (default: ``calibration_settings(quick)``).
    cold_reads : time loads as reads of the disk (``--cold-reads`` renders); default: from
        the page cache, as renders of a store already read load.

    Returns
    -------
    CostModel
        The measured constants, ``cores`` (CPUs this process may run on) and ``machine``.

    Raises
    ------
    InputError
        The store is missing or damaged (naming the file).
    CalibrationError
        The peer process of the wire measurement did not start or answer.

    Notes
    -----
    The peer process is started with multiprocessing's spawn method, which imports the
    caller's main module again: a script calling ``calibrate`` needs its main code under
    ``if __name__ == "__main__":`` (the ``vastray`` command has it).
    """
    start = time.perf_counter()
    effort = QUICK if quick else FULL
    report = _Stages(progress)
    report("setup", 0.0, "opening the store")
    store = Store(store_path)
    settings = settings or calibration_settings(quick)
    setup = RenderSetup.of(store, config or SceneConfig(text=""), settings)
    report("loads", 0.0, "loading domains")
    read_fixed_s, load_byte_s, build_fixed_s, build_triangle_s = load_costs(
        time_loads(store, setup.keep, effort, report.within("loads"), cold_reads),
        time_merged_builds(store, setup.keep))
    report("tracing", 0.0, "tracing tiles")
    tiles, offload = time_tiles(store, setup, settings, effort, report.within("tracing"))
    tracing = trace_costs(tiles)
    report("wire", 0.0, "ray batches between two processes")
    latency_s, byte_s = wire_costs(time_wire(setup, effort, report.within("wire")))
    report("wire", 1.0, "ray batches between two nodes' management actors")
    # what the nodes' messaging costs beyond the raw wire's one-way time (charged to the
    # receiver: its routing, checks and mailbox)
    receive_s = max(0.0, time_node_messages(setup, effort) - latency_s)
    report("warmup", 0.0, "busy processes side by side, one and several at a time")
    cores = usable_cores()
    throughput = process_costs(str(store_path), quick, cores)
    # decisions and traces are charged at the CPU time the real code takes where it
    # simulates (the constants stay for another machine's simulations, trace_scale 0)
    model = CostModel(
        **tracing, load_byte_s=load_byte_s, build_triangle_s=build_triangle_s,
        read_fixed_s=read_fixed_s, build_fixed_s=build_fixed_s,
        latency_s=latency_s, byte_s=byte_s, receive_s=receive_s, decision_scale=1.0,
        trace_scale=1.0, node_cpu_scale=1.0, load_scale=1.0,
        offload_s=float(np.median(offload)) if offload else 0.0,
        cores=cores, throughput=throughput)
    report("first touch", 0.0, "fresh processes touching their memory")
    # before the set-up renders: what a fresh node pays in proportion to its paths is not
    # its fixed cost
    page_fault_s, fresh_pages_per_path = first_touch.measure(str(store_path), quick)
    model = replace(model, page_fault_s=page_fault_s, fresh_pages_per_path=fresh_pages_per_path)
    report("node", 0.0, f"renders on {SETUP_NODES} real nodes")
    # each pair starts SETUP_NODES fresh node processes (about 8 s on 2 cores)
    config, repeats = config or SceneConfig(text=""), 2 if quick else 3

    def fixed_cost(scheduler: str, done: float) -> float:
        cost = setup_cost(store_path, model, config, setup_settings(settings), scheduler,
                          repeats)
        report("node", done, f"renders on {SETUP_NODES} real nodes")
        return cost

    node_fixed = fixed_cost("async", 1 / 3)  # the node runtimes
    tile_fixed = fixed_cost("image", 2 / 3)  # the sort-first nodes
    insitu_fixed = fixed_cost("spec-insitu", 1.0)  # the in-situ nodes
    # what every runtime pays (a fresh process's first use), then what each adds
    warmup_s = min(node_fixed, tile_fixed, insitu_fixed)
    node_setup_s = node_fixed - warmup_s
    tile_setup_s = tile_fixed - warmup_s
    insitu_setup_s = insitu_fixed - warmup_s
    return replace(
        model, warmup_s=warmup_s, node_setup_s=node_setup_s, tile_setup_s=tile_setup_s,
        insitu_setup_s=insitu_setup_s,
        machine=machine_info(calibration={"store": str(Path(store_path)), "quick": quick,
                                          "cold_reads": cold_reads,
                                          "seconds": round(time.perf_counter() - start, 2)}))


class _Stages:
    """``progress`` in terms of ``STAGES``: (stage, fraction of that stage, text)."""

    def __init__(self, progress: Progress | None):
        self.progress = progress

    def __call__(self, stage: str, fraction: float, text: str) -> None:
        if self.progress is None:
            return
        names = list(STAGES)
        done = sum(STAGES[n] for n in names[:names.index(stage)])
        self.progress(min(1.0, round(done + STAGES[stage] * min(max(fraction, 0.0), 1.0), 6)),
                      text)

    def within(self, stage: str) -> Callable[[float, str], None]:
        """``progress`` of one stage: (fraction of the stage, text)."""
        return lambda fraction, text: self(stage, fraction, text)


# -- loads ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class LoadSample:
    """One load of a domain: its manifest bytes and triangles, the wall seconds of the read of
    its files and the CPU seconds (every thread's) of its BVH build (``_timed_load``)."""

    nbytes: int
    triangles: int
    read_s: float
    build_s: float


def drop_store_pages(store: Store) -> None:
    """Write back and drop the page cache of every domain file, so that the first load of
    each is a read of the disk too (the kernel drops clean pages only; a store written
    moments before may still have dirty ones)."""
    if not hasattr(os, "posix_fadvise"):
        return
    for info in store.domains:
        for kind in info.files:
            fd = os.open(store.domain_path(info, kind), os.O_RDONLY)
            try:
                os.fdatasync(fd)
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
            finally:
                os.close(fd)


def time_loads(store: Store, keep: frozenset[str], effort: Effort,
               progress: Callable[[float, str], None], cold: bool = False) -> list[LoadSample]:
    """Loads of the non-empty domains, round after round, for ``effort.load_s`` seconds
    (and at least ``effort.min_loads``), after one untimed load (first-use costs). ``cold``:
    every read is a read of the disk (as ``vastray render --cold-reads``); otherwise the
    files come from the page cache, as a render's loads do once a store has been read.

    Returns
    -------
    list of LoadSample, one per timed load (``_timed_load``: the read in wall seconds, the
    build in CPU seconds).
    """
    domains = [d.id for d in store.domains if d.n_triangles > 0]
    if not domains:
        raise CalibrationError(f"{store.path}: the store has no triangles to load")
    if cold:
        drop_store_pages(store)
    else:  # every file read once, untimed: in the page cache from now on
        for domain in domains:
            store.load_domain(domain)
    cache = DomainCache(store, 1, keep, drop_page_cache=cold)
    cache.load(domains[0]).close()  # the Embree device, first reads of the code paths
    samples: list[LoadSample] = []
    start = time.perf_counter()
    while (elapsed := time.perf_counter() - start) < effort.load_s or len(samples) < effort.min_loads:
        progress(elapsed / effort.load_s, f"loading domains ({len(samples)} loads)")
        samples.append(_timed_load(cache, domains[len(samples) % len(domains)]))
    return samples


def _timed_load(cache: DomainCache, domain: int) -> LoadSample:
    """One load of ``domain`` as ``cache.load`` makes it (not kept): the read's wall seconds
    and the build's CPU seconds.

    The build is timed in CPU seconds of the whole process (``time.process_time``: Embree's
    build threads too), not in wall seconds: Embree builds a domain of tens of thousands of
    triangles on every core (a turbine scan's 25,000-triangle domain here: 6.4 ms of wall
    time, 12.5 ms of CPU on 2 cores; one of rm 64³'s 2,400 triangles: one core), and a node
    that shares its cores with its own traces and other nodes pays the CPU. Timed in wall
    seconds on the idle calibration machine, a large domain's build was charged half of it.
    """
    store = cache.store
    start = time.perf_counter()
    arrays = store.load_domain(domain, drop_cache=cache.drop_page_cache, attributes=cache.keep)
    read_s = time.perf_counter() - start
    cpu = time.process_time()
    bvh = DomainBVH(domain, arrays, cache.keep, None, cache.build_quality, cache.mesh_quality)
    build_s = time.process_time() - cpu
    bvh.close()
    info = store.domains[domain]
    return LoadSample(info.read_bytes(cache.keep), info.n_triangles, read_s, build_s)


def time_merged_builds(store: Store, keep: frozenset[str], rounds: int = 3
                       ) -> list[tuple[int, float]]:
    """BVH builds over the first k non-empty domains' triangles as one mesh (placed as in the
    store), k = 2, 4, 8, ... and all, ``rounds`` times each, as ``DomainCache.load`` builds
    (its build qualities for a cache smaller than the store).

    A store's domains are of similar sizes (rm 64³ in 3x3x2: 1,472-3,267 triangles), too
    close to tell a build's fixed cost from its cost per triangle; these builds span one
    domain to the whole store.

    Returns
    -------
    list of (triangles, CPU seconds of every thread: ``_timed_load``), one per build.
    """
    ids = [d.id for d in store.domains if d.n_triangles > 0]
    arrays = [store.load_domain(i) for i in ids]
    cache = DomainCache(store, 1, keep)
    counts = sorted({min(2 ** j, len(ids)) for j in range(1, max(1, len(ids) - 1).bit_length() + 1)})
    # the first build pays first uses (4-8x a warm one): untimed
    DomainBVH(-1, arrays[0], keep, None, cache.build_quality, cache.mesh_quality).close()
    samples = []
    for k in counts:
        merged = merged_arrays(arrays[:k])
        for _ in range(rounds):
            cpu = time.process_time()  # CPU seconds, Embree's build threads too (_timed_load)
            bvh = DomainBVH(-1, merged, keep, None, cache.build_quality, cache.mesh_quality)
            samples.append((int(merged.indices.shape[0]), time.process_time() - cpu))
            bvh.close()
    return samples


def merged_arrays(parts: list[DomainArrays]) -> DomainArrays:
    """The triangles of ``parts`` as one mesh, each placed at its origin relative to the
    first's (no attributes: a build does not read them)."""
    base = np.zeros(3) if parts[0].origin is None else np.asarray(parts[0].origin, np.float64)
    vertices, indices, offset = [], [], 0
    for part in parts:
        origin = np.zeros(3) if part.origin is None else np.asarray(part.origin, np.float64)
        vertices.append((part.vertices + (origin - base)).astype(np.float32))
        indices.append(part.indices + np.uint32(offset))
        offset += part.vertices.shape[0]
    return DomainArrays(vertices=np.concatenate(vertices), indices=np.concatenate(indices),
                        origin=None if parts[0].origin is None else base)


def load_costs(samples: list[LoadSample], builds: list[tuple[int, float]] = ()
               ) -> tuple[float, float, float, float]:
    """(read_fixed_s, load_byte_s, build_fixed_s, build_triangle_s): a load's read and build
    each fitted as a fixed cost plus a cost per byte or per triangle.

    Least squares with relative residuals (weights 1 / seconds**2): the read over the loads'
    bytes; the build over one point a size, the loads' medians (triangles, seconds) and the
    median of each size of ``builds`` (``time_merged_builds``: up to the whole store, which
    is what sets the build's slope; thousands of loads at one size would otherwise outweigh
    them). A fit that noise leaves with a negative part, or sizes too alike to fit (the
    largest under 1.5x the smallest), falls back to no fixed cost and the ratio of totals,
    which gives exactly the measured total at the measured sizes. Before session 30 both
    were that ratio: it charged the domains of a CT scan, 10x the calibration store's
    triangles, 2.4x their real load time (a load's fixed part, about 0.5-1 ms here, charged
    per triangle).
    """
    nbytes = np.array([s.nbytes for s in samples], np.float64)
    read = np.array([s.read_s for s in samples], np.float64)
    sizes = sorted({t for t, _ in builds})
    triangles = np.array([np.median([s.triangles for s in samples])] + sizes, np.float64)
    build = np.array([np.median([s.build_s for s in samples])]
                     + [np.median([b for t, b in builds if t == size]) for size in sizes],
                     np.float64)
    if not builds:  # no wider sizes: the loads themselves, as the read
        triangles = np.array([s.triangles for s in samples], np.float64)
        build = np.array([s.build_s for s in samples], np.float64)
    return (*_fixed_and_slope(nbytes, read), *_fixed_and_slope(triangles, build))


def _fixed_and_slope(x: np.ndarray, seconds: np.ndarray) -> tuple[float, float]:
    """(fixed, per unit) of ``seconds ~ fixed + x * per_unit``, as ``load_costs`` says."""
    ratio = (0.0, float(seconds.sum() / max(x.sum(), 1.0)))
    usable = (x > 0) & (seconds > 0)
    if usable.sum() < 2 or x[usable].max() < 1.5 * x[usable].min():
        return ratio
    fixed, slope = fit_line(x[usable], seconds[usable], 1.0 / seconds[usable] ** 2)
    return (fixed, slope) if fixed >= 0.0 and slope > 0.0 else ratio


# -- tracing --------------------------------------------------------------------------------
@dataclass(frozen=True)
class TileTiming:
    """One traced tile.

    Attributes
    ----------
    camera_s : seconds to make its camera rays (``path_context`` and
        ``launched_camera_rays``, as the nodes make them: none where nothing can be seen).
    paths : its paths (the cost model's ``camera_ray_s`` is per path).
    calls : ((domain, radiance queries, shadow queries, seconds), ...) of each ``process``
        call, in order.
    shade_s : the schedule's ``shade_s`` counter at the end.
    """

    camera_s: float
    paths: int
    calls: tuple[tuple[int, int, int, float], ...]
    shade_s: float


def resident_cache(store: Store, keep: frozenset[str]) -> DomainCache:
    """A cache with room for every domain, the non-empty ones loaded now (none is evicted
    while tracing; the schedule never sends rays to an empty one)."""
    cache = DomainCache(store, max(len(store.domains), 1), keep)
    for info in store.domains:
        if info.n_triangles > 0:
            cache.get(info.id)
    return cache


def time_tile(setup: RenderSetup, settings: RenderSettings, cache: DomainCache) -> TileTiming:
    """Trace one tile of every path of ``settings`` with the ``image`` schedule, as the
    one-process runtime does (every domain resident, so the schedule serves them in its own
    order), timing each ``process`` call."""
    start = time.perf_counter()
    ctx = path_context(setup.shading, settings, 0, settings.paths, setup.ao_distance)
    camera_s = time.perf_counter() - start
    policy = ImageSchedule(ctx, setup.geometry, setup.color_source, setup.scalar_range)
    start = time.perf_counter()
    rays = launched_camera_rays(setup.camera, ctx, policy.result)
    camera_s += time.perf_counter() - start
    policy.start(rays)
    resident = cache.resident_set()
    calls = []
    while (domain := policy.next_domain(resident)) is not None:
        bvh = cache.get(domain)
        t0 = time.perf_counter()
        queries = traced_queries(policy, domain, bvh)
        seconds = time.perf_counter() - t0
        calls.append((domain, queries.radiance, queries.shadow, seconds))
    return TileTiming(camera_s, len(ctx.pixel), tuple(calls), policy.counters["shade_s"])


def time_tiles(store: Store, setup: RenderSetup, settings: RenderSettings, effort: Effort,
               progress: Callable[[float, str], None]) -> list[TileTiming]:
    """The same tile traced again and again for ``effort.trace_s`` seconds (at least
    ``effort.min_tiles`` times), after one untimed tile (kernels loaded, first-use costs).

    Returns
    -------
    tiles : list of TileTiming, one per timed tile.
    offload : seconds each activation of two more tiles waited beyond its trace when traced
        on a worker thread (``time_offload``).
    """
    cache = resident_cache(store, setup.keep)
    try:
        time_tile(setup, settings, cache)
        tiles: list[TileTiming] = []
        start = time.perf_counter()
        while (elapsed := time.perf_counter() - start) < effort.trace_s or len(tiles) < effort.min_tiles:
            progress(elapsed / effort.trace_s, f"tracing tiles ({len(tiles)} done)")
            tiles.append(time_tile(setup, settings, cache))
        progress(1.0, "tracing tiles on a worker thread, as nodes do")
        offload = time_offload(setup, settings, cache)
    finally:
        cache.close()
    return tiles, offload


def time_offload(setup: RenderSetup, settings: RenderSettings, cache: DomainCache,
                 tiles: int = 2) -> list[float]:
    """What a node runtime pays per activation to trace on a worker thread: ``tiles`` tiles
    traced as the nodes' ``DomainLoop`` with ``offload`` does (each ``process`` call through
    ``asyncio.to_thread``, on uvloop's event loop as ``vastray node`` runs), each call's
    seconds as the event loop waited for it less the seconds it ran on the worker thread.

    Returns
    -------
    list of float, one per call (>= 0).
    """
    def on_worker(policy, domain, bvh) -> float:
        start = time.perf_counter()
        traced_queries(policy, domain, bvh)
        return time.perf_counter() - start

    async def run() -> list[float]:
        out = []
        resident = cache.resident_set()
        for _ in range(tiles):
            ctx = path_context(setup.shading, settings, 0, settings.paths, setup.ao_distance)
            policy = ImageSchedule(ctx, setup.geometry, setup.color_source, setup.scalar_range)
            policy.start(launched_camera_rays(setup.camera, ctx, policy.result))
            while (domain := policy.next_domain(resident)) is not None:
                bvh = cache.get(domain)
                start = time.perf_counter()
                worked = await asyncio.to_thread(on_worker, policy, domain, bvh)
                out.append(max(0.0, time.perf_counter() - start - worked))
        return out

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        return runner.run(run())


def median_calls(tiles: list[TileTiming]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(radiance (m,), shadow (m,), seconds (m,)) queries and seconds of each distinct call,
    its seconds the median over the tiles that made it.

    The tiles are the same paths, and the schedule's order and ray counts do not depend on
    timing (the project's invariant), so call k of every tile is the same work: its median
    is robust to another process taking the CPU for a while on a shared machine. Calls are
    keyed by (position, domain, queries), so a tile that differed would only add keys.
    """
    groups: dict[tuple[int, int, int, int], list[float]] = {}
    for tile in tiles:
        for k, (domain, radiance, shadow, seconds) in enumerate(tile.calls):
            groups.setdefault((k, domain, radiance, shadow), []).append(seconds)
    keys = sorted(groups)
    return (np.array([k[2] for k in keys], np.float64), np.array([k[3] for k in keys],
                                                                 np.float64),
            np.array([np.median(groups[k]) for k in keys], np.float64))


def fit_line(x: np.ndarray, y: np.ndarray,
             weights: np.ndarray | None = None) -> tuple[float, float]:
    """Least-squares (intercept, slope) of ``y ~ intercept + slope * x``.

    Parameters
    ----------
    x, y : (m,) float64, m >= 1.
    weights : (m,) float64 > 0, each squared residual's weight (None: all 1).
    """
    w = np.sqrt(np.ones_like(y) if weights is None else weights)
    design = np.stack([np.ones_like(x), x], axis=1) * w[:, None]
    (intercept, slope), *_ = np.linalg.lstsq(design, y * w, rcond=None)
    return float(intercept), float(slope)


def trace_costs(tiles: list[TileTiming]) -> dict[str, float]:
    """trace_ray_s, shade_ray_s, shadow_ray_s, activation_s, shadow_activation_s and
    camera_ray_s from timed tiles.

    The seconds of a ``process`` call with r radiance and s shadow queries are fitted as
    ``activation_s [r > 0] + shadow_activation_s [r = 0] + r (trace + shade) + s shadow_ray_s``
    (least squares over the calls, each constant clipped to >= 0): an activation that shades
    costs several times one that only tests shadow rays, and one constant for both
    overcharged a schedule that activates many shadow-only domains. ``shade_ray_s`` is the
    schedule's shading time (``shade_s``) per radiance query and ``trace_ray_s`` the rest;
    if noise leaves no rest, the radiance cost is split in the proportion of shading time to
    all ``process`` time instead. ``camera_ray_s`` is the median over the tiles of making
    their camera rays, per ray.
    """
    radiance, shadow, seconds = median_calls(tiles)
    design = np.stack([radiance > 0, radiance == 0, radiance, shadow], axis=1).astype(np.float64)
    fit, *_ = np.linalg.lstsq(design, seconds, rcond=None)
    activation_s, shadow_activation_s, per_radiance, shadow_ray_s = np.maximum(fit, 0.0)
    if per_radiance == 0.0:  # no spread in the calls' sizes: the mean cost of a query
        per_radiance = float(seconds.sum() / max(radiance.sum() + shadow.sum(), 1.0))
    all_radiance = sum(r for tile in tiles for _, r, _, _ in tile.calls)
    all_shade = sum(tile.shade_s for tile in tiles)
    shade_ray_s = all_shade / max(all_radiance, 1)
    trace_ray_s = per_radiance - shade_ray_s
    if trace_ray_s <= 0.0:
        share = all_shade / max(sum(t for tile in tiles for *_, t in tile.calls), 1e-12)
        shade_ray_s, trace_ray_s = per_radiance * share, per_radiance * (1.0 - share)
    camera_ray_s = float(np.median([t.camera_s / max(t.paths, 1) for t in tiles]))
    return {"trace_ray_s": float(trace_ray_s), "shade_ray_s": float(shade_ray_s),
            "shadow_ray_s": float(shadow_ray_s), "activation_s": float(activation_s),
            "shadow_activation_s": float(shadow_activation_s), "camera_ray_s": camera_ray_s}


# -- the wire -------------------------------------------------------------------------------
def ray_batch(setup: RenderSetup, n: int) -> dict[str, np.ndarray]:
    """The arrays of a batch of ``n`` radiance rays as ``RayPost.send`` sends them: the camera
    rays of the first ``n`` paths (of as many samples per pixel as it takes), each with its
    empty hit record and its cursor at the first domain it enters, and that domain; ``{}``
    for ``n == 0`` (the empty batch). Colour hit fields as the store has them."""
    if n == 0:
        return {}
    pixels = setup.camera.width * setup.camera.height
    settings = RenderSettings(width=setup.camera.width, height=setup.camera.height,
                              spp=math.ceil(n / pixels))
    ctx = path_context(setup.shading, settings, 0, n, setup.ao_distance)
    rays = radiance_soa(camera_rays(setup.camera, ctx), setup.color_source is not None,
                        **start_cursor(n))
    domain, entry = setup.geometry.next_domain(rays["origin"], rays["direction"], rays["at_t"],
                                               rays["at_d"], np.full(n, np.inf, np.float32))
    rays["at_t"], rays["at_d"] = entry, domain
    return {"domain": domain, **rays.fields}


def _close(*sockets: zmq.Socket) -> None:
    for sock in sockets:
        sock.close(linger=0)


def echo_peer(endpoint: str, idle_timeout_s: float) -> None:
    """The peer process: say hello to ``endpoint`` (the caller's ROUTER) with its own
    ROUTER's endpoint, then decode each message that comes, and send it back re-encoded,
    until a ``"stop"`` message or ``idle_timeout_s`` seconds without one (the caller gone)."""
    ctx = zmq.Context()
    router, dealer = ctx.socket(zmq.ROUTER), ctx.socket(zmq.DEALER)
    try:
        port = router.bind_to_random_port("tcp://127.0.0.1")
        dealer.connect(endpoint)
        dealer.send_multipart(encode("hello", {}, {"endpoint": f"tcp://127.0.0.1:{port}"}))
        while router.poll(int(idle_timeout_s * 1000)):
            message = decode(router.recv_multipart(copy=False)[1:])
            if message.kind == "stop":
                return
            dealer.send_multipart(encode(message.kind, message.arrays, message.meta),
                                  copy=False)
    finally:
        _close(router, dealer)
        ctx.term()


class Peer:
    """A peer process (``echo_peer``, started with the spawn method) and this side's sockets:
    a ROUTER it sends to and a DEALER to its ROUTER, as two nodes are connected. A context
    manager: leaving it stops the peer (terminated if it does not stop at once)."""

    def __init__(self):
        self.ctx = zmq.Context()
        self.router = self.ctx.socket(zmq.ROUTER)
        self.dealer = self.ctx.socket(zmq.DEALER)
        self.process = None

    def __enter__(self) -> Peer:
        try:
            port = self.router.bind_to_random_port("tcp://127.0.0.1")
            spawn = multiprocessing.get_context("spawn")
            self.process = spawn.Process(target=echo_peer, daemon=True, name="vastray-calibrate-peer",
                                         args=(f"tcp://127.0.0.1:{port}", PEER_REPLY_TIMEOUT_S * 3))
            self.process.start()
            hello = self.receive(PEER_START_TIMEOUT_S, "say hello", SPAWN_HINT)
            self.dealer.connect(hello.meta["endpoint"])
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def receive(self, timeout_s: float, what: str, hint: str = "") -> Message:
        """The next message to this side's ROUTER, decoded; ``CalibrationError`` (saying
        the peer did not ``what``, then ``hint``) if none comes within ``timeout_s`` seconds
        or the peer process has died."""
        deadline = time.monotonic() + timeout_s
        while not self.router.poll(100):
            if not self.process.is_alive():
                raise CalibrationError(f"the calibration peer process exited (status "
                                       f"{self.process.exitcode}) before it could {what}{hint}")
            if time.monotonic() > deadline:
                raise CalibrationError(f"the calibration peer process did not {what} within "
                                       f"{timeout_s:g} s")
        return decode(self.router.recv_multipart(copy=False)[1:])

    def round_trip(self, frames: list) -> float:
        """Seconds from sending ``frames`` to having decoded their echo."""
        start = time.perf_counter()
        self.dealer.send_multipart(frames, copy=False)
        self.receive(PEER_REPLY_TIMEOUT_S, "answer a ray batch")
        return time.perf_counter() - start

    def __exit__(self, *exc) -> None:
        try:
            if self.process is not None and self.process.is_alive():
                self.dealer.send_multipart(encode("stop", {}), flags=zmq.NOBLOCK)
        except zmq.ZMQError:
            pass
        finally:
            self.router.close(linger=0)
            self.dealer.close(linger=1000)  # time for the stop to leave
            self.ctx.term()
            self._stop_process()

    def _stop_process(self) -> None:
        if self.process is None or self.process.pid is None:
            return
        self.process.join(2.0)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(2.0)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(2.0)
        self.process.close()


def time_wire(setup: RenderSetup, effort: Effort,
              progress: Callable[[float, str], None]) -> list[tuple[int, float]]:
    """Ping-pong of ray batches of ``WIRE_RAYS`` rays with a peer process: for each size,
    ``effort.wire_s`` seconds (at least ``effort.min_pings`` round trips) after two untimed.

    Returns
    -------
    [(bytes, one-way seconds), ...]: per size the message's bytes (header and frames) and the
    median round trip halved (each way: encode, send, receive, decode).
    """
    progress(0.0, "starting the peer process")
    out = []
    with Peer() as peer:
        for i, n in enumerate(WIRE_RAYS):
            progress((i + 0.5) / len(WIRE_RAYS), f"ray batches of {n} rays")
            frames = encode(protocol.RAYS, ray_batch(setup, n),
                            {"queue": "radiance", "rank": 0, "tile": 0})
            nbytes = frames_nbytes(frames)
            for _ in range(2):  # connections made, buffers allocated
                peer.round_trip(frames)
            trips = []
            start = time.perf_counter()
            while time.perf_counter() - start < effort.wire_s or len(trips) < effort.min_pings:
                trips.append(peer.round_trip(frames))
            out.append((nbytes, float(np.median(trips)) / 2))
    progress(1.0, "ray batches done")
    return out


#: Rays in each batch the nodes' messaging is measured with (``time_node_messages``).
NODE_MESSAGE_RAYS = 100


def time_node_messages(setup: RenderSetup, effort: Effort) -> float:
    """CPU seconds one ray batch costs the two processes it passes between when nodes send
    it: two of the nodes' own management actors (``ManagementActor``) in this process (on
    uvloop, with a join secret, as ``vastray node`` runs them), one sending batches of
    ``NODE_MESSAGE_RAYS`` rays to the other over loopback TCP, each received (checked,
    decoded, put in its mailbox, taken by a waiting ``receive``) before the next is sent,
    for ``effort.wire_s`` seconds after ten untimed. The process's CPU time covers both actors,
    both event loops' turns and ZeroMQ's I/O threads.

    Returns
    -------
    float
        CPU seconds per batch (the median of ten runs' means).
    """
    import secrets

    import zmq.asyncio

    from vastray.actors.management import ManagementActor
    from vastray.transport.security import Credentials, Gate

    arrays = ray_batch(setup, NODE_MESSAGE_RAYS)
    # a node sends only rays bound for a domain (a camera ray that enters none is not sent)
    arrays["domain"] = np.maximum(arrays["domain"], 0)
    n_domains = setup.geometry.n_domains

    async def run() -> float:
        ctx = zmq.asyncio.Context()
        credentials = Credentials(secret=secrets.token_bytes(16))
        gate = Gate(ctx, secret=credentials.secret, what="the calibration")
        actors = [ManagementActor(ctx, "tcp://127.0.0.1:9", "127.0.0.1", "127.0.0.1",
                                  PEER_REPLY_TIMEOUT_S, credentials, gate) for _ in range(2)]
        shared = secrets.token_bytes(16)  # the token of the pair (0, 1)
        tokens = [[secrets.token_bytes(16), shared], [shared, secrets.token_bytes(16)]]
        try:
            for rank, actor in enumerate(actors):
                actor.join(secrets.token_bytes(16), {
                    "size": 2, "rank": rank, "endpoints": [a.endpoint for a in actors],
                    "peer_tokens": tokens[rank], "domains": n_domains, "units": [0]})
            frames = encode(protocol.RAYS, arrays, {"queue": "radiance", "rank": 0, "tile": 0})

            async def batches(count: int) -> None:
                for _ in range(count):
                    await actors[0].to_peer(1, frames)
                    await actors[1].receive(protocol.RAYS, "a calibration ray batch")

            await batches(10)  # connections made, buffers allocated
            means = []
            per_run = effort.wire_s / 10
            for _ in range(10):
                count, cpu, start = 0, time.process_time(), time.perf_counter()
                while time.perf_counter() - start < per_run or count < effort.min_pings:
                    await batches(10)
                    count += 10
                means.append((time.process_time() - cpu) / count)
            return float(np.median(means))
        finally:
            for actor in actors:
                actor.close()
            gate.close()
            ctx.destroy(linger=0)

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        return runner.run(run())


#: Effort of ``MachineProbe``: a fraction of a second a probe.
PROBE = Effort(load_s=0.0, min_loads=0, trace_s=0.0, min_tiles=1, spp=1, wire_s=0.1,
               min_pings=4)


class MachineProbe:
    """What moves most with this machine's moment, measured again in a couple of seconds:
    ``receive_s`` and ``offload_s`` as ``calibrate`` measures them (two management actors
    exchanging batches; tiles traced through a worker thread), and the throughput with 1 to
    4 x ``cores`` busy processes (``warmup``'s warm processes rendering the calibration tile,
    alone and ``cores``, 2 x and 4 x ``cores`` side by side, as the quick calibration does:
    more than ``cores`` run ``cores`` at a time, each slower by switching). On the 2-core machine
    the same message measurement gave 0.55 ms a batch and, a minute later, 1.10 ms; two
    calibrations back to back an ``offload_s`` of 1.50 and 0.26 ms; and the throughput of 2
    processes 1.61 at one calibration and 2.0 at another, the validation's 2-node rows
    over-predicted by up to 38 % after the first. A validation that compares real runs with
    simulations minutes apart takes them beside each real run (``bench/simulate.py``).

    Beyond ``cores`` processes the probe measures too (``beyond_cores``, the default): until
    session 73 it kept the calibration's ratio to its own at ``cores`` (``oversubscribed``,
    still what ``beyond_cores=False`` does), and a quick calibration's three rounds gave 8
    processes on 2 cores 1.00 of 2 in one calibration and 0.65 in the next, 40 minutes apart
    (twelve rounds in between: 0.71-0.89): every 8-node validation row moved with it, rm
    128³'s by +30 to +56 % after the second (session 73). The probe's ``WINDOW`` latest rounds
    around the rows they charge follow the machine instead, for about 2 s more a probe.

    Each ``now`` measures each of them once more and charges the medians of the latest
    ``WINDOW`` measurements (``SEED_ROUNDS`` of each taken as the probe starts). One message
    measurement is noise too: one validation's 21 probes gave ``receive_s`` 0.21-1.00 ms, and
    the row charged the 1.00 (the scan's 8-node ``dynamic``, a message-heavy one) was
    over-predicted by 85 % while its 2-node row, probed alike, was within 3 % (session 33).
    The throughput: each ``now`` adds one round of renders to those of the probe so far and
    charges the throughput of the latest ``WINDOW``. One round is noise: twelve in a row here
    gave 1.68-2.00 for 2 processes (median 1.97), the lone render's own CPU moving 0.55-0.82 s
    from one round to the next as the host's speed drifts, and the 8-node validation rows
    charged at the 1.48-1.62 of a single round over-predicted by 27-62 % (session 32). How
    much busy processes slow each other is the machine's; what others take of it at the
    moment is ``sim.steal.Contention``'s, around each real run. Processes of others running
    during the probe's rounds (``others``, seen as each round starts) slowed its processes
    too, so the throughput is read at the count in all (``warmup.beside_others``), where the
    simulator runs them beside its nodes again.

    Parameters
    ----------
    store_path : the calibration store (its tile and ray batches are the ones measured).
    cores : the cores the throughput is measured for (default: ``usable_cores``).
    beyond_cores : also measure 2 and 4 x ``cores`` processes (default); False: the
        calibration's ratio beyond ``cores`` (``oversubscribed``).
    """

    #: Rounds of side-by-side renders a probe measures as it starts (about 2.7 s each: 1, 2,
    #: 4 and 8 processes on 2 cores).
    SEED_ROUNDS = 2
    #: The latest rounds ``now`` charges the medians of: enough that one round's noise moves
    #: them little (twelve rounds in a row gave 1.68-2.00 for 2 processes), few enough to
    #: follow the host over minutes (one validation's first 8 rounds gave 1.67, taken while
    #: its calibration measured traces at twice their usual cost, and kept for every later
    #: row: the scan's sort-first rows then over-predicted by 30-61 %).
    WINDOW = 6

    def __init__(self, store_path: str | os.PathLike, cores: int | None = None,
                 beyond_cores: bool = True):
        store = Store(store_path)
        # a quarter of the calibration tile: as many activations, a hand-off each
        self.settings = calibration_settings(True, spp=1, width=32, height=24)
        self.setup = RenderSetup.of(store, SceneConfig(text=""), self.settings)
        self.cache = resident_cache(store, self.setup.keep)
        self.cores = cores or usable_cores()
        # contention depends on how many run at once, min(k, cores), and on switching among
        # more processes than cores: the quick calibration's counts
        self.counts = (throughput_counts(True, self.cores) if beyond_cores
                       else sorted({1, self.cores}))
        try:
            self.processes = WarmProcesses(str(store_path), True, self.counts[-1], tile=True)
            #: busy processes of others seen as each round of renders started (``now``
            #: charges the throughput as measured beside them: ``beside_others``)
            self.others = [others_running()]
            #: every round of side-by-side renders measured so far (``now`` adds one)
            self.rounds = measure_rounds(self.processes, self.counts, self.SEED_ROUNDS)
            #: the latest measurements of a batch's messaging (s) and of a hand-off (s)
            self.messages: list[float] = []
            self.offloads: list[float] = []
            for _ in range(self.SEED_ROUNDS):
                self._measure_messaging()
        except BaseException:
            if hasattr(self, "processes"):
                self.processes.close()
            self.cache.close()
            raise

    def now(self, costs: CostModel) -> CostModel:
        """``costs`` with ``receive_s``, ``offload_s`` and ``throughput`` as this machine pays
        them now (``receive_s`` beyond ``costs.latency_s``, as ``calibrate`` splits them)."""
        self._measure_messaging()
        self.others = (self.others + [others_running()])[-self.WINDOW:]
        self.rounds = (self.rounds + measure_rounds(self.processes, self.counts, 1)
                       )[-self.WINDOW:]
        # measured to 4 x cores (``beyond_cores``) it stays as measured; else extended
        throughput = oversubscribed(interpolated(throughput_of(self.rounds, self.cores)),
                                    costs.throughput, 4 * self.cores)
        throughput = beside_others(throughput, float(np.median(self.others)), self.cores)
        node_messages = float(np.median(self.messages))
        return replace(costs, receive_s=max(0.0, node_messages - costs.latency_s),
                       offload_s=(float(np.median(self.offloads)) if self.offloads
                                  else costs.offload_s),
                       throughput=throughput)

    def _measure_messaging(self) -> None:
        """Measure a batch's messaging and a hand-off once more, keeping the latest
        ``WINDOW`` of each."""
        self.messages = (self.messages + [time_node_messages(self.setup, PROBE)]
                         )[-self.WINDOW:]
        offload = time_offload(self.setup, self.settings, self.cache, tiles=1)
        if offload:
            self.offloads = (self.offloads + [float(np.median(offload))])[-self.WINDOW:]

    def close(self) -> None:
        self.processes.close()
        self.cache.close()


def oversubscribed(measured: tuple[float, ...], calibrated: tuple[float, ...],
                   count: int) -> tuple[float, ...]:
    """``measured`` (the throughput of 1 .. ``cores`` busy processes, measured now) extended
    to ``count`` processes. Beyond the cores, ``cores`` run at a time, each slower by what
    the calibration measured there (``calibrated``: its throughput beyond the cores over
    its own at the cores: switching among more processes than cores costs each of them
    CPU, 1.91 and 1.82 for 3 and 4 processes on 2 cores against 2.00); where the
    calibration has no such count, as fast as at the cores. A ``measured`` already
    ``count`` long (``MachineProbe(beyond_cores=True)``) is returned as it is.

    Parameters
    ----------
    measured : (cores,) aggregate throughput now, in single-process speeds.
    calibrated : (K,) the calibration's, K >= cores for its ratios to count.
    count : the length of the result.
    """
    cores = len(measured)
    out = list(measured)
    for k in range(cores + 1, count + 1):
        ratio = (calibrated[k - 1] / calibrated[cores - 1]
                 if len(calibrated) >= k and calibrated[cores - 1] > 0 else 1.0)
        out.append(measured[-1] * min(1.0, ratio))
    return tuple(out)


def wire_costs(samples: list[tuple[int, float]]) -> tuple[float, float]:
    """(latency_s, byte_s) of ``one_way = latency_s + bytes * byte_s``.

    Least squares weighted by 1 / one_way**2 (relative residuals): the sizes span five
    orders of magnitude, and unweighted the largest batch alone would set the intercept.
    If noise leaves the intercept <= 0, latency_s is the smallest message's time; a slope
    <= 0, the difference of the largest and smallest over their bytes.
    """
    nbytes = np.array([b for b, _ in samples], np.float64)
    seconds = np.array([s for _, s in samples], np.float64)
    latency_s, byte_s = fit_line(nbytes, seconds, 1.0 / seconds ** 2)
    small, large = int(np.argmin(nbytes)), int(np.argmax(nbytes))
    if latency_s <= 0.0:
        latency_s = float(seconds[small])
    if byte_s <= 0.0:
        byte_s = max(float((seconds[large] - seconds[small]) / max(nbytes[large] - nbytes[small], 1)),
                     1e-15)
    return latency_s, byte_s


# -- reductions -----------------------------------------------------------------------------
def cpu_model() -> str | None:
    """The first ``model name`` of /proc/cpuinfo, else ``platform.processor()`` (None if
    neither says)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and ":" in line:
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def usable_cores() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def machine_info(**extra) -> dict:
    """What the constants were measured on: host name, CPU model, platform, Python, the
    vastray version and the date (UTC, ISO 8601), plus ``extra``."""
    return {"hostname": socket.gethostname(), "cpu": cpu_model(),
            "platform": platform.platform(), "python": sys.version.split()[0],
            "vastray": package_version(),
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            **extra}
