"""From ``vastray render``'s command line to the job it runs: the options that apply to the
chosen scheduler, as one ``JobOptions``, and a clear refusal of every option given where it
would change nothing."""

from __future__ import annotations

import argparse

from vastray.actors.job_options import DEFAULT_PORTAL_RESOLUTION, JobOptions
from vastray.scene.errors import InputError

#: Paths traced at once by the out-of-core schedulers in one process, and per node with
#: ``--nodes`` (a quarter: every node on this machine holds its own).
DEFAULT_SAMPLES_IN_FLIGHT = 262144
DEFAULT_NODE_SAMPLES_IN_FLIGHT = DEFAULT_SAMPLES_IN_FLIGHT // 4

#: Defaults of options whose absence is checked (they default to None on the parser).
DEFAULT_BATCH_SIZE = 65536
DEFAULT_NODE_TIMEOUT_S = 120.0
DEFAULT_HEARTBEAT_TIMEOUT_S = 10.0
DEFAULT_EXPOSURE = 1.0
DEFAULT_PORTAL_INTERVAL = 10
DEFAULT_PORTAL_THRESHOLD = 0.5

#: Options that only mean something with ``--nodes``.
NODE_OPTIONS = ("node_timeout", "heartbeat_timeout", "listen", "keys", "log_dir")


def _flag(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def refuse_inapplicable(args: argparse.Namespace) -> None:
    """Refuse every option given where it changes nothing whatever the scheduler: without
    ``--nodes``, for the other integrator, or without a PNG output. Call it before the
    defaults are filled in (an option left unset is None).

    Raises
    ------
    InputError
        Naming the option, why it does not apply, and what would make it apply.
    """
    if not args.nodes:
        for dest in NODE_OPTIONS:
            if getattr(args, dest) is not None:
                raise InputError(None, f"{_flag(dest)} applies to node processes: give "
                                       "--nodes N with it, or drop it")
    if args.integrator == "pt" and args.ao_distance is not None:
        raise InputError(None, "--ao-distance is the ambient-occlusion ray length: it applies "
                               "to --integrator ao only")
    if args.integrator == "ao" and args.bounces is not None:
        raise InputError(None, "--bounces counts path-tracing bounces: --integrator ao traces "
                               "one hit per path (use --integrator pt, or drop --bounces)")
    portal = [dest for dest in ("portal_interval", "portal_resolution", "portal_threshold",
                                "portal_memory")
              if getattr(args, dest) is not None]
    if portal and args.simplified != "portal":
        raise InputError(None, f"{_flag(portal[0])} tunes the virtual portals of --simplified "
                               "portal; give --simplified portal (with --scheduler async or "
                               "temporal), or drop it")
    if args.exposure is not None and not (args.png or str(args.output).lower().endswith(".png")):
        raise InputError(None, "--exposure scales PNG output only: give --png FILE or a .png "
                               "-o, or drop it")


def refuse_for_lights(args: argparse.Namespace, shadow_samples_given: bool, lights: list) -> None:
    """Refuse ``--shadow-samples`` for path tracing where no light is sampled stochastically
    (point and directional lights get one shadow ray each: the count would change nothing).

    Raises
    ------
    InputError
        Naming the option and what would make it apply.
    """
    if (shadow_samples_given and args.integrator == "pt"
            and not any(light.stochastic for light in lights)):
        raise InputError(None, "--shadow-samples sets the shadow rays per hit for area and sky "
                               "lights (and ambient occlusion); this scene's lights are point "
                               "or directional, one shadow ray each: drop it, or add such a "
                               "light")


def refuse_for_scheduler(args: argparse.Namespace, scheduler: str) -> None:
    """Refuse the options given that ``scheduler`` (resolved from ``auto``) does not read.

    Raises
    ------
    InputError
        Naming the option, why it does not apply, and what would make it apply.
    """
    if args.batch_size is not None and scheduler != "reference":
        raise InputError(None, f"--batch-size sets the in-core reference render's batches; "
                               f"--scheduler {scheduler} traces --max-samples-in-flight paths "
                               "at a time (use that instead)")
    if scheduler == "reference":
        for dest in ("max_samples_in_flight", "history_depth"):
            if getattr(args, dest) is not None:
                raise InputError(None, f"{_flag(dest)} applies to the out-of-core schedulers; "
                                       "this render is the in-core reference (every domain "
                                       "fits in --cache): give --scheduler image or spec-ooc "
                                       "with a smaller --cache, or drop it")
        if args.no_preload:
            raise InputError(None, "--no-preload applies to the out-of-core schedulers; the "
                                   "in-core reference render loads each domain once and never "
                                   "preloads")
        if args.cold_reads:
            raise InputError(None, "--cold-reads applies to the out-of-core schedulers; the "
                                   "in-core reference render loads each domain once (give "
                                   "--scheduler image or spec-ooc with --cache or "
                                   "--memory-limit)")
    if args.cache is not None and scheduler == "spec-insitu":
        raise InputError(None, "--cache does not apply to --scheduler spec-insitu: in situ, "
                               "every node keeps all the domains it owns loaded")


def job_options(args: argparse.Namespace, scheduler: str, cache: int | None) -> JobOptions:
    """The job's options from the command line (defaults filled in where the scheduler uses
    them), for ``scheduler`` as resolved from ``auto``, with ``cache`` in domains."""
    tiles = scheduler != "reference"
    in_flight = args.max_samples_in_flight
    if in_flight is None and tiles:
        in_flight = DEFAULT_NODE_SAMPLES_IN_FLIGHT if args.nodes else DEFAULT_SAMPLES_IN_FLIGHT
    return JobOptions(
        scheduler=scheduler, cache=None if scheduler == "spec-insitu" else cache,
        max_samples_in_flight=in_flight,
        history_depth=args.history_depth, threads=args.threads,
        preload=not args.no_preload, load_bandwidth=args.load_bandwidth,
        cold_reads=args.cold_reads, eviction=args.eviction,
        simplified=args.simplified,
        portal_interval=args.portal_interval or DEFAULT_PORTAL_INTERVAL,
        portal_threshold=(DEFAULT_PORTAL_THRESHOLD if args.portal_threshold is None
                          else args.portal_threshold),
        portal_resolution=args.portal_resolution or DEFAULT_PORTAL_RESOLUTION,
        portal_accuracy=args.portal_accuracy,
        portal_memory=args.portal_memory or 0,
        assignment=args.assignment or ("affinity" if scheduler == "temporal" else None),
        priority=args.priority or ("cost-rate" if scheduler == "temporal" else None),
    )
