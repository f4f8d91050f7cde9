"""A render checked and planned, before the first ray: the store and scene opened, the
scheduler resolved, the memory checked and the job's runtime picked (``plan_render``), for
``vastray render`` and the Python API alike."""

from __future__ import annotations

import argparse
import functools
import logging
import math
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from vastray.actors.coordinator import render_distributed
from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.preflight import (
    MemoryEstimate,
    RenderMemory,
    cache_within,
    check_limit_fits_machine,
    check_memory,
    check_owned_fit,
    crossings_from_surface,
    domain_footprints,
    estimate_memory,
    reference_paths_in_flight,
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
from vastray.render_job import (
    DEFAULT_BATCH_SIZE,
    DEFAULT_EXPOSURE,
    DEFAULT_HEARTBEAT_TIMEOUT_S,
    DEFAULT_NODE_SAMPLES_IN_FLIGHT,
    DEFAULT_NODE_TIMEOUT_S,
    DEFAULT_SAMPLES_IN_FLIGHT,
    job_options,
    refuse_for_lights,
    refuse_for_scheduler,
    refuse_inapplicable,
)
from vastray.report import build_report, count_overflow
from vastray.request import BUILTIN_DEFAULTS, STORE_DEFAULTS
from vastray.scene.cpus import available_cpus
from vastray.scene.errors import InputError
from vastray.scene.extent import check_extent
from vastray.scene.store import Store
from vastray.transport.keys import load_coordinator_keys

log = logging.getLogger(__name__)


def resolve_defaults(args: argparse.Namespace) -> None:
    """Fill the options left unset with the defaults of the built-in scene or of a store (and
    the defaults of the options ``refuse_inapplicable`` checks for presence)."""
    defaults = BUILTIN_DEFAULTS if args.store is None else STORE_DEFAULTS
    defaults = dict(defaults, exposure=DEFAULT_EXPOSURE,
                    node_timeout=DEFAULT_NODE_TIMEOUT_S,
                    heartbeat_timeout=DEFAULT_HEARTBEAT_TIMEOUT_S)
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)


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
    report_options : the run's switches, as its report records them (``run_options``).
    reference : (H, W, 3) image to measure the error against, or None.
    render_one : ``render_one(config, settings) -> RenderResult`` (``_renderer``).
    legend : the colour bar PNGs get, or None (``png_legend``).
    memory : the peak memory the preflight expects (``preflight.RenderMemory``).
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

    def progression(self, reference: np.ndarray | None = None,
                    resumed=None) -> Progression:
        """A fresh ``Progression`` of one image with the plan's stopping rules, measured
        against ``reference`` (default: the plan's)."""
        return Progression(self.settings.width, self.settings.height,
                           self.rules or StopRules(self.settings.spp),
                           self.reference if reference is None else reference,
                           resumed=resumed)


def check_and_default(args: argparse.Namespace) -> bool:
    """Refuse the options given where they change nothing, then fill in the defaults.
    Returns whether ``--shadow-samples`` was given (``plan_render`` needs to know)."""
    refuse_inapplicable(args)  # before the defaults fill in what was not given
    shadow_samples_given = args.shadow_samples is not None
    resolve_defaults(args)
    return shadow_samples_given


