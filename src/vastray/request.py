"""A render as one typed, checked value: ``RenderRequest``, what ``vastray render`` parses its
command line into and ``vastray.render(...)`` builds from its keyword arguments.

It is the one place for the options' types, their defaults and their refusals: the
command line takes each option's converter, choices and default from the request's own
fields (``argument``), a request refuses a bad value when it is made (with the CLI's
converter, so the message is the same whoever made it) and an option given where it changes
nothing (``refuse_inapplicable``); ``resolved`` fills in the defaults that depend on the
store; the refusals that depend on the plan (the lights, the scheduler as resolved from
``auto``, an animation) are its methods, which ``planning.plan_render`` calls. ``run`` renders
a request to its files (``vastray.execute``).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vastray.preflight import parse_size
from vastray.scene.bvh_choice import CHOICES as BVH_CHOICES
from vastray.scene.errors import InputError
from vastray.schedule import portals
from vastray.schedule.registry import (
    ASSIGNMENTS,
    PRIORITIES,
    RENDER_CHOICES,
    Option,
    Runtime,
    spec,
)

#: Defaults for a user's store, and for the built-in scene (a first picture in a few seconds:
#: larger, smoother, one bounce and two shadow rays toward the sky).
STORE_DEFAULTS = {"width": 320, "height": 240, "spp": 4, "bounces": 3, "shadow_samples": 16}
BUILTIN_DEFAULTS = {"width": 640, "height": 480, "spp": 8, "bounces": 1, "shadow_samples": 2}

#: Paths traced at once by the out-of-core schedulers in one process, and with ``--nodes``
#: a quarter of it (every node on this machine holds its own): a sort-first node's tile, or
#: a domain-decomposition job's, shared by its nodes (``JobOptions.max_samples_in_flight``).
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



def _size(text: str) -> int:
    try:
        return parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def positive_int(text: str) -> int:
    """An option's whole number of at least 1 (argparse type: the refusal says which it is not)."""
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


#: Most samples per pixel a render may ask for: the passes are planned up front (about one
#: per 16 samples past the first few, ``render.progressive.pass_bounds``), and 10**12 once
#: planned passes until memory ran out before any check. At 2**20 a 64x48 image is already
#: 3 G paths; for "until the time is up", give this with --time-limit.
MAX_SPP = 1 << 20


def _spp(text: str) -> int:
    value = positive_int(text)
    if value > MAX_SPP:
        raise argparse.ArgumentTypeError(f"at most {MAX_SPP:,} (to render until a time is up, "
                                         f"give --spp {MAX_SPP} with --time-limit), got {value:,}")
    return value


def _portal_resolution(text: str) -> int:
    value = positive_int(text)
    if value > portals.MAX_RESOLUTION:
        raise argparse.ArgumentTypeError(f"at most {portals.MAX_RESOLUTION} (the paper's "
                                         f"largest), got {value}")
    return value


def _host_port(text: str) -> str:
    """``HOST:PORT`` with a host and a port in 0..65535 (0: a free port), as given."""
    host, colon, port = text.rpartition(":")
    if not colon or not host or not port.isdigit() or int(port) > 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT with a port in 0..65535 (0: any "
                                         f"free port), got {text!r}")
    return text


def _cache_size(text: str) -> int | str:
    """``N`` domains or ``P%`` of the domains (resolved once the store is open)."""
    if text.endswith("%"):
        try:
            value = float(text[:-1])
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected N domains or P% of them, got {text!r}"
                                             ) from None
        if not 0 < value <= 100:
            raise argparse.ArgumentTypeError(f"percentage must be in (0, 100], got {text}")
        return text
    return positive_int(text)


def resolve_cache(cache: int | str | None, n_domains: int) -> int | None:
    """The cache size in domains: ``P%`` of ``n_domains`` rounded up (at least 1)."""
    if isinstance(cache, str):
        return max(1, math.ceil(float(cache[:-1]) / 100.0 * n_domains))
    return cache


def _bandwidths(text: str) -> float | list[float]:
    """``MB/s`` or a comma-separated list of them (one per rank, cycled)."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MB/s numbers like 200 or 200,100; got "
                                         f"{text!r}") from None
    if not all(0 < v < float("inf") for v in values):
        raise argparse.ArgumentTypeError(f"bandwidths must be positive, got {text!r}")
    return values[0] if len(values) == 1 else values


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None


def _non_negative(text: str) -> int:
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {value}")
    return value


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def positive_float(text: str) -> float:
    """An option's positive finite number (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
    return value


