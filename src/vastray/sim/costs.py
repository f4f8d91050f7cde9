"""The simulator's cost model: what each kind of work costs in virtual seconds.

``vastray calibrate`` measures these constants on the machine it runs on and writes them to a
JSON file; ``vastray simulate`` reads it and records it in its report, so a simulated figure
always says which machine's costs it stands for.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from vastray.scene.errors import InputError

#: The format of a calibration file; a file of another version is refused.
VERSION = 1


def aggregate_throughput(throughput: tuple, cores: int | None, busy: float) -> float:
    """The aggregate throughput, in single-process speeds, of ``busy`` (> 0, may be
    fractional) busy processes on ``cores`` cores that give ``throughput`` ((K,) with 1 .. K
    busy processes): interpolated between counts, under one process in proportion, beyond K
    the last value; empty: the ideal ``min(busy, cores)`` (``cores`` None: ``busy``)."""
    if not throughput:
        return float(min(busy, cores if cores is not None else busy))
    if busy <= 1.0:
        return float(busy * throughput[0])
    return float(np.interp(busy, np.arange(1, len(throughput) + 1), throughput))


@dataclass(frozen=True)
class CostModel:
    """Seconds charged per unit of work.

    Attributes
    ----------
    trace_ray_s : one radiance ray's closest-hit query against a loaded domain.
    shade_ray_s : the shading and bookkeeping of one radiance query's result (integrator,
        spawned rays, queues).
    shadow_ray_s : one shadow ray's occlusion query and what follows it (light brought
        home, queues).
    activation_s : one activation of a domain that traces radiance rays (its fixed cost:
        queue handling, kernel launches, shading set-up).
    shadow_activation_s : one activation that traces shadow rays only.

    camera_ray_s : making one camera ray (path context included).
    load_byte_s : reading one byte of a domain's files.
    build_triangle_s : building the BVH over one triangle, in CPU seconds of every thread
        Embree builds on (a large domain's build runs on every core; a node sharing its
        cores pays the CPU, not the wall time of the idle calibration machine).
    read_fixed_s, build_fixed_s : what a load's read and its build cost besides the bytes and
        the triangles (opening the files, checks, allocations; making the Embree scene). Here
        about 0.4 ms and 0.1-0.4 ms: for a store of small domains most of a load, so that
        folded into the per-unit costs (as calibrations before session 30 did) they charged a
        CT scan's domains, 10x the triangles of the calibration store's, 2.4x their real load.
    latency_s : one message between two nodes, end to end (encode, send, receive, decode).
    byte_s : one byte on the wire (the inverse of the bandwidth).
    receive_s : what one message costs the node that receives it beyond the raw wire's
        ``latency_s`` (its management actor's routing on the event loop, the checks of who
        may send what, the mailbox and the waiting ``receive``): measured between two of the
        nodes' own management actors (0.4-0.5 ms of CPU a batch here, against 0.1 ms one way
        on raw sockets), charged to the receiver's core before the message is in its
        mailbox; 0 (files written before it) charges nothing.
    warmup_s : what a fresh node pays once, at its first trace, of its first use of the
        render code beyond what it paid before its first hello (``actors.node_warm_up``:
        numba's set-up and every kernel's first call): first allocations, modules of its
        runtime imported on first use.
    node_setup_s : what a node of the asynchronous and domain runtimes pays once beyond
        ``warmup_s`` (worker and loader threads, first sockets to peers, first turns of its
        event loop).
    tile_setup_s : the same for a sort-first node (``image``, ``spec-ooc``), which runs the
        one-process runtime on a thread of its own.
    insitu_setup_s : the same for an in-situ node (``spec-insitu``), which loads its domains
        first and traces on its event loop's thread (no hand-off, no termination waves).
    page_fault_s : CPU seconds of one minor page fault: the first touch of a fresh 4 KiB page
        of memory, the kernel mapping and zeroing it (``sim.first_touch``; 2.6-3.6 us on this
        virtual machine).
    fresh_pages_per_path : pages a fresh node's render thread first touches per path in
        flight (its paths, ray batches, queues and film), measured on the calibration store
        (``sim.first_touch``): a fresh node pays ``first_touch_s`` of its paths once, at its
        first trace, which the simulator's own long-lived process, its heap touched long
        before, does not (real nodes: 10,000-30,000 faults a node in a 0.2-0.5 s busy span,
        30-80 ms). 0 (the default, and what calibration files written before it mean)
        charges nothing.
    decision_scale : virtual seconds charged per CPU second a schedule spends deciding
        (``next_domain`` with spec-ooc's filtering, ``likely_next``, the dynamic schedule's
        rounds), measured as the simulator runs the real schedule code (``launch.cpu_time``:
        the thread's CPU with its split pieces', so another process on the cores does not
        inflate it): 1.0 where the simulator runs on
        the calibrated machine (``vastray calibrate`` writes 1.0), 0 charges nothing (the
        default, and what calibration files written before it mean).
    trace_scale : virtual seconds charged per CPU second the simulator spends running an
        activation's real trace (``process``: queries, shading, forwarding, queues; measured
        with ``launch.cpu_time`` as it simulates): 1.0 where the simulator runs on the
        calibrated machine (``vastray calibrate`` writes 1.0), so an activation costs its own
        work on any store, bounce count and domain count; 0 charges the constants above
        (``trace_s``: the default, and what calibration files written before it mean). The
        constants are fitted on one store's tile and do not carry over: on 128 domains with
        3 bounces an activation took about 1.3 times what rm 64³'s 18 domains predicted.
    node_cpu_scale : virtual seconds charged per CPU second a virtual node's own code spends
        beyond the work charged apart (its frame loop, the film it folds paths into, the
        batches it cuts, its waves; ``sim.meter``), measured as the simulator runs it: 1.0
        where the simulator runs on the calibrated machine (``vastray calibrate`` writes
        1.0), 0 charges nothing (the default, and what calibration files written before it
        mean). Where it is set, making camera rays is measured with the rest
        (``camera_ray_s`` is not charged besides).
    load_scale : virtual seconds charged per CPU second a domain's load (its read and its BVH
        build at the node cache's build qualities) takes the simulator here
        (``sim.cache.Domains.load_cpu_s``: each domain timed once): 1.0 where the simulator
        runs on the calibrated machine (``vastray calibrate`` writes 1.0), 0 charges the
        constants (``read_s`` and ``build_s``: the default, and what calibration files
        written before it mean). A build's cost per triangle moves with the geometry: the
        turbine-blade scan's domains cost about a quarter more a triangle than rm 64³'s,
        whose builds the constants are fitted on.
    offload_s : one activation of a node runtime handed to a worker thread, beyond its trace:
        the hand-off there and back to the event loop (``DomainLoop`` with ``offload``,
        ``asyncio.to_thread``; ``domain_loop.hands_off``: activations of more than
        ``INLINE_RAYS`` rays, and every one of an asynchronous frame with peers). Sort-first
        and in-situ nodes, tracing on their own thread, do not pay it.
    cores : cores of the calibrated machine: node processes share this many when the
        simulator reproduces a run on it (None: every node has a core of its own).
    throughput : the calibrated machine's aggregate throughput with 1, 2, ... busy processes,
        in single-process speeds (empty: ideal, one core's worth per core).
    others : busy processes that are not the render's on the shared cores (a simulation
        beside it, another job; ``sim.steal.others_running``, fractional for work that comes
        and goes): the shared cores run them beside the nodes (``beside``). 0 from a
        calibration.
    machine : what machine the constants were measured on (free text for reports).
    """

    trace_ray_s: float = 1.5e-6
    shade_ray_s: float = 1.5e-6
    shadow_ray_s: float = 5e-7
    activation_s: float = 2e-4
    shadow_activation_s: float = 1e-4
    camera_ray_s: float = 2e-7
    load_byte_s: float = 1e-9
    build_triangle_s: float = 2e-7
    read_fixed_s: float = 0.0
    build_fixed_s: float = 0.0
    latency_s: float = 2e-4
    byte_s: float = 1e-9
    receive_s: float = 0.0
    warmup_s: float = 0.0
    node_setup_s: float = 0.0
    tile_setup_s: float = 0.0
    insitu_setup_s: float = 0.0
    page_fault_s: float = 0.0
    fresh_pages_per_path: float = 0.0
    decision_scale: float = 0.0
    trace_scale: float = 0.0
    node_cpu_scale: float = 0.0
    load_scale: float = 0.0
    offload_s: float = 0.0
    cores: int | None = None
    throughput: tuple = ()
    others: float = 0.0
    machine: dict = field(default_factory=dict)

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("machine", "cores", "throughput"):
                continue
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"cost {f.name} must be a finite number >= 0, got {value!r}")
        if self.cores is not None and (not isinstance(self.cores, int) or self.cores < 1):
            raise ValueError(f"cores must be a positive integer or None, got {self.cores!r}")
        throughput = tuple(self.throughput) if isinstance(self.throughput, (list, tuple)) \
            else (None,)
        if not all(isinstance(t, (int, float)) and math.isfinite(t) and t > 0
                   for t in throughput):
            raise ValueError(f"throughput must be positive numbers, got {self.throughput!r}")
        object.__setattr__(self, "throughput", throughput)

    def trace_s(self, radiance: int, shadow: int) -> float:
        """Seconds of one activation that makes ``radiance`` closest-hit and ``shadow``
        occlusion queries (and what follows them)."""
        fixed = self.activation_s if radiance else self.shadow_activation_s
        return (fixed + radiance * (self.trace_ray_s + self.shade_ray_s)
                + shadow * self.shadow_ray_s)

    def trace_charge(self, radiance: int, shadow: int, cpu_seconds: float) -> float:
        """Seconds charged for one activation's trace of ``radiance`` closest-hit and ``shadow``
        occlusion queries that took the simulator ``cpu_seconds`` of CPU to run: the CPU time
        times ``trace_scale`` where it is set, else the constants (``trace_s``)."""
        if self.trace_scale:
            return cpu_seconds * self.trace_scale
        return self.trace_s(radiance, shadow)

    def first_touch_s(self, paths: int) -> float:
        """Seconds a fresh node pays once to first touch the memory of ``paths`` paths in
        flight (``page_fault_s`` times ``fresh_pages_per_path`` a path)."""
        return self.page_fault_s * self.fresh_pages_per_path * max(paths, 0)

    def read_s(self, nbytes: int) -> float:
        """Seconds to read a domain of ``nbytes`` bytes from the store."""
        return self.read_fixed_s + nbytes * self.load_byte_s

    def build_s(self, triangles: int) -> float:
        """Seconds to build a domain's BVH over ``triangles``."""
        return self.build_fixed_s + triangles * self.build_triangle_s

    def load_s(self, nbytes: int, triangles: int) -> float:
        """Seconds to load a domain of ``nbytes`` bytes and build its BVH over ``triangles``."""
        return self.read_s(nbytes) + self.build_s(triangles)

    def message_s(self, nbytes: int) -> float:
        """Seconds from a message's send to its delivery."""
        return self.latency_s + nbytes * self.byte_s

    def with_cores(self, cores: int | None) -> CostModel:
        """The same costs with ``cores`` cores shared by the nodes (None: one each)."""
        return CostModel(**{**asdict(self), "cores": cores})

    def beside(self, others: float) -> CostModel:
        """The same costs on shared cores that also run ``others`` busy processes of others
        (>= 0; see the attribute). Without ``cores`` (a core a node), unchanged."""
        if not (math.isfinite(others) and others >= 0.0):
            raise ValueError(f"other processes must be a finite count >= 0, got {others!r}")
        if self.cores is None or others == 0.0:
            return self
        return replace(self, others=float(others))

    def throughput_at(self, busy: float) -> float:
        """The aggregate throughput, in single-process speeds, with ``busy`` (> 0, may be
        fractional) busy processes on the shared cores: ``throughput`` interpolated (beyond
        its end, its last value; empty: the ideal ``min(busy, cores)``)."""
        return aggregate_throughput(self.throughput, self.cores, busy)

    def stolen(self, share: float) -> CostModel:
        """The same costs on shared cores of which the host gave ``share`` (0 <= share < 1) of
        the wanted time to other machines (``sim.steal``): every entry of ``throughput`` (the
        ideal ``min(k, cores)`` where it is empty) times ``1 - share``, for 1 .. 2 x cores
        busy processes. Without ``cores`` (a core a node), unchanged."""
        if not 0.0 <= share < 1.0:
            raise ValueError(f"a stolen share must be in [0, 1), got {share!r}")
        if self.cores is None or share == 0.0:
            return self
        counts = max(len(self.throughput), 2 * self.cores)
        full = [self.throughput_at(k) for k in range(1, counts + 1)]
        return replace(self, throughput=tuple(t * (1.0 - share) for t in full))

    @classmethod
    def free(cls) -> CostModel:
        """Every cost 0 (a core a node, no throughput measured): what sets a few costs and
        charges nothing else, e.g. a node's decisions alone."""
        return cls(**{f.name: 0.0 for f in fields(cls)
                      if f.name not in ("cores", "machine", "throughput")})

    def warm(self) -> CostModel:
        """The same costs for nodes already started and warm (``warmup_s``, the set-ups and
        the first touch of memory 0: a long job's later frames, a running service)."""
        return CostModel(**{**asdict(self), "warmup_s": 0.0, "node_setup_s": 0.0,
                            "tile_setup_s": 0.0, "insitu_setup_s": 0.0,
                            "fresh_pages_per_path": 0.0})

    def as_dict(self) -> dict:
        return {"version": VERSION, **asdict(self)}

    def save(self, path: str | Path) -> None:
        """Write the model as JSON (written whole to a temporary name, then renamed)."""
        path = Path(path)
        partial = path.with_name(path.name + ".partial")
        partial.write_text(json.dumps(self.as_dict(), indent=2) + "\n")
        partial.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> CostModel:
        """Read a calibration file; a clear ``InputError`` names the file and the problem."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise InputError(path, "no such calibration file "
                                   "(write one with `vastray calibrate -o FILE`)") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(path, f"not a calibration file: {exc}") from None
        if not isinstance(data, dict) or data.get("version") != VERSION:
            raise InputError(path, f"calibration format version {data.get('version')!r} "
                                   f"is not {VERSION}; run `vastray calibrate` again"
                                   if isinstance(data, dict) else "not a JSON object")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known - {"version"})
        if unknown:
            raise InputError(path, f"unknown cost fields {unknown}")
        try:
            return cls(**{k: v for k, v in data.items() if k in known})
        except (TypeError, ValueError) as exc:
            raise InputError(path, str(exc)) from None