def plan_render(args: argparse.Namespace, shadow_samples_given: bool, *,
                animating: bool = False, launched: dict | None = None,
                store: Store | None = None, camera: dict | None = None) -> RenderPlan:
    """Open the store and scene, refuse what cannot work, and pick the scheduler and the
    job's options: everything before the first ray, for ``args`` as ``check_and_default``
    left them.

    Parameters
    ----------
    animating : an animation checks the camera (and reference) of each of its frames.
    launched : node processes started elsewhere (``vastray launch``).
    store : ``args.store`` already opened.
    camera : ``[camera]`` keys replacing the scene's camera (``scene_config.with_camera``).

    Raises
    ------
    InputError
        Naming the file or option and the problem.
    """
    if args.store is None:
        from vastray.default_scene import default_scene_config, default_store

        store_path = default_store(quiet=args.quiet)
        config = load_scene_config(args.scene) if args.scene else default_scene_config()
    else:
        store_path = Path(args.store)
        config = load_scene_config(args.scene)
    store = Store(store_path) if store is None else store
    check_extent(store.bounds, store.path, "partition it again")
    if camera is not None:
        config = with_camera(config, camera)
    config.check_objects(store.objects)
    legend = png_legend(args, store)
    refuse_for_lights(args, shadow_samples_given, config.resolve_lights())
    if not animating:  # an animation checks the camera of each of its frames
        config.resolve_camera(*store.world_bounds, args.width, args.height)
    reference = None
    if isinstance(args.reference, np.ndarray):
        reference = args.reference
    elif args.reference and not animating:
        reference = read_image(args.reference)
    settings = RenderSettings(
        width=args.width, height=args.height, spp=args.spp, integrator=args.integrator,
        bounces=args.bounces, shadow_samples=args.shadow_samples, ao_distance=args.ao_distance,
        seed=args.seed, batch_size=args.batch_size or DEFAULT_BATCH_SIZE,
        colormap=args.colormap,
        color_min=args.color_range[0] if args.color_range else None,
        color_max=args.color_range[1] if args.color_range else None,
    )
    if reference is not None and reference.shape != (args.height, args.width, 3):
        where = args.reference if isinstance(args.reference, str) else "reference"
        raise InputError(where, f"reference is {reference.shape[1]}x{reference.shape[0]}"
                                f", the render is {args.width}x{args.height}")
    cache = resolve_cache(args.cache, len(store.domains))
    scheduler = args.scheduler
    cache, memory = _check_render_memory(args, config,
                                         "reference" if scheduler == "auto" else scheduler,
                                         store, cache)
    if scheduler == "auto":
        scheduler = "reference" if cache is None or cache >= len(store.domains) else "spec-ooc"
    if args.rendezvous and not args.listen:
        raise InputError(None, "--rendezvous FILE needs --listen HOST:PORT (the nodes it "
                               "guides are started elsewhere)")
    if args.keys and not args.listen:
        raise InputError(None, "--keys is for nodes started elsewhere (--listen HOST:PORT); "
                               "the nodes --nodes starts here join with a secret handed to "
                               "them")
    if args.keys:
        load_coordinator_keys(args.keys)  # a missing or malformed key fails before the render
    if args.log_dir and args.listen:
        raise InputError(None, "--log-dir keeps the logs of nodes started here; nodes started "
                               "elsewhere (--listen) keep their own (`vastray launch --logs`)")
    if scheduler in ("domain", "async", "dynamic", "spec-insitu", "temporal") and not args.nodes:
        raise InputError(None, f"--scheduler {scheduler} distributes domains over nodes; "
                               "give --nodes N")
    if args.nodes:
        scheduler = "image" if scheduler == "reference" else scheduler
        cores = available_cpus()
        if not args.listen and args.nodes > cores:
            log.warning("--nodes %d on %d core(s): the nodes share them, so more than %d "
                        "nodes render no faster here", args.nodes, cores, cores)
    refuse_for_scheduler(args, scheduler)
    refuse_for_passes(args, animating)
    options = job_options(args, scheduler, cache)
    rules = StopRules(args.spp, args.time_limit, args.target_error,
                      args.max_pass_spp or DEFAULT_MAX_PASS_SPP)
    return RenderPlan(store_path, store, config, settings, scheduler, options,
                      run_options(args, options), reference,
                      _renderer(args, store, store_path, options, launched), legend, rules,
                      memory)


def refuse_for_passes(args: argparse.Namespace, animating: bool) -> None:
    """Refuse checkpoint options where they cannot work.

    Raises
    ------
    InputError
        Naming the option and what to do instead.
    """
    for dest in ("checkpoint_every", "checkpoint", "resume"):
        if getattr(args, dest, None) is not None and animating:
            raise InputError(None, f"--{dest.replace('_', '-')} is for one image; an animation goes on "
                                   "from a frame with --first-frame F")
    if args.resume is not None and args.simplified not in (None, "none"):
        raise InputError(args.resume, "--resume is for lossless renders: --simplified keeps "
                                      "a radiance cache that is not in the checkpoint")
    if (getattr(args, "target_error", None) is not None and not args.reference
            and args.simplified not in (None, "none")):
        raise InputError(None, "--target-error without --reference is for lossless renders: "
                               "--simplified is biased, and the film's error estimate sees "
                               "its noise, not its bias (give --reference IMAGE)")
    if args.checkpoint is not None and args.checkpoint_every is None:
        log.info("--checkpoint without --checkpoint-every: written on SIGUSR1 and Ctrl-C")


