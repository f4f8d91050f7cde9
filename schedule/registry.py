"""The schedulers, each declared once: its name, the runtime that runs it, the options it
accepts, its defaults and how the simulator runs it.

This module holds data only. The runtimes (``actors.local``, ``actors.node``,
``actors.decomposition``, ``vastray.sim.simulate``), the option checks (``actors.job_options``,
the CLI) and the reports read these attributes and dispatch on them; no other module compares
scheduler names (``tests/test_scheduler_registry.py`` checks the source). A new scheduler is a
new ``SchedulerSpec`` in ``SPECS`` plus the runner its attributes select.

Layering: ``schedule/`` imports ``scene`` and ``render`` only, so the registry names the
runtimes by kind (``Runtime``, ``Decomposition``, ``Simulation``), not by their functions.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from vastray.scene.errors import InputError

__all__ = ["Decomposition", "JOB_SCHEDULERS", "Option", "RENDER_CHOICES", "Runtime",
           "SIMULATE_CHOICES", "SPECS", "SchedulerSpec", "Simulation", "UnknownScheduler",
           "accepting", "find", "names", "resolve", "running", "spec"]


class Runtime(Enum):
    """Which runtime runs a scheduler's jobs."""

    #: Not a schedule: a name the CLI resolves to another scheduler before the job (``auto``).
    RESOLVED = "resolved to another scheduler before the job"
    #: The in-core reference: one process, every wavefront through all its domains
    #: (``render.driver.render``).
    IN_CORE = "in core, one process"
    #: Out of core in tiles of paths: one process, or each node its sort-first share of the
    #: tiles (``actors.local.render_out_of_core``).
    TILES = "out-of-core tiles: one process, or sort-first tiles on every node"
    #: Domains owned by nodes, rays sent between them (``actors.decomposition``); --nodes only.
    DOMAINS = "domain decomposition over nodes"
    #: SpRay in situ: each node keeps all its own domains loaded (``actors.insitu``);
    #: --nodes only.
    IN_SITU = "in situ over nodes"

    @property
    def on_nodes(self) -> bool:
        """Its jobs run on nodes (``render_distributed``)."""
        return self in (Runtime.TILES, Runtime.DOMAINS, Runtime.IN_SITU)

    @property
    def nodes_only(self) -> bool:
        """It distributes domains over nodes: a job needs ``--nodes``."""
        return self in (Runtime.DOMAINS, Runtime.IN_SITU)


class Decomposition(Enum):
    """How a ``Runtime.DOMAINS`` frame moves rays between nodes (``actors.decomposition``)."""

    #: Navrátil's static domain schedule: tiles traced in bulk-synchronous rounds.
    ROUNDS = "static ownership, bulk-synchronous rounds"
    #: Navrátil's dynamic schedule: ray-weighted rounds re-assigning domains, the next tile
    #: taken in while the last one's rays thin out.
    RAY_WEIGHTED = "ray-weighted rounds re-assigning domains"
    #: Galaxy: no global rounds, credit-based injection, termination detection per frame.
    ASYNC = "owned domains, no global rounds"
    #: Xu et al. 2022: async with each frame's domain groups and screen tiles planned from the
    #: last frame's ray statistics.
    PLANNED = "async, each frame planned from the last one's ray statistics"

    @property
    def rounds(self) -> bool:
        """Rays move in rounds that end with all-reductions over the butterfly of ranks
        (``domain``: each tile's rounds in turn; ``dynamic``: the frame's, two tiles
        overlapping, ``DynamicFrame``); else the whole frame runs without rounds, as one
        ``AsyncFrame`` or ``TemporalFrame``."""
        return self in (Decomposition.ROUNDS, Decomposition.RAY_WEIGHTED)


class Simulation(Enum):
    """How ``vastray simulate`` runs a scheduler on virtual nodes (``sim.simulate``)."""

    #: The out-of-core tile loop of ``actors.local`` on virtual time, each node its
    #: sort-first tiles.
    SORT_FIRST = "the sort-first tile loop on virtual time"
    #: The nodes' own ``actors.decomposition.render_owned_domains``.
    DOMAINS = "the nodes' domain decomposition"
    #: The nodes' own ``actors.insitu.render_spec_insitu``.
    IN_SITU = "the nodes' in-situ runtime"


class Option(Enum):
    """A job option some schedulers read and others refuse (the value: the command line's)."""

    CACHE = "--cache"
    BATCH_SIZE = "--batch-size"
    SAMPLES_IN_FLIGHT = "--max-samples-in-flight"
    HISTORY_DEPTH = "--history-depth"
    #: turning preloading off (every scheduler that preloads)
    NO_PRELOAD = "--no-preload"
    COLD_READS = "--cold-reads"
    #: turning ``resident_first`` off: the schedule chooses among domains in memory first
    RESIDENT_FIRST = "resident_first"
    #: the ray batches nodes send each other (``max_batch_rays``)
    MAX_BATCH_RAYS = "max_batch_rays"
    #: an eviction rule other than ``lru``
    EVICTION = "--eviction"
    SIMPLIFIED = "--simplified"


