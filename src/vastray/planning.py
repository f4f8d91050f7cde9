"""A render checked and planned, before the first ray: the store and scene opened, the
scheduler resolved, the memory checked and the job's runtime picked (``plan_render``), for
``vastray render`` and the Python API alike."""

from __future__ import annotations

import functools
import logging
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import DEFAULT_PORTAL_RESOLUTION, JobOptions, default_tile
from vastray.actors.local import render_out_of_core
from vastray.preflight import (
    MemoryEstimate,
    RenderMemory,
    cache_room,
    check_limit_fits_machine,
    check_memory,
    check_owned_fit,
    crossings_from_surface,
    domain_build_bytes,
    domain_footprints,
    estimate_memory,
    fitting_count,
    gigabytes,
    reference_paths_in_flight,
    smallest_limit,
    speculative_copies,
)
from vastray.render.colormaps import Legend, colormap_lut, coloured_by_scalars, legend_for
from vastray.render.driver import FrameCache, RenderResult, render
from vastray.render.imageio import image_error, read_image
from vastray.render.integrators import RenderSettings
from vastray.render.lights import shadow_rays
from vastray.render.progressive import DEFAULT_MAX_PASS_SPP, Progression, StopRules
from vastray.render.scene_camera import with_camera
from vastray.render.scene_config import SceneConfig, load_scene_config
from vastray.report import build_report, count_overflow
from vastray.request import (
    DEFAULT_BATCH_SIZE,
    DEFAULT_PORTAL_INTERVAL,
    DEFAULT_PORTAL_THRESHOLD,
    DEFAULT_SAMPLES_IN_FLIGHT,
    RenderRequest,
    resolve_cache,
)
from vastray.scene.bvh_choice import describe as describe_bvh
from vastray.scene.bvh_choice import fast_builds
from vastray.scene.cpus import available_cpus
from vastray.scene.errors import InputError
from vastray.scene.extent import check_extent
from vastray.scene.store import Store
from vastray.schedule.registry import Option, Runtime, resolve, spec
from vastray.transport.keys import load_coordinator_keys

log = logging.getLogger(__name__)


@dataclass
class RenderPlan:
    """A render checked and ready to run, as ``vastray render`` and ``vastray.render`` (the
    Python API) both prepare it with ``plan_render``.

    Attributes
    ----------
    store_path : the store's folder (the built-in scene's, without a store).
    store : the opened store.
    config : camera, lights and materials.
    settings : image size, integrator and sampling (defaults filled in).
    scheduler : as resolved from ``auto``.
    options : the job's options, as the schedulers receive them.
    report_options : the run's switches, as its report records them
        (``RenderRequest.report_options``).
    reference : (H, W, 3) image to measure the error against, or None.
    render_one : ``render_one(config, settings) -> RenderResult`` (``_renderer``).
    legend : the colour bar PNGs get, or None (``png_legend``).
    memory : the peak memory the preflight expects (``preflight.RenderMemory``).
    request : the request planned, its defaults filled in (``RenderRequest.resolved``).
    """

    store_path: Path
    store: Store
    config: SceneConfig
    settings: RenderSettings
    scheduler: str
    options: JobOptions
    report_options: dict
    reference: np.ndarray | None
    render_one: Callable[..., RenderResult]
    legend: Legend | None = None
    rules: StopRules | None = None
    memory: RenderMemory | None = None
    request: RenderRequest | None = None

    def progression(self, reference: np.ndarray | None = None,
                    resumed=None) -> Progression:
        """A fresh ``Progression`` of one image with the plan's stopping rules, measured
        against ``reference`` (default: the plan's)."""
        return Progression(self.settings.width, self.settings.height,
                           self.rules or StopRules(self.settings.spp),
                           self.reference if reference is None else reference,
                           resumed=resumed)


