"""A render job's options: everything a scheduler is told besides the scene and the image
settings, as one typed, frozen, versioned object.

``vastray render`` builds it once from its command line; ``render_out_of_core`` (one process)
and every node scheduler (``--nodes``) receive it whole, and each field has one reader (named
in the field's comment). Between the coordinator and the nodes it travels as a plain dict with
a ``version`` (``to_wire``), checked on receipt (``from_wire``): an unknown version, an unknown
or missing field, or a value of the wrong type is refused with an error that names it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from vastray.scene.errors import InputError
from vastray.schedule import registry
from vastray.schedule.portals import DEFAULT_RESOLUTION
from vastray.schedule.registry import ASSIGNMENTS, PRIORITIES, Option

#: Paths a sort-first node traces at once where the job's options leave
#: ``max_samples_in_flight`` unset, and a domain-decomposition job's tile on up to 16 nodes.
DEFAULT_NODE_TILE = 65536
#: Paths a domain-decomposition job's default tile gives each node at least: past 16 nodes the
#: tile grows with the nodes (``default_tile``), up to ``MAX_JOB_TILE``.
MIN_NODE_SHARE = 4096
#: The most paths a domain-decomposition job's default tile holds (1,024 nodes' shares):
#: every node keeps path state for each path of a tile (about 48 bytes a path, so 200 MB).
MAX_JOB_TILE = 1 << 22

#: Rays per batch between two nodes unless told otherwise (``node_work.NodeWork``; about
#: 6 MB of path-tracing rays).
DEFAULT_MAX_BATCH_RAYS = 65536

#: The wire layout's version: a node refuses a job whose options carry another. 2: cold_reads,
#: eviction; 3: portal_memory, assignment paper|affinity; 4: the same options, but dynamic's
#: and spec-insitu's batches go only where rays go (their counts in the schedule, or summed
#: over the tree), so nodes of version 3 would wait for batches that never come; 5: the job's
#: settings beside these options carry color_min and color_max (``--color-range``), which a
#: node of version 4 cannot read; 6: trace_ahead (``--passes-alone``), and a time-limited
#: job's passes traced ahead by the clock each grant brings; 8: memory_limit (a node's cache
#: gives the heap's free memory back as its RSS nears it); 9: cache_bytes (a node's cache
#: bounded by bytes, which a node of version 8 would ignore, holding more than the limit allows).
VERSION = 9

SIMPLIFIED_POLICIES = ("portal", "depth>0", "depth>1", "depth>2", "none")
EVICTIONS = ("lru", "demand")

DEFAULT_PORTAL_RESOLUTION = DEFAULT_RESOLUTION  # the paper's


def default_tile(scheduler: str, nodes: int) -> int:
    """The paths in flight (``max_samples_in_flight``) where a job on ``nodes`` nodes leaves
    them unset: a sort-first node's own ``DEFAULT_NODE_TILE``; a domain-decomposition job's
    ``DEFAULT_NODE_TILE`` or ``MIN_NODE_SHARE`` a node, whichever is more, at most
    ``MAX_JOB_TILE``.

    Why the job's tile grows with the nodes: every node starts 1/P of each tile, and each of
    a tile's rounds (``domain``, ``dynamic``, ``spec-insitu``) costs an all-reduction of
    log2 P steps whatever its work. At 1,024 nodes a fixed tile of 65,536 paths gave a node
    64 paths a tile, and by replay at 4,096 paths a node (``bench/replay_variants.py``,
    section 2) ``domain`` and ``dynamic`` ran at 0.17 of one node's speed, their frames 64
    tiles of 10-30 rounds each. What it costs is memory: every node keeps path state for
    each path of a tile (about 48 bytes a path: 3 MB at 65,536 paths, 200 MB at
    ``MAX_JOB_TILE``; ``spec-insitu`` also a t-buffer key of 8 bytes and an o-buffer byte
    a shadow slot), and the rays waiting for its domains, up to the whole tile's where
    they all gather there. ``--max-samples-in-flight`` sets a hard bound.
    """
    if nodes < 1:
        raise ValueError(f"a job needs at least 1 node, not {nodes}")
    if not registry.spec(scheduler).runtime.nodes_only:
        return DEFAULT_NODE_TILE
    return min(max(DEFAULT_NODE_TILE, MIN_NODE_SHARE * nodes), MAX_JOB_TILE)


class JobOptionsError(InputError):
    """Job options that do not fit together, or a wire dict that is not job options of this
    version; the message names the option and what to do."""

    def __init__(self, problem: str):
        super().__init__(None, problem)


@dataclass(frozen=True)
class JobOptions:
    """How one render job runs. Each runtime reads each field in one place, named beside
    it: the in-core reference (``planning._renderer``), the out-of-core runtime of
    one process or of a node's sort-first tiles (``local.render_out_of_core``), and the
    domain-decomposition runtimes of the nodes (``decomposition.render_owned_domains`` and
    ``insitu.render_spec_insitu``, through ``NodeState.preloader_for`` for the cache, threads,
    preloading and bandwidth).

    Parameters
    ----------
    scheduler : the schedule every process runs (the CLI's renderer, ``render_share`` on a
        node and ``render_out_of_core`` dispatch on it).
    cache : most domains resident per process; None: all (or as many as a node owns).
    max_samples_in_flight : paths traced at once (the tile): a sort-first node's own (it
        renders its band of the image, or its tiles round robin, alone:
        ``ownership.sort_first_tile_paths``), a domain-decomposition job's as a whole (every
        node starts its share of each tile, 1/P of its paths, and a node holds the rays
        waiting for its domains, up to the whole tile's where they gather there); None: all
        of them (``render_distributed`` fills in ``default_tile``: 65,536, or 4,096 a node
        for a domain-decomposition job on more than 16 nodes, up to 4,194,304).
    history_depth : spec-ooc's H, bounces speculated before hits resolve; None: every bounce
        (passed to ``schedule.spec_ooc.SpeculativeSchedule``).
    max_batch_rays : most rays in one batch between two nodes (``node_work.NodeWork``).
    threads : threads each process's Embree queries split their rays over; None: all cores
        (``render_distributed`` fills in this machine's cores shared among its nodes).
    preload : load the next domain in the background (the domain cache's preloading).
    build_ahead : out of core, keep one slot of the cache for the next domain to load, built
        on the preloader thread while the schedule names no preload (``DomainCache.build_ahead``;
        spec-ooc names none while it serves the domain a load would evict). Off by default: in
        ``bench/ooc.py --large`` it made spec-ooc 4-10 % faster at a quarter of the domains
        cached with cold reads, 6-7 % slower at 200 MB/s, and at half either way (-2 to
        +7 %), the replaced builds costing CPU (bench/README, sessions 64 and 65).
    trace_ahead : out of core with passes apart (a reference, a time limit, an error target),
        trace later passes on the current one's domain loads
        (``SortFirstTiles.render_ahead``); False: each pass sweeps the domains alone
        (``--passes-alone``: the earliest error point of each pass, at more loads).
    resident_first : schedules serve domains in memory before loading others (the image and
        spec-ooc schedules, and async's).
    load_bandwidth : MB/s of emulated network storage: a domain load takes at least its size
        over this; one number for every process or one per rank, cycled
        (``load_bytes_per_second``); None: the disk's own speed.
    eviction : which resident domain a load evicts in the out-of-core runtime
        (``local.render_out_of_core``): ``lru``, the least recently used, or ``demand``, the
        one the tile schedule will need last by its own order (its ``demand()``: an
        approximation of Belady's rule, the same rule for both tile schedules).
    cold_reads : read each domain's files whole and have the kernel drop their pages
        (``posix_fadvise(POSIX_FADV_DONTNEED)``), so every reload after an eviction is a read
        from the disk, not from the page cache (the domain cache, ``scene.cache``).
    simplified : the simplified-model policy of ``schedule.simplified`` (async, temporal);
        None: off (``simplified_frames.simplified_routing``).
    portal_interval, portal_threshold, portal_resolution, portal_accuracy : the virtual
        portals of ``simplified="portal"`` (``simplified_frames.simplified_routing``).
    portal_memory : 0 (the paper's): only recording frames record; N >= 1: predicting
        frames also record the depth-1 rays they trace fine, and a cell no frame has
        recorded for N frames is forgotten (``Portals.refresh``).
    assignment : domain ownership, ``sequential`` (async's round robin, its only one so far),
        ``spatial``, ``paper`` (Algorithm 1) or ``affinity`` (Algorithm 1 with cache
        affinity); None: the scheduler's default (``decomposition._temporal_frame`` for
        temporal: ``affinity``).
    priority : temporal's domain priority; None: ``cost-rate`` (``decomposition._temporal_frame``).
    memory_limit : bytes each process may use (``--memory-limit``, which sized ``cache``);
        each process's domain cache gives the C heap's free memory back to the system before
        a build while its RSS is above ``scene.heap.TRIM_ABOVE`` of it (``DomainCache``'s
        ``rss_ceiling``); None: never.
    cache_bytes : most bytes each process's domain cache may hold, each domain counted as
        the preflight counts it (``DomainCache``'s ``max_bytes``; ``--memory-limit`` sets it
        to what the process's film, paths, builds and margin leave, and ``cache`` to the most
        domains that could fit in it); None: ``cache`` alone bounds the cache.

    Raises
    ------
    JobOptionsError
        On construction, for a value of the wrong type or range, or options that do not fit
        the scheduler (each message names the command-line option).
    """

    scheduler: str = "image"
    cache: int | None = None
    max_samples_in_flight: int | None = None
    history_depth: int | None = None
    max_batch_rays: int = DEFAULT_MAX_BATCH_RAYS
    threads: int | None = None
    preload: bool = True
    build_ahead: bool = False
    trace_ahead: bool = True
    resident_first: bool = True
    load_bandwidth: tuple[float, ...] | None = None
    cold_reads: bool = False
    eviction: str = "lru"
    simplified: str | None = None
    portal_interval: int = 10
    portal_threshold: float = 0.5
    portal_resolution: int = DEFAULT_PORTAL_RESOLUTION
    portal_accuracy: bool = False
    portal_memory: int = 0
    assignment: str | None = None
    priority: str | None = None
    memory_limit: int | None = None
    cache_bytes: int | None = None

    def __post_init__(self) -> None:
        if isinstance(self.load_bandwidth, (int, float)) and not isinstance(self.load_bandwidth,
                                                                             bool):
            object.__setattr__(self, "load_bandwidth", (float(self.load_bandwidth),))
        elif isinstance(self.load_bandwidth, list):
            object.__setattr__(self, "load_bandwidth", tuple(self.load_bandwidth))
        self._check_types()
        self._check_values()

    def _check_types(self) -> None:
        for name, kinds in _TYPES.items():
            value = getattr(self, name)
            if value is None and name in _OPTIONAL:
                continue
            if kinds is bool:
                ok = type(value) is bool
            else:
                ok = isinstance(value, kinds) and not isinstance(value, bool)
            if not ok:
                raise JobOptionsError(f"job option {name!r} must be {_TYPE_NAMES[name]}, got "
                                      f"{value!r}")
        if self.load_bandwidth is not None and not all(
                isinstance(v, (int, float)) and not isinstance(v, bool)
                for v in self.load_bandwidth):
            raise JobOptionsError(f"job option 'load_bandwidth' must be MB/s numbers, got "
                                  f"{self.load_bandwidth!r}")

    def _check_values(self) -> None:
        # What each scheduler accepts is declared once, in ``schedule.registry``.
        sched = registry.find(self.scheduler)
        if sched is None or sched.runtime is registry.Runtime.RESOLVED:
            raise JobOptionsError(f"unknown scheduler {self.scheduler!r}; choose from "
                                  f"{', '.join(registry.JOB_SCHEDULERS)}")
        for name in ("cache", "max_samples_in_flight", "max_batch_rays", "threads",
                     "portal_interval", "portal_resolution", "memory_limit", "cache_bytes"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise JobOptionsError(f"job option {name!r} must be at least 1, got {value}")
        if self.history_depth is not None and self.history_depth < 0:
            raise JobOptionsError(f"--history-depth must not be negative, got "
                                  f"{self.history_depth}")
        if self.load_bandwidth is not None and not (
                self.load_bandwidth and all(0 < v < float("inf") for v in self.load_bandwidth)):
            raise JobOptionsError(f"--load-bandwidth must be positive MB/s, got "
                                  f"{list(self.load_bandwidth)}")
        if ((self.max_samples_in_flight is not None
             and not sched.accepts(Option.SAMPLES_IN_FLIGHT))
                or (not self.preload and not sched.accepts(Option.NO_PRELOAD))
                or (self.cold_reads and not sched.accepts(Option.COLD_READS))):
            raise JobOptionsError("--max-samples-in-flight, --no-preload and --cold-reads apply "
                                  "to the out-of-core schedulers, not to the in-core reference "
                                  "render (it loads each domain once)")
        if not self.resident_first and not sched.accepts(Option.RESIDENT_FIRST):
            raise JobOptionsError(f"resident_first chooses among domains in memory in the "
                                  f"{', '.join(registry.accepting(Option.RESIDENT_FIRST))} "
                                  f"schedules; --scheduler {self.scheduler} has no such choice")
        if (self.max_batch_rays != DEFAULT_MAX_BATCH_RAYS
                and not sched.accepts(Option.MAX_BATCH_RAYS)):
            raise JobOptionsError(f"max_batch_rays bounds the ray batches nodes send each other "
                                  f"({', '.join(registry.accepting(Option.MAX_BATCH_RAYS))}); "
                                  f"--scheduler {self.scheduler} sends none")
        if self.eviction not in EVICTIONS:
            raise JobOptionsError(f"unknown --eviction {self.eviction!r}; choose from "
                                  f"{', '.join(EVICTIONS)}")
        if self.eviction != "lru" and not sched.accepts(Option.EVICTION):
            raise JobOptionsError(f"--eviction chooses what the "
                                  f"{' and '.join(registry.accepting(Option.EVICTION))} "
                                  f"schedules evict; --scheduler {self.scheduler} has its own "
                                  "rule (drop --eviction)")
        if self.history_depth is not None and not sched.accepts(Option.HISTORY_DEPTH):
            raise JobOptionsError(f"--history-depth bounds spec-ooc's speculation; --scheduler "
                                  f"{self.scheduler} does not speculate (drop it or use "
                                  "--scheduler spec-ooc)")
        if self.simplified is not None:
            if self.simplified not in SIMPLIFIED_POLICIES:
                raise JobOptionsError(f"unknown --simplified policy {self.simplified!r}; "
                                      f"choose from {', '.join(SIMPLIFIED_POLICIES)}")
            if not sched.accepts(Option.SIMPLIFIED):
                raise JobOptionsError("--simplified works with --scheduler "
                                      f"{' or '.join(registry.accepting(Option.SIMPLIFIED))}")
        if self.portal_memory < 0:
            raise JobOptionsError(f"--portal-memory must not be negative, got "
                                  f"{self.portal_memory}")
        if self.portal_memory and self.simplified != "portal":
            raise JobOptionsError("--portal-memory accumulates the virtual portals of "
                                  "--simplified portal: give --simplified portal, or drop it")
        if self.portal_accuracy and self.simplified != "portal":
            raise JobOptionsError("--portal-accuracy measures the portals' predictions: use it "
                                  "with --simplified portal (and --frames 2 or more)")
        if self.assignment is not None and self.assignment not in ASSIGNMENTS:
            raise JobOptionsError(f"unknown --assignment {self.assignment!r}; choose from "
                                  f"{', '.join(ASSIGNMENTS)}")
        if self.priority is not None and self.priority not in PRIORITIES:
            raise JobOptionsError(f"unknown --priority {self.priority!r}; choose from "
                                  f"{', '.join(PRIORITIES)}")
        if ((self.assignment is not None and self.assignment not in sched.assignments)
                or (self.priority is not None and self.priority not in sched.priorities)):
            raise JobOptionsError("--assignment and --priority choose how --scheduler temporal "
                                  "plans (async takes only --assignment sequential so far)")

    def out_of_core(self, domains: int) -> bool:
        """Whether a process of this job caches fewer of a store's ``domains`` than it has
        (``cache`` set and below them)."""
        return self.cache is not None and self.cache < domains

    def load_bytes_per_second(self, rank: int = 0) -> float | None:
        """The emulated storage bandwidth of process ``rank`` in bytes/s (``load_bandwidth``
        cycled over the ranks), or None."""
        if self.load_bandwidth is None:
            return None
        return float(self.load_bandwidth[rank % len(self.load_bandwidth)]) * 1e6

    def to_wire(self) -> dict:
        """A msgpack-ready dict: the fields (tuples as lists) and ``version``."""
        wire = asdict(self)
        if self.load_bandwidth is not None:
            wire["load_bandwidth"] = list(self.load_bandwidth)
        wire["version"] = VERSION
        return wire

    @classmethod
    def from_wire(cls, wire: object) -> JobOptions:
        """The options a ``to_wire`` dict holds.

        Raises
        ------
        JobOptionsError
            For anything else: not a dict, another version, an unknown or missing field, a
            value of the wrong type or out of range.
        """
        if not isinstance(wire, dict):
            raise JobOptionsError(f"job options must be a dict, got {type(wire).__name__}")
        version = wire.get("version")
        if version != VERSION:
            raise JobOptionsError(f"job options version {version!r} is not this node's "
                                  f"({VERSION}): run the same vastray version on the "
                                  "coordinator and every node")
        names = {f.name for f in fields(cls)}
        unknown = sorted(str(k) for k in set(wire) - names - {"version"})
        if unknown:
            raise JobOptionsError(f"job options carry unknown field(s) {unknown[:5]} for "
                                  f"version {VERSION}: run the same vastray version on the "
                                  "coordinator and every node")
        missing = sorted(names - set(wire))
        if missing:
            raise JobOptionsError(f"job options lack field(s) {missing} of version {VERSION}")
        return cls(**{name: wire[name] for name in names})

    def for_report(self) -> dict:
        """The options as a report records them (JSON-ready)."""
        report = asdict(self)
        if self.load_bandwidth is not None:
            report["load_bandwidth"] = (self.load_bandwidth[0] if len(self.load_bandwidth) == 1
                                        else list(self.load_bandwidth))
        return report


_INT, _FLOAT = (int,), (int, float)
_TYPES = {
    "scheduler": str, "cache": _INT, "max_samples_in_flight": _INT, "history_depth": _INT,
    "max_batch_rays": _INT, "threads": _INT, "preload": bool, "build_ahead": bool,
    "trace_ahead": bool,
    "resident_first": bool,
    "load_bandwidth": tuple, "cold_reads": bool, "eviction": str, "simplified": str,
    "portal_interval": _INT,
    "portal_threshold": _FLOAT, "portal_resolution": _INT, "portal_accuracy": bool,
    "portal_memory": _INT, "assignment": str, "priority": str, "memory_limit": _INT,
    "cache_bytes": _INT,
}
_OPTIONAL = frozenset({"cache", "max_samples_in_flight", "history_depth", "threads",
                       "load_bandwidth", "simplified", "assignment", "priority",
                       "memory_limit", "cache_bytes"})
_TYPE_NAMES = {name: ("true or false" if kinds is bool else "a string" if kinds is str
                      else "a number" if kinds is _FLOAT else "a list" if kinds is tuple
                      else "an integer") + (" or None" if name in _OPTIONAL else "")
               for name, kinds in _TYPES.items()}