def _option(default=None, *, type=None, choices=None, nargs=None, const=None,
            switch: bool = False):
    """A field of ``RenderRequest`` that is an option of ``vastray render``: its default, and
    how a value is read (``type``: the command line's converter of a text; ``choices``;
    ``nargs``, ``const``; ``switch``: a flag, True or False)."""
    return field(default=default, metadata={"option": dict(
        type=type, choices=choices, nargs=nargs, const=const, switch=switch)})


@dataclass(frozen=True)
class RenderRequest:
    """One render, as ``vastray render``'s options give it: the scene (``store``, ``scene``,
    ``camera``), the image's settings, the run's options, its outputs and its stopping rules.

    Every option is a field named as its long option with underscores (``--history-depth``:
    ``history_depth``); None is "not given" (``resolved`` fills in the defaults that depend
    on the store). Made with bad values, or with an option that changes nothing for the
    others, it is refused with ``InputError``: the messages ``vastray render`` prints.
    """

    # the scene
    store: str | None = _option(nargs="?")
    output: str | None = _option()
    png: str | None = _option()
    scene: str | None = _option()
    # the image
    integrator: str = _option("pt", choices=("ao", "pt"))
    spp: int | None = _option(type=_spp)
    bounces: int | None = _option(type=_non_negative)
    shadow_samples: int | None = _option(type=positive_int)
    ao_distance: float | None = _option(type=positive_float)
    width: int | None = _option(type=positive_int)
    height: int | None = _option(type=positive_int)
    seed: int = _option(0, type=_non_negative)
    bvh: str = _option("auto", choices=BVH_CHOICES)
    # how it is run
    cache: int | str | None = _option(type=_cache_size)
    scheduler: str = _option("auto", choices=RENDER_CHOICES)
    memory_limit: int | None = _option(type=_size)
    max_samples_in_flight: int | None = _option(type=positive_int)
    history_depth: int | None = _option(type=_non_negative)
    nodes: int | None = _option(type=positive_int)
    node_timeout: float | None = _option(type=positive_float)
    log_dir: str | None = _option()
    heartbeat_timeout: float | None = _option(type=positive_float)
    listen: str | None = _option(type=_host_port)
    rendezvous: str | None = _option()
    keys: str | None = _option()
    no_preload: bool = _option(False, switch=True)
    passes_alone: bool = _option(False, switch=True)
    assignment: str | None = _option(choices=ASSIGNMENTS)
    priority: str | None = _option(choices=PRIORITIES)
    simplified: str | None = _option(nargs="?", const="portal",
                                     choices=("portal", "depth>0", "depth>1", "depth>2",
                                              "none"))
    portal_interval: int | None = _option(type=positive_int)
    portal_memory: int | None = _option(type=positive_int)
    portal_resolution: int | None = _option(type=_portal_resolution)
    portal_threshold: float | None = _option(type=float)
    portal_accuracy: bool = _option(False, switch=True)
    load_bandwidth: float | list[float] | None = _option(type=_bandwidths)
    cold_reads: bool = _option(False, switch=True)
    eviction: str = _option("lru", choices=("lru", "demand"))
    batch_size: int | None = _option(type=positive_int)
    threads: int | None = _option(type=positive_int)
    # outputs
    report: str | None = _option()
    reference: str | np.ndarray | None = _option()
    frames: int | None = _option(type=positive_int)
    first_frame: int | None = _option(type=_non_negative)
    exposure: float | None = _option(type=positive_float)
    colormap: str | None = _option()
    color_range: list[float] | None = _option(type=_finite_float, nargs=2)
    legend: bool | None = _option(switch=True)
    quiet: bool = _option(False, switch=True)
    # progressive passes, stopping rules and checkpoints
    time_limit: float | None = _option(type=positive_float)
    target_error: float | None = _option(type=positive_float)
    max_pass_spp: int | None = _option(type=positive_int)
    checkpoint_every: float | None = _option(type=positive_float)
    checkpoint: str | None = _option()
    resume: str | None = _option()
    #: the view, replacing the scene's ``[camera]`` (``scene_camera.with_camera``): the
    #: Python API's ``camera=``; the command line has none.
    camera: Mapping | Any | None = None
    #: the command line's own arguments, kept in its checkpoints (the Python API has none).
    argv: tuple[str, ...] | None = field(default=None, compare=False, repr=False)
    #: the options given (set, not at their defaults), once ``resolved`` has filled in the
    #: others (None before).
    given: frozenset[str] | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        for name in OPTIONS:
            object.__setattr__(self, name, converted(name, getattr(self, name)))
        if self.given is None:
            self.refuse_inapplicable()

    @classmethod
    def field_default(cls, name: str):
        """Option ``name``'s default as given to the command line's parser."""
        return OPTIONS[name].default

    @classmethod
    def from_namespace(cls, args: argparse.Namespace, **changes) -> RenderRequest:
        """The request of ``vastray render``'s (or ``launch``'s) parsed command line, with
        ``changes`` (``launch`` sets ``nodes`` and ``listen``)."""
        values = {name: getattr(args, name) for name in OPTIONS}
        argv = getattr(args, "argv", None)
        return cls(**{**values, **changes}, argv=None if argv is None else tuple(argv))

    def resolved(self) -> RenderRequest:
        """The request with the options left unset at the defaults of the built-in scene or
        of a store (and at the defaults of the options ``refuse_inapplicable`` checks for
        presence); ``given`` names the options that were given."""
        if self.given is not None:
            return self
        defaults = BUILTIN_DEFAULTS if self.store is None else STORE_DEFAULTS
        defaults = dict(defaults, exposure=DEFAULT_EXPOSURE, node_timeout=DEFAULT_NODE_TIMEOUT_S,
                        heartbeat_timeout=DEFAULT_HEARTBEAT_TIMEOUT_S)
        given = frozenset(name for name in OPTIONS if _given(getattr(self, name), name))
        return dataclasses.replace(self, **{key: value for key, value in defaults.items()
                                            if getattr(self, key) is None}, given=given)

    def refuse_inapplicable(self) -> None:
        """Refuse every option given where it changes nothing whatever the scheduler: without
        ``--nodes``, for the other integrator, or without a PNG output (before the defaults
        are filled in: an option left unset is None).

        Raises
        ------
        InputError
            Naming the option, why it does not apply, and what would make it apply.
        """
        if not self.nodes:
            for dest in NODE_OPTIONS:
                if getattr(self, dest) is not None:
                    raise InputError(None, f"{_flag(dest)} applies to node processes: give "
                                           "--nodes N with it, or drop it")
        if self.integrator == "pt" and self.ao_distance is not None:
            raise InputError(None, "--ao-distance is the ambient-occlusion ray length: it "
                                   "applies to --integrator ao only")
        if self.integrator == "ao" and self.bounces is not None:
            raise InputError(None, "--bounces counts path-tracing bounces: --integrator ao "
                                   "traces one hit per path (use --integrator pt, or drop "
                                   "--bounces)")
        portal = [dest for dest in ("portal_interval", "portal_resolution", "portal_threshold",
                                    "portal_memory")
                  if getattr(self, dest) is not None]
        if portal and self.simplified != "portal":
            raise InputError(None, f"{_flag(portal[0])} tunes the virtual portals of "
                                   "--simplified portal; give --simplified portal (with "
                                   "--scheduler async or temporal), or drop it")
        if self.exposure is not None and not self.png_output:
            raise InputError(None, "--exposure scales PNG output only: give --png FILE or a "
                                   ".png -o, or drop it")

    @property
    def png_output(self) -> bool:
        """Whether the render writes a PNG (``--png``, or a .png ``-o``)."""
        return bool(self.png or str(self.output).lower().endswith(".png"))

    def refuse_for_lights(self, lights: list) -> None:
        """Refuse ``--shadow-samples`` for path tracing where no light is sampled
        stochastically (point and directional lights get one shadow ray each: the count would
        change nothing).

        Raises
        ------
        InputError
            Naming the option and what would make it apply.
        """
        given = self.shadow_samples is not None if self.given is None \
            else "shadow_samples" in self.given
        if (given and self.integrator == "pt"
                and not any(light.stochastic for light in lights)):
            raise InputError(None, "--shadow-samples sets the shadow rays per hit for area and "
                                   "sky lights (and ambient occlusion); this scene's lights are "
                                   "point or directional, one shadow ray each: drop it, or add "
                                   "such a light")

    def refuse_for_scheduler(self, scheduler: str) -> None:
        """Refuse the options given that ``scheduler`` (resolved from ``auto``) does not read.

        Raises
        ------
        InputError
            Naming the option, why it does not apply, and what would make it apply.
        """
        job = spec(scheduler)
        if self.batch_size is not None and not job.accepts(Option.BATCH_SIZE):
            raise InputError(None, f"--batch-size sets the in-core reference render's batches; "
                                   f"--scheduler {scheduler} traces --max-samples-in-flight "
                                   "paths at a time (use that instead)")
        if job.runtime is Runtime.IN_CORE:
            for dest in ("max_samples_in_flight", "history_depth"):
                if getattr(self, dest) is not None:
                    raise InputError(None, f"{_flag(dest)} applies to the out-of-core "
                                           "schedulers; this render is the in-core reference "
                                           "(every domain fits in --cache): give --scheduler "
                                           "image or spec-ooc with a smaller --cache, or drop "
                                           "it")
            if self.no_preload:
                raise InputError(None, "--no-preload applies to the out-of-core schedulers; "
                                       "the in-core reference render loads each domain once "
                                       "and never preloads")
            if self.passes_alone:
                raise InputError(None, "--passes-alone applies to the out-of-core schedulers "
                                       "(in core every pass is alone: it loads nothing)")
            if self.cold_reads:
                raise InputError(None, "--cold-reads applies to the out-of-core schedulers; "
                                       "the in-core reference render loads each domain once "
                                       "(give --scheduler image or spec-ooc with --cache or "
                                       "--memory-limit)")
        if self.cache is not None and not job.accepts(Option.CACHE):
            raise InputError(None, f"--cache does not apply to --scheduler {scheduler}: in "
                                   "situ, every node keeps all the domains it owns loaded")

    def refuse_for_nodes(self, scheduler: str) -> None:
        """Refuse the node options that cannot work together (``--rendezvous`` and ``--keys``
        without ``--listen``, ``--log-dir`` with it), and a scheduler that distributes domains
        without ``--nodes`` (``scheduler`` as resolved from ``auto``).

        Raises
        ------
        InputError
            Naming the option and what it needs.
        """
        if self.rendezvous and not self.listen:
            raise InputError(None, "--rendezvous FILE needs --listen HOST:PORT (the nodes it "
                                   "guides are started elsewhere)")
        if self.keys and not self.listen:
            raise InputError(None, "--keys is for nodes started elsewhere (--listen "
                                   "HOST:PORT); the nodes --nodes starts here join with a "
                                   "secret handed to them")
        if self.log_dir and self.listen:
            raise InputError(None, "--log-dir keeps the logs of nodes started here; nodes "
                                   "started elsewhere (--listen) keep their own (`vastray "
                                   "launch --logs`)")
        if spec(scheduler).runtime.nodes_only and not self.nodes:
            raise InputError(None, f"--scheduler {scheduler} distributes domains over nodes; "
                                   "give --nodes N")

    def refuse_for_passes(self, animating: bool) -> None:
        """Refuse checkpoint options where they cannot work, and ``--passes-alone`` without
        passes apart.

        Raises
        ------
        InputError
            Naming the option and what to do instead.
        """
        for dest in ("checkpoint_every", "checkpoint", "resume"):
            if getattr(self, dest) is not None and animating:
                raise InputError(None, f"--{dest.replace('_', '-')} is for one image; an "
                                       "animation goes on from a frame with --first-frame F")
        if self.resume is not None and self.simplified not in (None, "none"):
            raise InputError(self.resume, "--resume is for lossless renders: --simplified "
                                          "keeps a radiance cache that is not in the "
                                          "checkpoint")
        if self.passes_alone and not (self.reference is not None or self.time_limit is not None
                                      or self.target_error is not None):
            raise InputError(None, "--passes-alone is for passes apart: give --reference, "
                                   "--time-limit or --target-error, or drop it (without them "
                                   "an out-of-core render is one pass)")
        if (self.target_error is not None and not self.reference
                and self.simplified not in (None, "none")):
            raise InputError(None, "--target-error without --reference is for lossless "
                                   "renders: --simplified is biased, and the film's error "
                                   "estimate sees its noise, not its bias (give --reference "
                                   "IMAGE)")

    def report_options(self, options) -> dict:
        """The run's switches besides the scheduler, for its report (and ``vastray plot``'s
        labels): the job's ``options`` (``JobOptions``) as the schedulers receive them
        (defaults filled in), the node count, timeouts and address, and the frames."""
        report = options.for_report()
        del report["scheduler"]  # the report's own "scheduler"
        nodes = {"node_timeout_s": self.node_timeout,
                 "heartbeat_timeout_s": self.heartbeat_timeout,
                 "listen": self.listen} if self.nodes else {}
        return {"nodes": self.nodes, **report, **nodes, "frames": self.frames,
                "first_frame": self.first_frame, "memory_limit": self.memory_limit}