def plan_render(request: RenderRequest, *, animating: bool = False,
                launched: dict | None = None, store: Store | None = None) -> RenderPlan:
    """Open the store and scene, refuse what cannot work, and pick the scheduler and the
    job's options: everything before the first ray, for ``request`` with its defaults filled
    in (``RenderRequest.resolved``).

    Parameters
    ----------
    animating : an animation checks the camera (and reference) of each of its frames.
    launched : node processes started elsewhere (``vastray launch``).
    store : ``request.store`` already opened.

    Raises
    ------
    InputError
        Naming the file or option and the problem.
    """
    request = request.resolved()
    if request.store is None:
        from vastray.default_scene import default_scene_config, default_store

        store_path = default_store(quiet=request.quiet)
        config = load_scene_config(request.scene) if request.scene else default_scene_config()
    else:
        store_path = Path(request.store)
        config = load_scene_config(request.scene)
    store = Store(store_path) if store is None else store
    check_extent(store.bounds, store.path, "partition it again")
    if request.camera is not None:
        config = with_camera(config, request.camera)
    config.check_objects(store.objects)
    legend = png_legend(request, store)
    request.refuse_for_lights(config.resolve_lights())
    if not animating:  # an animation checks the camera of each of its frames
        config.resolve_camera(*store.world_bounds, request.width, request.height)
    reference = None
    if isinstance(request.reference, np.ndarray):
        reference = request.reference
    elif request.reference and not animating:
        reference = read_image(request.reference)
    settings = RenderSettings(
        width=request.width, height=request.height, spp=request.spp, integrator=request.integrator,
        bounces=request.bounces, shadow_samples=request.shadow_samples, ao_distance=request.ao_distance,
        seed=request.seed, batch_size=request.batch_size or DEFAULT_BATCH_SIZE,
        colormap=request.colormap, bvh=request.bvh,
        color_min=request.color_range[0] if request.color_range else None,
        color_max=request.color_range[1] if request.color_range else None,
    )
    if reference is not None and reference.shape != (request.height, request.width, 3):
        where = request.reference if isinstance(request.reference, str) else "reference"
        raise InputError(where, f"reference is {reference.shape[1]}x{reference.shape[0]}"
                                f", the render is {request.width}x{request.height}")
    cache = resolve_cache(request.cache, len(store.domains))
    scheduler = request.scheduler
    # auto is checked as the in-core reference, then resolved by the cache it leaves
    cache, cache_bytes, memory = _check_render_memory(
        request, config, resolve(scheduler, fits=True), store, cache)
    scheduler = resolve(scheduler, fits=cache is None or cache >= len(store.domains))
    request.refuse_for_nodes(scheduler)
    if request.keys:
        load_coordinator_keys(request.keys)  # a missing or malformed key fails before the render
    if request.nodes:
        scheduler = spec(scheduler).on_nodes  # the in-core reference runs as image
        cores = available_cpus()
        if not request.listen and request.nodes > cores:
            log.warning("--nodes %d on %d core(s): the nodes share them, so more than %d "
                        "nodes render no faster here", request.nodes, cores, cores)
    request.refuse_for_scheduler(scheduler)
    request.refuse_for_passes(animating)
    options = job_options(request, scheduler, cache, cache_bytes)
    rules = StopRules(request.spp, request.time_limit, request.target_error,
                      request.max_pass_spp or DEFAULT_MAX_PASS_SPP,
                      one_pass=renders_in_one_pass(request, options, len(store.domains), reference))
    return RenderPlan(store_path, store, config, settings, scheduler, options,
                      request.report_options(options), reference,
                      _renderer(request, store, store_path, options, launched), legend, rules,
                      memory, request)


def renders_in_one_pass(request: RenderRequest, options: JobOptions, domains: int,
                        reference: np.ndarray | None) -> bool:
    """Whether the render runs as one pass instead of the progressive series (issue 40).

    Out of core (a domain cache smaller than the store), every pass sweeps the domains again
    and reloads what the cache lost since the last: 1.4-4x the loads of one pass on a store
    at a quarter cached. Where nothing reads the image between passes (no reference to
    measure against, no stopping rule, no checkpoint due, no ``--max-pass-spp`` asked for),
    the passes buy nothing, so the render is one pass: its tiles and domain loads are the
    one-pass render's, and its report's series has one point (the final image's error
    estimate). In core, passes cost no loads and stay."""
    watched = (reference is not None or request.time_limit is not None
               or request.target_error is not None or request.checkpoint_every is not None
               or request.checkpoint is not None or request.max_pass_spp is not None
               or request.resume is not None)
    return options.out_of_core(domains) and not watched