def finish_render(plan: RenderPlan, result: RenderResult, where: str | os.PathLike,
                  reference_name: str | None) -> tuple[np.ndarray, dict | None, dict]:
    """A finished render's image ((H, W, 3) as the film holds it), its error against the
    plan's reference (or None) and its report (the dict ``--report`` writes); non-finite
    pixels are counted (and said on stderr, naming ``where``)."""
    image = result.film.image()
    count_overflow(image, result.counters, where)
    error = image_error(image, plan.reference) if plan.reference is not None else None
    report = build_report(
        store=str(plan.store_path), settings=asdict(plan.settings), seconds=result.seconds,
        counters=result.counters, error=error, reference=reference_name,
        scheduler=plan.scheduler, options=plan.report_options, progress=result.progress,
    )
    return image, error, report


def png_legend(args: argparse.Namespace, store: Store) -> Legend | None:
    """The colour bar PNGs get (None: not coloured by scalars, or not asked for: ``--legend``,
    by default on with ``--colormap``); checks
    the ``--colormap`` name first, so a wrong one is refused before any rendering."""
    if args.colormap is not None:
        colormap_lut(args.colormap)
    by_scalars = coloured_by_scalars(store)
    for option, given in (("--colormap", args.colormap is not None), ("--legend", args.legend),
                          ("--color-range", args.color_range is not None)):
        if given and not by_scalars:
            raise InputError(store.path, f"{option} is for a store coloured by its scalar field;"
                                         " this one has " + ("per-vertex colours" if
                                                             store.has_colors else "no scalars"))
    if args.legend and not (args.png or str(args.output).lower().endswith(".png")):
        raise InputError(None, "--legend draws into PNG output only: give --png FILE or a .png "
                               "-o")
    if args.color_range is not None and not args.color_range[0] < args.color_range[1]:
        raise InputError(None, f"--color-range LO HI needs LO < HI, got "
                               f"{args.color_range[0]:g} {args.color_range[1]:g}")
    wanted = args.legend if args.legend is not None else args.colormap is not None
    return legend_for(store, args.colormap, args.color_range and tuple(args.color_range)) \
        if wanted else None


def _renderer(args: argparse.Namespace, store: Store, store_path: Path, options: JobOptions,
              launched: dict | None) -> Callable[..., RenderResult]:
    """The job's scheduler as ``render_one(config, settings, progression=None) ->
    RenderResult``: the image in the passes ``progression`` asks for (None: in one pass),
    the result's ``progress`` its report. The distributed one also takes
    ``render_distributed``'s ``frames``, ``on_frame`` and ``progression_of``."""
    if args.nodes:
        def render_one(config, settings, progression=None, **frames):
            if progression is not None:
                frames["progression_of"] = lambda frame: progression
            return render_distributed(
                store_path, args.scene, settings, args.nodes, options,
                timeout=args.node_timeout, listen=args.listen,
                keys=load_coordinator_keys(args.keys) if args.keys else None,
                launched=launched,
                progress=not args.quiet, config=config, rendezvous=args.rendezvous,
                heartbeat_timeout=args.heartbeat_timeout, log_dir=node_log_dir(args),
                **frames)
    elif options.scheduler == "reference":
        kept = FrameCache(store, options.cache, options.load_bytes_per_second())

        def render_one(config, settings, progression=None):
            return _with_progress(render(
                store, config, settings, threads=options.threads, progress=not args.quiet,
                cache=kept.for_frame(config, settings.integrator), progression=progression),
                progression)
    else:
        def render_one(config, settings, progression=None):
            return _with_progress(render_out_of_core(
                store, config, settings, options, progress=not args.quiet,
                progression=progression), progression)
    return render_one


def node_log_dir(args: argparse.Namespace) -> Path | None:
    """Where the logs of the nodes started here are kept: ``--log-dir``, else beside
    ``--report`` (``REPORT.nodes``; the report names it), else nowhere (removed)."""
    if args.log_dir:
        return Path(args.log_dir)
    if args.report and not args.listen:
        return Path(f"{args.report}.nodes")
    return None


def _with_progress(result: RenderResult, progression: Progression | None) -> RenderResult:
    if progression is not None:
        result.progress = progression.report()
    return result


def run_options(args: argparse.Namespace, options: JobOptions) -> dict:
    """The run's switches besides the scheduler, for its report (and ``vastray plot``'s
    labels): the job's options as the schedulers receive them (defaults filled in), the node
    count, timeouts and address, and the frames."""
    report = options.for_report()
    del report["scheduler"]  # the report's own "scheduler"
    nodes = {"node_timeout_s": args.node_timeout, "heartbeat_timeout_s": args.heartbeat_timeout,
             "listen": args.listen} if args.nodes else {}
    return {"nodes": args.nodes, **report, **nodes, "frames": args.frames,
            "first_frame": args.first_frame, "memory_limit": args.memory_limit}