#: Names of the domain assignments and priorities, defined once here (the registry loads
#: nothing heavy): ``schedule.temporal``, the job options and the CLI take them from it.
ASSIGNMENTS = ("sequential", "spatial", "paper", "affinity", "fit")
PRIORITIES = ("queue", "spray", "queue+act", "cost-benefit", "cost-rate", "queue+resident")


@dataclass(frozen=True)
class SchedulerSpec:
    """One scheduler, declared once.

    Attributes
    ----------
    name : what ``--scheduler`` and ``JobOptions.scheduler`` call it.
    runtime : which runtime runs its jobs.
    summary : what it does, in one line.
    lossless : its image is the in-core reference's, sample for sample.
    speculates : it traces rays speculatively before their hits resolve (SpRay's schedules;
        among the tile schedulers, the ``SpeculativeSchedule`` rather than the
        ``ImageSchedule``).
    evicts : its schedule is handed the cache's next eviction victim and serves that domain's
        rays before it goes (spec-ooc's ``serve_before_evict``).
    options : the options of ``Option`` it reads; the others are refused when given.
    assignments : the ``--assignment`` values it takes (empty: none).
    priorities : the ``--priority`` values it takes (empty: none).
    default_assignment, default_priority : what it uses where none is given (None: no choice).
    frame_statistics : it keeps (D, D) ray statistics of each frame (bounded domain count,
        memory per node).
    decomposition : how its frames move rays (``Runtime.DOMAINS`` only).
    simulation : how ``vastray simulate`` runs it (None: not simulated).
    nodes_as : the scheduler its jobs run as on nodes where it cannot run there itself (the
        in-core reference: ``image``, the same image); None: itself.
    resolves : (when every domain fits in the cache, otherwise): the schedulers a
        ``Runtime.RESOLVED`` name stands for.
    policies : the ``schedule/`` objects that make its decisions (dotted names).
    """

    name: str
    runtime: Runtime
    summary: str
    lossless: bool = True
    speculates: bool = False
    evicts: bool = False
    options: frozenset[Option] = frozenset()
    assignments: tuple[str, ...] = ()
    priorities: tuple[str, ...] = ()
    default_assignment: str | None = None
    default_priority: str | None = None
    frame_statistics: bool = False
    decomposition: Decomposition | None = None
    simulation: Simulation | None = None
    nodes_as: str | None = None
    resolves: tuple[str, str] | None = None
    policies: tuple[str, ...] = ()

    def accepts(self, option: Option) -> bool:
        """It reads ``option`` (else the option is refused when given)."""
        return option in self.options

    @property
    def on_nodes(self) -> str:
        """The scheduler its jobs run as with ``--nodes``."""
        return self.nodes_as or self.name

    @property
    def tile_copies(self) -> bool:
        """Its tiles hold speculative copies of their shadow rays, which a memory estimate
        counts (``preflight.speculative_copies``: spec-ooc's)."""
        return self.speculates and self.runtime is Runtime.TILES


_OUT_OF_CORE = frozenset({Option.CACHE, Option.SAMPLES_IN_FLIGHT, Option.NO_PRELOAD,
                          Option.COLD_READS})
_TILES = _OUT_OF_CORE | {Option.RESIDENT_FIRST, Option.EVICTION}
_BATCHING = _OUT_OF_CORE | {Option.MAX_BATCH_RAYS}