def traces_passes_ahead(plan: RenderPlan) -> bool | None:
    """Out of core with passes apart (a reference, a time limit or an error target) in a tile
    schedule (``image``, ``spec-ooc``): whether later passes are traced on the current one's
    domain loads (True; under a time limit, the passes its rule may still grant), or each
    pass sweeps the domains alone (False: ``--passes-alone``). None where neither applies
    (in core, in one pass, unpaced passes kept for checkpoints, which run on from one pass
    into the next, or other schedulers)."""
    request, options = plan.request, plan.options
    apart = (plan.reference is not None or request.time_limit is not None
             or request.target_error is not None)
    if (not options.out_of_core(len(plan.store.domains)) or not apart or plan.rules.one_pass
            or spec(plan.scheduler).runtime is not Runtime.TILES):
        return None
    return options.trace_ahead


def finish_render(plan: RenderPlan, result: RenderResult, where: str | os.PathLike,
                  reference_name: str | None) -> tuple[np.ndarray, dict | None, dict]:
    """A finished render's image ((H, W, 3) as the film holds it), its error against the
    plan's reference (or None) and its report (the dict ``--report`` writes); non-finite
    pixels are counted (and said on stderr, naming ``where``)."""
    image = result.film.image()
    count_overflow(image, result.counters, where)
    error = image_error(image, plan.reference) if plan.reference is not None else None
    report = build_report(
        store=str(plan.store_path),
        settings=dict(asdict(plan.settings),
                      bvh_built=describe_bvh(plan.settings.bvh, plan.store.n_triangles)),
        seconds=result.seconds,
        counters=result.counters, error=error, reference=reference_name,
        scheduler=plan.scheduler, options=plan.report_options, progress=result.progress,
    )
    return image, error, report


def png_legend(request: RenderRequest, store: Store) -> Legend | None:
    """The colour bar PNGs get (None: not coloured by scalars, or not asked for: ``--legend``,
    by default on with ``--colormap``); checks
    the ``--colormap`` name first, so a wrong one is refused before any rendering."""
    if request.colormap is not None:
        colormap_lut(request.colormap)
    by_scalars = coloured_by_scalars(store)
    for option, given in (("--colormap", request.colormap is not None), ("--legend", request.legend),
                          ("--color-range", request.color_range is not None)):
        if given and not by_scalars:
            raise InputError(store.path, f"{option} is for a store coloured by its scalar field;"
                                         " this one has " + ("per-vertex colours" if
                                                             store.has_colors else "no scalars"))
    if request.legend and not request.png_output:
        raise InputError(None, "--legend draws into PNG output only: give --png FILE or a .png "
                               "-o")
    if request.color_range is not None and not request.color_range[0] < request.color_range[1]:
        raise InputError(None, f"--color-range LO HI needs LO < HI, got "
                               f"{request.color_range[0]:g} {request.color_range[1]:g}")
    wanted = request.legend if request.legend is not None else request.colormap is not None
    return legend_for(store, request.colormap, request.color_range and tuple(request.color_range)) \
        if wanted else None


def _renderer(request: RenderRequest, store: Store, store_path: Path, options: JobOptions,
              launched: dict | None) -> Callable[..., RenderResult]:
    """The job's scheduler as ``render_one(config, settings, progression=None) ->
    RenderResult``: the image in the passes ``progression`` asks for (None: in one pass),
    the result's ``progress`` its report. The distributed one also takes
    ``render_distributed``'s ``frames``, ``on_frame`` and ``progression_of``."""
    if request.nodes:
        def render_one(config, settings, progression=None, **frames):
            if progression is not None:
                frames["progression_of"] = lambda frame: progression
            return render_distributed(
                store_path, request.scene, settings, request.nodes, options,
                timeout=request.node_timeout, listen=request.listen,
                keys=load_coordinator_keys(request.keys) if request.keys else None,
                launched=launched,
                progress=not request.quiet, config=config, rendezvous=request.rendezvous,
                heartbeat_timeout=request.heartbeat_timeout, log_dir=node_log_dir(request),
                **frames)
    elif spec(options.scheduler).runtime is Runtime.IN_CORE:
        kept = FrameCache(store, options.cache, options.load_bytes_per_second(),
                          options.cache_bytes)

        def render_one(config, settings, progression=None):
            return _with_progress(render(
                store, config, settings, threads=options.threads, progress=not request.quiet,
                cache=kept.for_frame(config, settings), progression=progression),
                progression)
    else:
        def render_one(config, settings, progression=None):
            return _with_progress(render_out_of_core(
                store, config, settings, options, progress=not request.quiet,
                progression=progression), progression)
    return render_one