#: The option fields of ``RenderRequest``, by name.
OPTIONS = {f.name: f for f in dataclasses.fields(RenderRequest) if "option" in f.metadata}


def argument(name: str) -> dict:
    """``add_argument``'s keywords for option ``name`` from the request's field: its
    converter, choices, nargs and default (a switch's action)."""
    spec = OPTIONS[name].metadata["option"]
    kwargs: dict = {"default": OPTIONS[name].default}
    if spec["switch"]:
        kwargs["action"] = "store_true" if kwargs["default"] is False \
            else argparse.BooleanOptionalAction
        return kwargs
    for key in ("type", "choices", "nargs", "const"):
        if spec[key] is not None:
            kwargs[key] = list(spec[key]) if key == "choices" else spec[key]
    return kwargs


def converted(name: str, value):
    """``value`` of option ``name`` as the command line's converter for it would give it
    (None: the default; an array, a ``reference`` image, as it is).

    Raises
    ------
    InputError
        Naming the option and what is wrong with the value.
    """
    default = OPTIONS[name].default
    spec = OPTIONS[name].metadata["option"]
    if value is None or isinstance(value, np.ndarray):
        return default if value is None else value
    flag = name if name == "store" else _flag(name)
    if spec["switch"]:
        if not isinstance(value, bool):
            raise InputError(None, f"{name} must be True or False, got {value!r}")
        return value
    if isinstance(spec["nargs"], int) and spec["nargs"] > 1:  # e.g. --color-range LO HI
        if not isinstance(value, (list, tuple)) or len(value) != spec["nargs"]:
            raise InputError(None, f"{name} takes {spec['nargs']} values, got {value!r}")
        return [_converted_one(name, spec, flag, v) for v in value]
    return _converted_one(name, spec, flag, value)


