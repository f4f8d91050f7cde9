"""The single-process reference renderer: batches of paths through the domain tracer to a film."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from vastray.processes import peak_rss_bytes
from vastray.render import kernels
from vastray.render.camera import Camera, start_distance
from vastray.render.colormaps import scalar_map
from vastray.render.film import Film
from vastray.render.integrators import (
    PathContext,
    RenderSettings,
    Shading,
    camera_pad,
    trace_paths,
)
from vastray.render.lights import QuadLight, check_power, in_frame
from vastray.render.progress import RenderBar
from vastray.render.progressive import Progression
from vastray.render.scene_config import SceneConfig
from vastray.render.seen_pixels import occupied_boxes, pixel_cover
from vastray.render.tracer import DomainTracer
from vastray.scene.bvh_choice import fast_builds
from vastray.scene.cache import DomainCache
from vastray.scene.cpus import available_cpus
from vastray.scene.store import Store

log = logging.getLogger(__name__)


@dataclass
class RenderResult:
    """A finished render: the film and what it cost."""

    film: Film
    camera: Camera
    seconds: dict = field(default_factory=dict)
    counters: dict = field(default_factory=dict)
    #: ``Progression.report()`` of a render in passes: why it stopped and the error series.
    progress: dict | None = None


def shading_inputs(store: Store, config: SceneConfig, integrator: str):
    """What shading needs from the store: leaves out attributes the scene does not use.

    Returns
    -------
    shading : Shading
    keep : attributes each loaded domain must keep
    color_source : "colors", "scalars" or None
    """
    color_source = "colors" if store.has_colors else "scalars" if store.has_scalars else None
    lights = [] if integrator == "ao" else in_frame(config.resolve_lights(), store.origin)
    check_power(lights, config.source or "scene")
    materials = config.material_table(store.objects)
    keep = set()
    if color_source:
        keep.add(color_source)
    if integrator == "pt" and len(materials) > 1:
        keep.add("objects")
    return Shading(lights, materials, color_source is not None), frozenset(keep), color_source


def quad_corners(lights: list) -> np.ndarray:
    """(q, 4, 3) float64 the corners of the quad lights among ``lights``."""
    quads = [light for light in lights if isinstance(light, QuadLight)]
    return np.array([light.corner + np.array([[0, 0], [1, 0], [0, 1], [1, 1]]) @ np.stack(
        [light.edge1, light.edge2]) for light in quads], np.float64).reshape(len(quads), 4, 3)


def with_camera_clip(shading: Shading, store: Store, camera: Camera) -> Shading:
    """``shading`` with the box camera rays from far away start near (``Shading.clip``): the
    store's bounds and its quad lights, in the store's frame."""
    points = np.concatenate([store.bounds, *quad_corners(shading.lights)])
    clip = np.stack([points.min(axis=0), points.max(axis=0)])
    return dataclasses.replace(shading, clip=clip, eye=np.asarray(camera.position, np.float64))


def with_seen_pixels(shading: Shading, store: Store, camera: Camera) -> Shading:
    """``shading`` (with its ``clip``) with the pixels whose camera rays can meet something
    (``Shading.seen_pixels``): the image of the store's occupied cells and of its quad
    lights (``render.seen_pixels``). The one-process tracer and the schedules that queue
    camera rays through ``integrators.launched_camera_rays`` read them (``spec-insitu`` makes
    every path's: its buffers cover them all). Without a ``clip``, every pixel."""
    if shading.clip is None:
        return shading
    lo, hi = occupied_boxes(store)
    corners = quad_corners(shading.lights)
    lo = np.concatenate([lo, corners.min(axis=1)])
    hi = np.concatenate([hi, corners.max(axis=1)])
    advance = start_distance(shading.eye, shading.clip)
    seen = pixel_cover(camera, lo, hi, camera_pad(shading, advance))
    return dataclasses.replace(shading, seen_pixels=seen)


def store_camera(config: SceneConfig, store: Store, width: int, height: int) -> Camera:
    """The configured camera (defaults framing the scene) in the store's frame, where rays
    are traced: resolved in world coordinates, then moved by ``-store.origin``."""
    lo, hi = store.world_bounds
    return config.resolve_camera(lo, hi, width, height).in_frame(store.origin)


def path_context(shading: Shading, settings: RenderSettings, first: int, stop: int,
                 ao_distance: float) -> PathContext:
    """The paths ``first <= i < stop`` of the pass ``settings.samples`` = (s0, s1): path ``i``
    is pixel ``i // (s1 - s0)``, sample ``s0 + i % (s1 - s0)``. A pass adds its samples to
    every pixel; without a window (the whole of ``spp``) it is today's pixel-major order."""
    s0, s1 = settings.samples
    n = max(stop - first, 0)
    pixel, sample = np.empty(n, np.uint32), np.empty(n, np.uint32)
    kernels.path_keys(int(first), int(s0), int(s1 - s0), pixel, sample)
    return PathContext(shading, settings, pixel, sample, ao_distance)


def paths_context(shading: Shading, settings: RenderSettings, ids: np.ndarray,
                  ao_distance: float) -> PathContext:
    """The paths ``ids`` ((n,) int64, ascending) of the pass ``settings.samples``, numbered
    as ``path_context`` numbers them; a run of consecutive ids is ``path_context``'s."""
    if len(ids) == 0 or int(ids[-1]) - int(ids[0]) + 1 == len(ids):
        first = int(ids[0]) if len(ids) else 0
        return path_context(shading, settings, first, first + len(ids), ao_distance)
    s0, s1 = settings.samples
    pixel = (ids // (s1 - s0)).astype(np.uint32)
    sample = (s0 + ids % (s1 - s0)).astype(np.uint32)
    return PathContext(shading, settings, pixel, sample, ao_distance)


def run_passes(trace_pass, settings: RenderSettings, progression: Progression | None,
               bar) -> Film:
    """The image's film: ``trace_pass(window, bar) -> Film`` for each pass ``progression``
    asks for (merged there), or once over ``settings`` as they are without one."""
    if progression is None:
        return trace_pass(settings, bar)
    while (step := progression.next_pass()) is not None:
        index, first, stop = step
        progression.add_pass(index, trace_pass(settings.window(first, stop), bar))
    if progression.stopped_by != "spp":  # the bar ends where the render does
        bar.total = bar.n
    return progression.film


def default_ao_distance(store: Store) -> float:
    """A tenth of the scene's diagonal."""
    return 0.1 * float(np.linalg.norm(store.bounds[1] - store.bounds[0])) or 1.0


def _bounded_map(fn, items, workers: int):
    """``map(fn, items)`` on ``workers`` threads, in order, with at most 2 x workers in flight."""
    if workers <= 1:
        yield from map(fn, items)
        return
    with ThreadPoolExecutor(workers) as pool:
        pending = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) >= 2 * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


class FrameCache:
    """One domain cache kept over the frames of a run, so that an animation loads a domain
    once while the cache can hold it, not once per frame; each frame's counters are its own.

    Parameters
    ----------
    store, capacity, load_bandwidth : as ``render``'s (capacity None: every domain).
    max_bytes : most bytes of domains the cache holds (``DomainCache``'s; None: no bound but
        ``capacity``).
    """

    def __init__(self, store: Store, capacity: int | None = None,
                 load_bandwidth: float | None = None, max_bytes: int | None = None):
        self.store, self.load_bandwidth, self.max_bytes = store, load_bandwidth, max_bytes
        self.capacity = capacity or max(len(store.domains), 1)
        self.cache: DomainCache | None = None

    def for_frame(self, config: SceneConfig, settings: RenderSettings) -> DomainCache:
        """The cache for the next frame, its counters at zero (a new cache where this
        frame's shading needs attributes the kept domains dropped, or another BVH)."""
        keep = shading_inputs(self.store, config, settings.integrator)[1]
        fast = fast_builds(settings.bvh, self.store.n_triangles)
        if (self.cache is None or not keep <= self.cache.keep
                or self.cache.fast_builds != fast):
            self.cache = DomainCache(self.store, self.capacity, keep,
                                     load_bandwidth=self.load_bandwidth, fast_builds=fast,
                                     max_bytes=self.max_bytes)
        self.cache.count_afresh()
        return self.cache


def render(store: Store, config: SceneConfig, settings: RenderSettings,
           cache_capacity: int | None = None, threads: int | None = None,
           progress: bool = True, drop_page_cache: bool = False,
           record_rays: list | None = None, two_level: bool = True,
           cache: DomainCache | None = None, load_bandwidth: float | None = None,
           progression: Progression | None = None) -> RenderResult:
    """Render a store with one process and an LRU domain cache.

    Parameters
    ----------
    store : the domains.
    config : camera, lights and materials.
    settings : image size, integrator and sampling.
    cache_capacity : most domains resident (default: all).
    threads : Embree query threads (default: ``scene.cpus.available_cpus``).
    progress : show a progress bar on stderr for renders longer than two seconds.
    drop_page_cache : make every domain load a real disk read.
    record_rays : if a list, every query batch is appended to it as (kind, origins,
        directions, t_max): closest-hit queries of ``"camera"`` and ``"bounce"`` rays (t_max
        None: unbounded) and ``"occluded"`` queries bounded by t_max, exactly what was asked
        of the domains.
    two_level : with every domain resident, trace through one top-level Embree scene of
        instances (``DomainTracer``); False: domain by domain (the same image, bit for bit).
    cache : a domain cache of ``store`` to use (e.g. with every domain already loaded, so
        benchmarks time no loads), building the BVH ``settings.bvh`` asks for; its capacity
        replaces ``cache_capacity``, and the
        ``load`` seconds and cache counters reported are its totals so far.
    load_bandwidth : bytes per second to emulate network storage with: every domain load
        takes at least its size over this (None: the disk's own speed; ignored with
        ``cache``).
    progression : render in the sample-major passes it asks for, until its rules stop it;
        the result's film is its film (None: the whole of ``settings.spp`` at once).
    """
    if settings.integrator not in ("ao", "pt"):
        raise ValueError(f"unknown integrator {settings.integrator!r}")
    start = time.perf_counter()
    shading, keep, color_source = shading_inputs(store, config, settings.integrator)
    fast = fast_builds(settings.bvh, store.n_triangles)
    if cache is None:
        capacity = cache_capacity or max(len(store.domains), 1)
        cache = DomainCache(store, capacity, keep, drop_page_cache=drop_page_cache,
                            load_bandwidth=load_bandwidth, fast_builds=fast)
    elif cache.fast_builds != fast:
        raise ValueError(f"the cache builds the {'fast' if cache.fast_builds else 'quality'} "
                         f"BVH; these settings ask for --bvh {settings.bvh}")
    capacity = cache.capacity
    threads = threads or available_cpus()
    # With every domain resident, whole batches run on one worker per thread, each tracing its
    # Embree queries on its own thread (serial kernels, no GIL, side by side): one worker's
    # Python and numpy work overlaps the others' queries. A pass of fewer batches than twice
    # the workers is cut finer so that every worker has some. (Measured on bench/peers.py, 2
    # cores: 0.43 s with threads + 1 workers whose queries took turns on both threads, one
    # launch at a time; 0.33 s so.) A bounded cache is shared by one worker, which would
    # otherwise thrash it; that worker splits its Embree queries over the threads instead.
    all_fit = capacity >= len(store.domains)
    workers = threads if all_fit and threads > 1 else 1
    tracer = DomainTracer(store, cache, color_source, threads=1 if workers > 1 else threads,
                          two_level=two_level,
                          scalars=scalar_map(store.scalar_range, settings.colormap,
                                             settings.color_range))
    tracer.record = record_rays
    camera = store_camera(config, store, settings.width, settings.height)
    shading = with_seen_pixels(with_camera_clip(shading, store, camera), store, camera)
    tracer.origin_bound = max(tracer.origin_bound, float(np.abs(camera.position).max()))
    ao_distance = settings.ao_distance or default_ao_distance(store)

    def trace_pass(window: RenderSettings, bar) -> Film:
        """The film of one pass (``window.samples``), batch after batch in path order."""
        total = window.paths
        batch = max(1, window.batch_size)
        if workers > 1:
            batch = min(batch, -(-total // (2 * workers)))
        film = Film(window.width, window.height)

        def trace_batch(first: int):
            ctx = path_context(shading, window, first, min(first + batch, total), ao_distance)
            return ctx, trace_paths(tracer, camera, ctx)

        for ctx, paths in _bounded_map(trace_batch, range(0, total, batch), workers):
            film.add_paths(ctx.pixel, ctx.sample, paths)
            bar.update(len(ctx.pixel))
        return film

    try:
        with RenderBar(total=settings.paths, unit="path", unit_scale=True, delay=2.0,
                       disable=not progress, desc="render", leave=False) as bar:
            film = run_passes(trace_pass, settings, progression, bar)
    finally:
        tracer.close()
    wall = time.perf_counter() - start
    stats = cache.stats
    counters = {
        "domains": len(store.domains),
        "domains_entered": len(tracer.stats.domains_entered),
        "rays": dict(tracer.stats.rays, total=sum(tracer.stats.rays.values())),
        "camera_rays_escaped": tracer.stats.camera_escaped,
        "ray_domain_tests": tracer.stats.ray_domain_tests,
        "cache_capacity": capacity,
        "cache_bytes": cache.max_bytes,
        "threads": threads,
        "render_workers": workers,
        "load_bandwidth_mb_s": None if cache.load_bandwidth is None else cache.load_bandwidth / 1e6,
        **stats.as_dict(),
        "peak_rss_bytes": peak_rss_bytes(),
    }
    seconds = {
        "total": round(wall, 4),
        "load": round(stats.load_seconds, 4),
        "trace_and_shade": round(wall - stats.load_seconds, 4),
    }
    return RenderResult(film, camera, seconds, counters)