def node_log_dir(request: RenderRequest) -> Path | None:
    """Where the logs of the nodes started here are kept: ``--log-dir``, else beside
    ``--report`` (``REPORT.nodes``; the report names it), else nowhere (removed)."""
    if request.log_dir:
        return Path(request.log_dir)
    if request.report and not request.listen:
        return Path(f"{request.report}.nodes")
    return None


def _with_progress(result: RenderResult, progression: Progression | None) -> RenderResult:
    if progression is not None:
        result.progress = progression.report()
    return result


def _check_render_memory(request: RenderRequest, config, scheduler: str, store: Store,
                         cache: int | None) -> tuple[int | None, int | None, RenderMemory]:
    """Refuse up front a render that cannot fit in memory (``preflight.check_memory``: every
    process it starts here, less a margin for the rest of the machine); with
    ``--memory-limit``, first bound each process's domain cache by what its base, film and
    paths in flight leave. Returns the cache in domains, the bytes it may hold (None: no byte
    bound) and the estimates.

    Under a limit the cache is bounded by bytes where the store does not fit: it holds
    whichever domains fit in the room (``DomainCache``'s ``max_bytes``), and its count is only
    the most that could (the smallest first; below the store's, so the render stays out of
    core). A count alone must assume the largest domains: on the 100 M-triangle store (domains
    of 17-216 MB built) 6 GiB held 23 of them, where about 33 of mean size fit the same room."""
    # shadow rays per hit: AO's samples, or per light its samples (area and sky) or one
    rays_per_hit = request.shadow_samples if request.integrator == "ao" else max(sum(
        shadow_rays(light, request.shadow_samples) for light in config.resolve_lights()), 1)
    threads = request.threads or available_cpus()
    total = request.width * request.height * request.spp
    footprints = domain_footprints(store.domains, fast_builds(request.bvh, store.n_triangles))
    # out of core (a limit or a cache below the store) two domains read ahead come on top of
    # the cache's; in core a domain read ahead is one the cache will hold anyway
    building = domain_build_bytes(store.domains, reads_ahead=request.memory_limit is not None
                                  or (cache is not None and cache < len(store.domains)))
    reference = request.reference is not None  # a file name, or an array (the Python API)
    # auto: resolved once the cache is known (spec-ooc when the domains do not all fit)
    resolved_later = spec(request.scheduler).runtime is Runtime.RESOLVED

    @functools.cache
    def copies() -> float:
        """spec-ooc's speculative copies of each shadow ray, beyond the model's own."""
        lo, hi = store.domain_boxes()
        return speculative_copies(
            crossings_from_surface(lo, hi, store.domain_triangles()),
            request.bounces + 1 if request.integrator == "pt" else 1)

    def process(cache: int | None) -> MemoryEstimate:
        """One rendering process (a node with --nodes), its domains left out."""
        if request.nodes:
            tile = request.max_samples_in_flight or default_tile(scheduler, request.nodes)
            return estimate_memory(request.width, request.height, min(tile, total), rays_per_hit,
                                   role="node",
                                   copies=copies() if spec(scheduler).tile_copies else 0.0)
        all_fit = cache is None or cache >= len(footprints)
        if spec(scheduler).runtime is Runtime.IN_CORE and (all_fit or not resolved_later):
            in_flight = reference_paths_in_flight(total, request.batch_size or DEFAULT_BATCH_SIZE,
                                                  threads, all_fit)
        else:  # out of core (auto becomes spec-ooc when the domains do not all fit)
            in_flight = min(request.max_samples_in_flight or DEFAULT_SAMPLES_IN_FLIGHT, total)
            if spec(resolve(request.scheduler, fits=False)).tile_copies:
                return estimate_memory(request.width, request.height, in_flight, rays_per_hit,
                                       reference=reference, copies=copies())
        return estimate_memory(request.width, request.height, in_flight, rays_per_hit,
                               reference=reference)

    cache_bytes = None
    if request.memory_limit is not None:
        if not request.listen:  # the processes it bounds run here
            check_limit_fits_machine(request.memory_limit)
        if spec(scheduler).runtime is Runtime.IN_SITU:  # no cache to bound: every node's own domains must fit
            from vastray.schedule.ownership import insitu_owners

            nodes = request.nodes or 1
            owners = insitu_owners(*store.domain_boxes(), store.domain_triangles(), nodes)
            check_owned_fit(request.memory_limit, process(cache), footprints, owners, nodes,
                            building)
        else:
            limit, size = request.memory_limit, (request.width, request.height)
            smallest = smallest_limit(process(cache), process(len(footprints) - 1),
                                      footprints, building)
            room = cache_room(limit, process(cache), footprints, *size, building, smallest)
            fitting = len(footprints)
            if sum(footprints) > room:  # out of core (auto becomes spec-ooc): bound by bytes
                room = cache_room(limit, process(fitting - 1), footprints, *size, building,
                                  smallest)
                cache_bytes = room  # whichever domains fit; the count: the most that could
                fitting = min(fitting_count(room, footprints, largest_first=False), fitting - 1)
            log.info("--memory-limit leaves %s per process for domains: %s", gigabytes(room),
                     f"up to {fitting} of {len(footprints)}" if cache_bytes else "all of them")
            cache = fitting if cache is None else min(cache, fitting)
    held = sum(sorted(footprints, reverse=True)[:cache or len(footprints)])
    if cache_bytes is not None:
        held = min(held, cache_bytes)
    one = process(cache) + MemoryEstimate(0, 0, 0, domains=held + building)
    coordinator, machine = None, one
    if request.nodes:  # the coordinator, and every node unless they run elsewhere
        coordinator = estimate_memory(request.width, request.height, 0, 0, role="coordinator",
                                      reference=reference)
        machine = coordinator if request.listen else coordinator + one.times(request.nodes)
    check_memory(machine, request.width, request.height)
    return cache, cache_bytes, RenderMemory(one, coordinator, machine)