#: Every scheduler, in the order ``vastray render --help`` lists them.
SPECS: tuple[SchedulerSpec, ...] = (
    SchedulerSpec(
        "auto", Runtime.RESOLVED,
        "reference when every domain fits in the cache, else spec-ooc (the CLI's default)",
        resolves=("reference", "spec-ooc")),
    SchedulerSpec(
        "reference", Runtime.IN_CORE,
        "each wavefront traced through all the domains it enters, every domain loaded once",
        options=frozenset({Option.CACHE, Option.BATCH_SIZE}), nodes_as="image",
        policies=("vastray.render.driver.render",)),
    SchedulerSpec(
        "image", Runtime.TILES,
        "rays queued per domain, the fullest queue processed (SpRay's baseline)",
        options=_TILES, simulation=Simulation.SORT_FIRST,
        policies=("vastray.schedule.image.ImageSchedule",)),
    SchedulerSpec(
        "spec-ooc", Runtime.TILES,
        "SpRay's speculative out-of-core schedule",
        speculates=True, evicts=True, options=_TILES | {Option.HISTORY_DEPTH},
        simulation=Simulation.SORT_FIRST,
        policies=("vastray.schedule.spec_ooc.SpeculativeSchedule",
                  "vastray.schedule.traversal", "vastray.schedule.belady")),
    SchedulerSpec(
        "domain", Runtime.DOMAINS,
        "static domain ownership, synchronous rounds",
        options=_BATCHING, decomposition=Decomposition.ROUNDS, simulation=Simulation.DOMAINS,
        policies=("vastray.schedule.image.ImageSchedule", "vastray.schedule.ownership")),
    SchedulerSpec(
        "async", Runtime.DOMAINS,
        "owned domains, rays move without global rounds (Galaxy)",
        options=_BATCHING | {Option.RESIDENT_FIRST, Option.SIMPLIFIED},
        assignments=("sequential",), decomposition=Decomposition.ASYNC,
        simulation=Simulation.DOMAINS,
        policies=("vastray.schedule.galaxy", "vastray.schedule.ownership",
                  "vastray.schedule.simplified", "vastray.schedule.portals")),
    SchedulerSpec(
        "dynamic", Runtime.DOMAINS,
        "Navrátil's ray-weighted rounds re-assigning domains",
        options=_BATCHING, decomposition=Decomposition.RAY_WEIGHTED,
        simulation=Simulation.DOMAINS,
        policies=("vastray.schedule.dynamic", "vastray.schedule.image.ImageSchedule")),
    SchedulerSpec(
        "spec-insitu", Runtime.IN_SITU,
        "SpRay in situ: z-order ownership, speculation, t-buffer MIN / o-buffer OR all-reduce",
        speculates=True, options=_OUT_OF_CORE - {Option.CACHE},
        simulation=Simulation.IN_SITU,
        policies=("vastray.schedule.spec_insitu", "vastray.schedule.ownership")),
    SchedulerSpec(
        "temporal", Runtime.DOMAINS,
        "async with each frame's domain groups and screen tiles planned from the last frame's "
        "ray statistics, and cost-based preloading (Xu et al. 2022)",
        options=_BATCHING | {Option.SIMPLIFIED},
        assignments=ASSIGNMENTS, priorities=PRIORITIES,
        default_assignment="affinity", default_priority="cost-rate", frame_statistics=True,
        decomposition=Decomposition.PLANNED, simulation=Simulation.DOMAINS,
        policies=("vastray.schedule.temporal", "vastray.schedule.simplified",
                  "vastray.schedule.portals")),
)

_BY_NAME = {s.name: s for s in SPECS}


class UnknownScheduler(InputError):
    """A scheduler name the registry does not know; the message lists the valid ones."""

    def __init__(self, name: object):
        self.name = name
        super().__init__(None, f"unknown scheduler {name!r}; choose from "
                               f"{', '.join(_BY_NAME)}")


def find(name: object) -> SchedulerSpec | None:
    """The scheduler called ``name``, or None."""
    return _BY_NAME.get(name) if isinstance(name, str) else None


def spec(name: str) -> SchedulerSpec:
    """The scheduler called ``name``.

    Raises
    ------
    UnknownScheduler
        For any other name (an ``InputError`` whose message lists the valid names).
    """
    found = find(name)
    if found is None:
        raise UnknownScheduler(name)
    return found


def names(where=lambda s: True) -> tuple[str, ...]:
    """The names of the schedulers ``where(spec)`` holds for, in ``SPECS``' order."""
    return tuple(s.name for s in SPECS if where(s))


def accepting(option: Option) -> tuple[str, ...]:
    """The schedulers that read ``option``, in ``SPECS``' order."""
    return names(lambda s: s.accepts(option))


def running(*runtimes: Runtime) -> tuple[str, ...]:
    """The schedulers run by any of ``runtimes``, in ``SPECS``' order."""
    return names(lambda s: s.runtime in runtimes)


def resolve(name: str, fits: bool) -> str:
    """The scheduler a job runs for ``name``: itself, or for a ``Runtime.RESOLVED`` name the
    one it stands for when every domain fits in the cache (``fits``) or when they do not."""
    found = spec(name)
    if found.resolves is None:
        return found.name
    return found.resolves[0] if fits else found.resolves[1]


#: ``vastray render --scheduler``'s choices, in its --help's order.
RENDER_CHOICES: tuple[str, ...] = names()
#: The schedulers a job (``JobOptions.scheduler``) may name: every one but those resolved first.
JOB_SCHEDULERS: tuple[str, ...] = names(lambda s: s.runtime is not Runtime.RESOLVED)
#: ``vastray simulate --scheduler``'s choices, in its --help's order (every scheduler with a
#: ``simulation``, as the simulator's reports have always listed them).
SIMULATE_CHOICES: tuple[str, ...] = tuple(
    _BY_NAME[n].name for n in ("image", "spec-ooc", "domain", "dynamic", "async", "spec-insitu",
                               "temporal"))


def _check() -> None:
    """The declarations fit together (run on import: a wrong one fails at once)."""
    assert len(_BY_NAME) == len(SPECS), "two schedulers of one name"
    assert set(SIMULATE_CHOICES) == set(names(lambda s: s.simulation is not None))
    for s in SPECS:
        assert (s.decomposition is not None) == (s.runtime is Runtime.DOMAINS), s.name
        assert (s.resolves is not None) == (s.runtime is Runtime.RESOLVED), s.name
        assert s.resolves is None or all(r in JOB_SCHEDULERS for r in s.resolves), s.name
        assert s.nodes_as is None or _BY_NAME[s.nodes_as].runtime.on_nodes, s.name
        assert s.default_assignment is None or s.default_assignment in s.assignments, s.name
        assert s.default_priority is None or s.default_priority in s.priorities, s.name


_check()