def _check_render_memory(args: argparse.Namespace, config, scheduler: str, store: Store,
                         cache: int | None) -> tuple[int | None, RenderMemory]:
    """Refuse up front a render that cannot fit in memory (``preflight.check_memory``: every
    process it starts here, less a margin for the rest of the machine); with
    ``--memory-limit``, first bound each process's domain cache by what its base, film and
    paths in flight leave. Returns the cache and the estimates."""
    # shadow rays per hit: AO's samples, or per light its samples (area and sky) or one
    rays_per_hit = args.shadow_samples if args.integrator == "ao" else max(sum(
        shadow_rays(light, args.shadow_samples) for light in config.resolve_lights()), 1)
    threads = args.threads or available_cpus()
    total = args.width * args.height * args.spp
    footprints = domain_footprints(store.domains)
    reference = args.reference is not None  # a file name, or an array (the Python API)

    @functools.cache
    def copies() -> float:
        """spec-ooc's speculative copies of each shadow ray, beyond the model's own."""
        lo, hi = store.domain_boxes()
        return speculative_copies(
            crossings_from_surface(lo, hi, [d.n_triangles for d in store.domains]),
            args.bounces + 1 if args.integrator == "pt" else 1)

    def process(cache: int | None) -> MemoryEstimate:
        """One rendering process (a node with --nodes), its domains left out."""
        if args.nodes:
            tile = args.max_samples_in_flight or DEFAULT_NODE_SAMPLES_IN_FLIGHT
            return estimate_memory(args.width, args.height, min(tile, total), rays_per_hit,
                                   role="node",
                                   copies=copies() if scheduler == "spec-ooc" else 0.0)
        all_fit = cache is None or cache >= len(footprints)
        if scheduler == "reference" and (all_fit or args.scheduler != "auto"):
            in_flight = reference_paths_in_flight(total, args.batch_size or DEFAULT_BATCH_SIZE,
                                                  threads, all_fit)
        else:  # out of core (auto becomes spec-ooc when the domains do not all fit)
            in_flight = min(args.max_samples_in_flight or DEFAULT_SAMPLES_IN_FLIGHT, total)
            if args.scheduler in ("spec-ooc", "auto"):
                return estimate_memory(args.width, args.height, in_flight, rays_per_hit,
                                       reference=reference, copies=copies())
        return estimate_memory(args.width, args.height, in_flight, rays_per_hit,
                               reference=reference)

    if args.memory_limit is not None:
        if not args.listen:  # the processes it bounds run here
            check_limit_fits_machine(args.memory_limit)
        if scheduler == "spec-insitu":  # no cache to bound: every node's own domains must fit
            from vastray.schedule.ownership import zorder_owners

            nodes = args.nodes or 1
            check_owned_fit(args.memory_limit, process(cache), footprints,
                            zorder_owners(*store.domain_boxes(), nodes), nodes)
        else:
            fitting = cache_within(args.memory_limit, process(cache), footprints,
                                   args.width, args.height)
            if fitting < len(footprints) and args.scheduler == "auto":  # becomes spec-ooc
                fitting = cache_within(args.memory_limit, process(fitting), footprints,
                                       args.width, args.height)
            log.info("--memory-limit leaves room for %d domains per process", fitting)
            cache = fitting if cache is None else min(cache, fitting)
    held = sum(sorted(footprints, reverse=True)[:cache or len(footprints)])
    one = process(cache) + MemoryEstimate(0, 0, 0, domains=held)
    coordinator, machine = None, one
    if args.nodes:  # the coordinator, and every node unless they run elsewhere
        coordinator = estimate_memory(args.width, args.height, 0, 0, role="coordinator",
                                      reference=reference)
        machine = coordinator if args.listen else coordinator + one.times(args.nodes)
    check_memory(machine, args.width, args.height)
    return cache, RenderMemory(one, coordinator, machine)


def resolve_cache(cache: int | str | None, n_domains: int) -> int | None:
    """The cache size in domains: ``P%`` of ``n_domains`` rounded up (at least 1)."""
    if isinstance(cache, str):
        return max(1, math.ceil(float(cache[:-1]) / 100.0 * n_domains))
    return cache