def job_options(request: RenderRequest, scheduler: str, cache: int | None,
                cache_bytes: int | None = None) -> JobOptions:
    """The job's options from the command line (defaults filled in where the scheduler uses
    them), for ``scheduler`` as resolved from ``auto``, with ``cache`` in domains and
    ``cache_bytes`` the bytes it may hold (None: no byte bound)."""
    job = spec(scheduler)
    tiles = job.runtime is not Runtime.IN_CORE
    in_flight = request.max_samples_in_flight
    if in_flight is None and tiles:
        in_flight = (default_tile(scheduler, request.nodes) if request.nodes
                     else DEFAULT_SAMPLES_IN_FLIGHT)
    return JobOptions(
        scheduler=scheduler, cache=cache if job.accepts(Option.CACHE) else None,
        cache_bytes=cache_bytes if job.accepts(Option.CACHE) else None,
        max_samples_in_flight=in_flight,
        history_depth=request.history_depth, threads=request.threads,
        preload=not request.no_preload, trace_ahead=not request.passes_alone,
        load_bandwidth=request.load_bandwidth,
        cold_reads=request.cold_reads, eviction=request.eviction,
        simplified=request.simplified,
        portal_interval=request.portal_interval or DEFAULT_PORTAL_INTERVAL,
        portal_threshold=(DEFAULT_PORTAL_THRESHOLD if request.portal_threshold is None
                          else request.portal_threshold),
        portal_resolution=request.portal_resolution or DEFAULT_PORTAL_RESOLUTION,
        portal_accuracy=request.portal_accuracy,
        portal_memory=request.portal_memory or 0,
        assignment=request.assignment or job.default_assignment,
        priority=request.priority or job.default_priority,
        memory_limit=request.memory_limit,
    )