def _converted_one(name: str, spec: dict, flag: str, value):
    """One value as the option's converter gives it (see ``converted``)."""
    if isinstance(value, bool) or not isinstance(value, (str, os.PathLike, int, float,
                                                         np.number, list, tuple)):
        raise InputError(None, f"{name}={value!r} is not a valid value of {flag} (see "
                               "`vastray render --help`)")
    if isinstance(value, (list, tuple)):  # --load-bandwidth's per-rank list
        text = ",".join(str(v) for v in value)
    else:
        text = os.fspath(value) if isinstance(value, os.PathLike) else str(value)
    if spec["type"] is not None:
        try:
            value = spec["type"](text)
        except argparse.ArgumentTypeError as exc:
            raise InputError(None, f"{name}={value!r}: {exc}") from None
        except (TypeError, ValueError):
            raise InputError(None, f"{name}={value!r} is not a valid value of {flag} (see "
                                   "`vastray render --help`)") from None
    else:
        value = text
    if spec["choices"] is not None and value not in spec["choices"]:
        raise InputError(None, f"{name}={value!r}: choose from "
                               f"{', '.join(map(str, spec['choices']))}")
    return value


def _given(value, name: str) -> bool:
    """Whether ``value`` of option ``name`` was given: set, and not the option's default."""
    if isinstance(value, np.ndarray):
        return True
    return value is not None and value != OPTIONS[name].default


def _flag(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def run(request: RenderRequest, launched: dict | None = None) -> int:
    """Render ``request`` to its files (``vastray render``): see ``vastray.execute.run``."""
    from vastray.execute import run as execute

    return execute(request, launched)
