"""The simulator at the papers' work per node: each scheduler replayed over one frame's
recorded domain crossings (``sim.crossings``) instead of tracing.

``sim.simulate`` runs the nodes' own code, traces included, which is exact but costs a real
trace per virtual activation: a few thousand paths on a thousand nodes. Here the rays are
traced once (``record_crossings``), and each scheduler's *policy* is replayed over them for any
node count: which node holds which ray, which domain it traces next, what it loads, what it
sends and where it waits, with the same ``CostModel`` as ``sim.simulate`` charged per
activation, load, message and reduction step. A replay step is a few array operations over a
batch of rays, never a loop per ray, so 2^20 paths on 1,024 nodes replay in seconds.

What is modelled, per scheduler (the runtimes' docstrings say what they do):

- ``domain`` (Navrátil's static schedule): tiles of ``tile`` paths in bulk-synchronous rounds;
  in a round a node traces every ray waiting for its domains, following rays that stay on
  its domains (one activation per domain and wave), ships the rest when it is done (a batch
  per peer and kind), and the round ends with an all-reduction over the butterfly of ranks
  (``transport.tree.butterfly_steps``: log2 P message steps, two more where P is no power
  of two).
- ``dynamic`` (ray-weighted): rays start on the node that made them; each round the real
  ``RayWeightedRounds`` assigns domains from the summed ray counts and the holders, rays move
  to their domain's node, each node traces its assigned domains once (when the last batch
  for it is sent); one all-reduction a round. A round whose rays waiting were under an eighth
  of a tile's paths, none for a domain no node holds, takes the next tile in at its end (at
  most two tiles in flight), as the nodes' ``DynamicFrame`` does (``takes_next_tile``).
- ``async`` (Galaxy): no rounds; each node, whenever free, injects its share of the next tile
  if fewer than ``tile`` rays wait there, else traces its fullest domain (cached first) and
  ships what that produced; messages arrive after their network time; the frame ends with
  the termination detection's two waves over the tree.
- ``spec-insitu`` (SpRay in situ): per tile, one iteration per bounce; a ray's copies go to
  the owners of every domain its line crosses (z-order runs of equal triangles,
  ``ownership.insitu_owners``), each node traces its copies,
  then the t-buffer and o-buffer all-reduction resolves the iteration (as the nodes': an
  8-byte key a path and a bit a shadow slot, over the tile's paths in the first iteration
  and those whose last iteration hit something after it; before session 50 the replay
  charged two all-reductions of 8 bytes a live path, where the second is the batches' (P,)
  counts). The copies travel over the two hops of ``schedule.relay`` (a batch per pair of
  its routes, queue and hop; before session 52 straight, a batch per pair that had copies,
  and the (P,) counts summed over the tree first).
- ``image`` and ``spec-ooc`` (sort-first): each node traces its tiles alone through an LRU
  cache of ``cache`` domains, the fullest (cached first) domain next; ``spec-ooc`` queues a
  ray's copies in every domain its line crosses, commits its hit once the domains it needs
  are traced (its children start then) and drops the copies left.

Limits, said where they matter: a load's read is not overlapped with tracing (the real nodes'
preloader hides part of it, so loads are pessimistic); an activation's rays are those waiting
when it starts (as the real loops); speculative copies beyond a ray's hit are charged as
traced where they were traced before the hit was known, and shading of speculative local hits
in ``spec-insitu`` is not charged.
"""

from __future__ import annotations

import heapq
import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np

from vastray.actors.job_options import DEFAULT_NODE_TILE, default_tile
from vastray.schedule import registry
from vastray.schedule.registry import Decomposition, Simulation
from vastray.sim.costs import CostModel
from vastray.sim.crossings import RADIANCE, Crossings, ranges
from vastray.transport.tree import butterfly, butterfly_steps, scatters, tree_steps

#: A sort-first node's paths in flight, and a domain-decomposition job's on up to 16 nodes
#: (``job_options.default_tile``, the coordinator's default).
DEFAULT_TILE = DEFAULT_NODE_TILE
#: Activations of more rays than this are handed to a worker thread in the node runtimes
#: (``actors.domain_loop.INLINE_RAYS``).
INLINE_RAYS = 1024
#: Bytes of a message's header (kind, metadata) beside its rays.
HEADER_BYTES = 64
#: How the replay runs each kind of scheduler (``schedule.registry``'s attributes: the sort-first
#: tiles, each ``Decomposition`` of the domain runtimes but ``temporal``'s planned one, and
#: in situ).
_REPLAYED_DECOMPOSITIONS = (Decomposition.ROUNDS, Decomposition.RAY_WEIGHTED,
                            Decomposition.ASYNC)


def replayed(spec: registry.SchedulerSpec | None) -> bool:
    """Whether the replay models this scheduler."""
    return spec is not None and (
        spec.simulation in (Simulation.SORT_FIRST, Simulation.IN_SITU)
        or (spec.simulation is Simulation.DOMAINS
            and spec.decomposition in _REPLAYED_DECOMPOSITIONS))


#: The schedulers the replay models, in ``registry.SPECS`` order.
REPLAY_SCHEDULERS = tuple(spec.name for spec in registry.SPECS if replayed(spec))


@dataclass(frozen=True)
class Network:
    """The wire between nodes, beyond the CPU a message costs its sender
    (``CostModel.message_s``): ``latency_s`` per message and ``bandwidth`` bytes per second
    (``inf``: loopback, as the calibration measured it)."""

    latency_s: float = 0.0
    bandwidth: float = math.inf

    def wire_s(self, nbytes: float) -> float:
        return self.latency_s + nbytes / self.bandwidth


@dataclass
class ReplayResult:
    """A replayed render.

    Attributes
    ----------
    scheduler, nodes : what was replayed.
    seconds : virtual seconds of the frame (the last node's end; reductions of the film
        after it are not in it, as in ``SimResult.seconds``).
    breakdown : mean seconds per node of ``trace`` (activations), ``load`` (reads and
        builds), ``messages`` (the sender's cost of ray batches), ``reduction`` (all-reductions
        and termination waves) and ``wait`` (the rest: idle, waiting for rays or a round).
    counters : ``activations``, ``loads``, ``messages``, ``bytes``, ``rounds`` (global
        synchronisations), ``traced`` (ray-domain tests, speculative copies included).
    wall_s : real seconds the replay took.
    busiest : the busiest node's seconds by the same kinds as ``breakdown`` (``wait`` left
        out) and its ``rank``: where the frame's critical path spends its time.
    """

    scheduler: str
    nodes: int
    seconds: float
    breakdown: dict
    counters: dict
    wall_s: float = 0.0
    busiest: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"scheduler": self.scheduler, "nodes": self.nodes,
                "seconds": round(self.seconds, 6),
                "breakdown": {k: round(v, 6) for k, v in self.breakdown.items()},
                "counters": self.counters, "wall_s": round(self.wall_s, 3),
                "busiest": self.busiest}


class _Lru:
    """A node's cache of ``capacity`` domains, least recently used evicted; ``mask`` ((D,)
    bool, where the store's size is given) says which are held."""

    __slots__ = ("capacity", "held", "loads", "mask")

    def __init__(self, capacity: int, n_domains: int = 0):
        self.capacity, self.held, self.loads = max(1, capacity), OrderedDict(), 0
        self.mask = np.zeros(n_domains, bool)

    def touch(self, domain: int) -> bool:
        """Use ``domain``; True when it had to be loaded."""
        if domain in self.held:
            self.held.move_to_end(domain)
            return False
        if len(self.held) >= self.capacity:
            evicted, _ = self.held.popitem(last=False)
            if len(self.mask):
                self.mask[evicted] = False
        self.held[domain] = None
        if len(self.mask):
            self.mask[domain] = True
        self.loads += 1
        return True


@dataclass
class _Ledger:
    """Per-node seconds by kind, and the counters."""

    size: int
    trace: np.ndarray = field(init=False)  # (P,) each
    load: np.ndarray = field(init=False)
    messages: np.ndarray = field(init=False)
    reduction: np.ndarray = field(init=False)
    own: np.ndarray = field(init=False)  # the nodes' own code (``NodeOwnCosts``)
    counters: dict = field(default_factory=lambda: {"activations": 0, "loads": 0,
                                                    "messages": 0, "bytes": 0, "rounds": 0,
                                                    "traced": 0})

    def __post_init__(self):
        for name in ("trace", "load", "messages", "reduction", "own"):
            setattr(self, name, np.zeros(self.size))

    def held(self, node: np.ndarray) -> None:
        """Count rays held: (n,) the node each ray waiting waits on; the counter
        ``most_rays_held`` keeps the most any node held at once (a round's start, for the
        round schedulers), a measure of a node's memory for rays."""
        if len(node):
            most = int(np.bincount(node, minlength=self.size).max())
            self.counters["most_rays_held"] = max(self.counters.get("most_rays_held", 0), most)

    def result(self, scheduler: str, seconds: float, start: float) -> ReplayResult:
        busy = self.trace + self.load + self.messages + self.reduction + self.own
        breakdown = {"trace": float(self.trace.mean()), "load": float(self.load.mean()),
                     "messages": float(self.messages.mean()),
                     "reduction": float(self.reduction.mean()), "own": float(self.own.mean()),
                     "wait": float(max(seconds - busy.mean(), 0.0))}
        rank = int(np.argmax(busy))
        busiest = {"rank": rank, **{name: float(getattr(self, name)[rank]) for name in
                                    ("trace", "load", "messages", "reduction", "own")}}
        return ReplayResult(scheduler, self.size, seconds, breakdown, dict(self.counters),
                            time.perf_counter() - start, busiest)


#: The all-reductions' patterns the replay charges: message steps on the critical path.
REDUCTIONS = {"butterfly": butterfly_steps, "tree": tree_steps}


class Replay:
    """One recorded frame, replayable under every scheduler of ``REPLAY_SCHEDULERS``.

    Parameters
    ----------
    crossings : the frame's recording.
    nbytes, triangles : (D,) each domain's bytes on storage and triangles (a load's cost).
    lo, hi : (D, 3) domain boxes (``spec-insitu``'s z-order groups).
    costs : the cost model (its ``cores`` ignored: a core per node).
    activations : what an activation costs (default: ``fit_activation_costs`` on the
        recording: this store's per-ray costs with the model's fixed ones).
    network : the wire beyond the messages' CPU cost.
    storage_bandwidth : bytes per second a node reads a domain at, at most (None: the
        calibrated ``read_s``; else the slower of the two, as ``DomainCache.load`` throttles).
    tile : paths in flight per tile; None: the coordinator's default for the scheduler and
        node count replayed (``job_options.default_tile``).
    own : each scheduler's nodes' own code (``fit_node_own_costs``; default: none charged).
    loads : (D,) read and (D,) build seconds of each domain's load, where measured
        (``sim.cache.Domains.load_seconds`` times ``CostModel.load_scale``, as the real-code
        simulator charges them); default: the constants (``read_s``, ``build_s``).
    reduction : the all-reductions' pattern, a key of ``REDUCTIONS``: ``"butterfly"`` (the
        product's) or ``"tree"`` (the first design's reduce and broadcast, for comparison:
        ``bench/replay_variants.py``).
    fill_busy : ``dynamic``'s rule 3 gives busy nodes unheld domains too (the product's,
        ``RayWeightedRounds``); False: only idle nodes, the paper's (for comparison).

    Attributes
    ----------
    insitu_routes : ``spec-insitu``'s copies over ``"relay"``, the two hops of
        ``schedule.relay`` (the product's), or ``"straight"``, a batch per pair with copies
        and the batches' (P,) counts all-reduced first (before session 52).
    insitu_holders : ``"camera"``, ``ownership.insitu_holders`` weighted by the camera
        rays' crossings (the product's since session 52: the nodes weigh a grid of at most
        ``spec_insitu.CROSSING_PROBES`` camera rays, the replay the recording's camera
        rays, and bound the extra holders by the domains' bytes on storage where the nodes
        take their resident bytes, ``preflight.domain_footprints``), or ``"owner"``, each
        domain held by its owner alone (before; SpRay's), or an ``ownership.Holders`` to
        replay with.
    """

    def __init__(self, crossings: Crossings, nbytes: np.ndarray, triangles: np.ndarray,
                 lo: np.ndarray, hi: np.ndarray, costs: CostModel,
                 activations: ActivationCosts | None = None,
                 network: Network = Network(), storage_bandwidth: float | None = None,
                 tile: int | None = None, own: dict[str, NodeOwnCosts] | None = None,
                 loads: tuple[np.ndarray, np.ndarray] | None = None,
                 reduction: str = "butterfly", fill_busy: bool = True):
        if reduction not in REDUCTIONS:
            raise ValueError(f"reduction must be one of {', '.join(REDUCTIONS)}, "
                             f"not {reduction!r}")
        #: message steps on an all-reduction's critical path over P nodes
        self.reduction_steps = REDUCTIONS[reduction]
        self.fill_busy = fill_busy
        self.c = crossings
        self.costs, self.network = costs, network
        #: each scheduler's ``NodeOwnCosts`` (none: charged as nothing)
        self.own_by_scheduler = own or {}
        self.own = NodeOwnCosts()  # the scheduler being replayed's
        self.activation = (fit_activation_costs(crossings, costs) if activations is None
                           else activations)
        self.lo, self.hi = lo, hi
        self.triangles = np.asarray(triangles, np.int64)  # (D,) ``spec-insitu``'s owners
        self.nbytes = np.asarray(nbytes, np.int64)
        self.insitu_routes, self.insitu_holders = "relay", "camera"
        #: the tile asked for (None: ``default_tile``'s), and the one of the run under way
        self.tile_asked = tile
        self.tile = DEFAULT_TILE if tile is None else tile
        self.n_domains = crossings.n_domains
        if loads is None:
            read = costs.read_fixed_s + nbytes * costs.load_byte_s
            build = costs.build_fixed_s + triangles * costs.build_triangle_s
        else:
            read, build = (np.asarray(seconds, np.float64) for seconds in loads)
        if storage_bandwidth is not None:  # as ``DomainCache.load``: the read waits out the rest
            read = np.maximum(read, nbytes / storage_bandwidth)
        #: (D,) seconds to load each domain (read, then build)
        self.load_s = read + build
        self._index()

    # -- the recording as arrays of visits ------------------------------------------------
    def _index(self) -> None:
        c = self.c
        visits = self.visits = c.visits  # (S,) domains each segment is traced in
        self.copies = c.copies  # (S,) domains each segment's line crosses
        n_seg = len(c)
        self.seg_of = np.repeat(np.arange(n_seg), visits)  # (V,) each visit's segment
        self.domain_of = c.visit_domain.astype(np.int64)  # (V,)
        self.radiance_of = c.kind[self.seg_of] == RADIANCE  # (V,)
        self.path_of = c.path[self.seg_of]  # (V,)
        last = np.zeros(len(self.seg_of), bool)
        ends = c.visit_first[1:][visits > 0] - 1
        last[ends] = True
        first, child = self.children = c.children()
        traced_child = child[visits[child] > 0]  # children that visit any domain
        per_parent = np.bincount(c.parent[traced_child], minlength=n_seg)
        n_succ = np.where(last, per_parent[self.seg_of], 1).astype(np.int64)
        self.succ_first = np.concatenate([[0], np.cumsum(n_succ)]).astype(np.int64)
        succ = np.empty(int(self.succ_first[-1]), np.int64)
        inner = np.nonzero(~last)[0]
        succ[self.succ_first[inner]] = inner + 1
        ends = np.nonzero(last)[0]
        succ[ranges(self.succ_first[ends], n_succ[ends])] = c.visit_first[traced_child]
        self.succ = succ
        camera = np.nonzero((c.parent < 0) & (visits > 0))[0]
        self.camera_visits = c.visit_first[camera]  # (n,) first visits of camera rays

    def successors(self, tokens: np.ndarray) -> np.ndarray:
        """The visits that follow ``tokens`` (visit ids): the same ray's next domain, or the
        rays a final hit spawned."""
        counts = self.succ_first[tokens + 1] - self.succ_first[tokens]
        return self.succ[ranges(self.succ_first[tokens], counts)]

    def _trace_s(self, radiance: int, shadow: int, decision_s: float | None = None) -> float:
        """One activation's seconds, its decision (``decision_s``, default the recording's)
        included."""
        a = self.activation
        return ((a.fixed_s if radiance else a.fixed_shadow_s) + radiance * a.radiance_s
                + shadow * a.shadow_s + (a.decision_s if decision_s is None else decision_s))

    def _ray_bytes(self, tokens: np.ndarray) -> float:
        radiance = int(np.count_nonzero(self.radiance_of[tokens]))
        b = self.c.ray_bytes
        return radiance * float(b[0]) + (len(tokens) - radiance) * float(b[1]) + HEADER_BYTES

    def _step_s(self, nbytes: float) -> float:
        """One message step of a reduction: sent, on the wire, received."""
        return (self.costs.message_s(nbytes) + self.network.wire_s(nbytes)
                + self.costs.receive_s)

    def _allreduce_s(self, size: int, nbytes: float = 64.0) -> float:
        """An all-reduction (``actors.tree_reduce``: over the butterfly of ranks, its
        ``butterfly_steps`` exchanges one after another), each step a message of ``nbytes``;
        of a long array (``transport.tree.scatters``) halving then doubling, step s's two
        messages of ``nbytes`` / 2^(s+1)."""
        if self.reduction_steps is butterfly_steps and scatters(size, int(nbytes)):
            core, steps = butterfly(size)
            halves = sum(self._step_s(nbytes / 2 ** (step + 1)) for step in range(steps))
            return 2 * halves + (2 * self._step_s(nbytes) if size > core else 0.0)
        return self.reduction_steps(size) * self._step_s(nbytes)

    def _wave_s(self, size: int) -> float:
        """A termination wave over the binary tree of ranks (``actors.tree_termination``):
        ceil(log2 P) steps down and as many replies up."""
        return tree_steps(size) * self._step_s(64.0)

    def _tiles(self, tokens: np.ndarray) -> list[np.ndarray]:
        """``tokens`` split by tile of paths, in tile order."""
        tile_of = self.path_of[tokens] // self.tile
        order = np.argsort(tile_of, kind="stable")
        bounds = np.searchsorted(tile_of[order], np.arange(tile_of.max() + 2 if len(tokens)
                                                           else 1))
        return [order[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]

    # -- the schedulers -----------------------------------------------------------------------
    def run(self, scheduler: str, nodes: int, cache: int | None = None) -> ReplayResult:
        """Replay ``scheduler`` on ``nodes`` nodes with a core each; ``cache``: domains a node
        holds (default: the product's, every domain it owns, or all for sort-first)."""
        spec = registry.find(scheduler)
        if not replayed(spec):
            raise ValueError(f"the replay models {', '.join(REPLAY_SCHEDULERS)}, not "
                             f"{scheduler!r}")
        if nodes < 1:
            raise ValueError("the replay needs at least 1 node")
        start = time.perf_counter()
        self.own = self.own_by_scheduler.get(scheduler, NodeOwnCosts())
        self.tile = (default_tile(scheduler, nodes) if self.tile_asked is None
                     else self.tile_asked)
        owned = -(-self.n_domains // nodes)
        if spec.simulation is Simulation.SORT_FIRST:
            ledger, seconds = self._sort_first(nodes, cache or self.n_domains, spec.speculates,
                                               scheduler)
        elif spec.simulation is Simulation.IN_SITU:
            ledger, seconds = self._insitu(nodes)
        else:
            run = {Decomposition.ROUNDS: self._rounds, Decomposition.RAY_WEIGHTED: self._dynamic,
                   Decomposition.ASYNC: self._async}[spec.decomposition]
            ledger, seconds = run(nodes, cache or owned)
        # every node's frame set-up at the start, all at once: the whole frame later by it
        ledger.own += self.own.per_node_s
        return ledger.result(scheduler, seconds + self.own.per_node_s, start)

    def _camera_s(self, paths: int) -> float:
        return self.costs.camera_ray_s * paths

    def _activations(self, ledger: _Ledger, caches: list[_Lru], node: np.ndarray,
                     tokens: np.ndarray, offload: bool) -> np.ndarray:
        """Charge one activation per (node, domain) of ``tokens`` held on ``node`` ((n,)
        each), loads included; returns (P,) seconds each node spent."""
        spent = np.zeros(ledger.size)
        if not len(tokens):
            return spent
        domain = self.domain_of[tokens]
        key = node * self.n_domains + domain
        keys, inverse = np.unique(key, return_inverse=True)
        radiance = np.bincount(inverse, weights=self.radiance_of[tokens], minlength=len(keys))
        total = np.bincount(inverse, minlength=len(keys))
        cost = self.activation.seconds(radiance, total) + self.activation.decision_s
        if offload and ledger.size > 1:
            cost = cost + np.where(total > INLINE_RAYS, self.costs.offload_s, 0.0)
        act_node, act_domain = keys // self.n_domains, keys % self.n_domains
        np.add.at(spent, act_node, cost)
        ledger.trace += np.bincount(act_node, weights=cost, minlength=ledger.size)
        own = self.own.activation_s * np.bincount(act_node, minlength=ledger.size)
        spent += own
        ledger.own += own
        load = np.zeros(ledger.size)
        for n, d in zip(act_node.tolist(), act_domain.tolist(), strict=True):
            if caches[n].touch(d):
                load[n] += self.load_s[d]
                ledger.counters["loads"] += 1
        ledger.load += load
        ledger.counters["activations"] += len(keys)
        ledger.counters["traced"] += len(tokens)
        return spent + load

    def _ship(self, ledger: _Ledger, source: np.ndarray, destination: np.ndarray,
              tokens: np.ndarray, activation: np.ndarray | None = None) -> np.ndarray:
        """Charge the batches of ``tokens`` (visits) moving from ``source`` to
        ``destination`` nodes (``_batches``); returns (P,) seconds each node spent."""
        return self._batches(ledger, source, destination, ~self.radiance_of[tokens],
                             activation)

    def _batches(self, ledger: _Ledger, source: np.ndarray, destination: np.ndarray,
                 shadow: np.ndarray, activation: np.ndarray | None = None) -> np.ndarray:
        """Charge rays (``shadow``: (n,) bool, each one's kind) moving from ``source`` to
        ``destination`` nodes: one batch per pair and kind that carries rays, and per
        ``activation`` that made them where given (a node ships after every activation)
        (``_charge``); returns (P,) seconds each node spent."""
        moving = source != destination
        if not moving.any():
            return np.zeros(ledger.size)
        pairs = 2 * ledger.size ** 2
        key = (source[moving] * ledger.size + destination[moving]) * 2 + shadow[moving]
        if activation is not None:  # per activation: the batches of each apart
            key = key + activation[moving].astype(np.int64) * pairs
        keys, counts = np.unique(key, return_counts=True)
        nbytes = counts * self.c.ray_bytes[keys % 2].astype(float) + HEADER_BYTES
        senders = keys % pairs // 2 // ledger.size
        receivers = keys % pairs // 2 % ledger.size
        sending, taking = self._charge(ledger, senders, receivers, counts, nbytes)
        return sending + taking

    def _charge(self, ledger: _Ledger, senders: np.ndarray, receivers: np.ndarray,
                rays: np.ndarray, nbytes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Charge ray batches ((b,) ``senders``, ``receivers``, the ``rays`` and ``nbytes``
        each carries): ``CostModel.message_s`` a batch to its sender, ``receive_s`` to its
        receiver, and to both their own code (``NodeOwnCosts.batches_s``). Returns (P,)
        seconds each node spent sending and (P,) taking in."""
        size = ledger.size
        sending = np.bincount(senders, weights=self.costs.message_s(nbytes), minlength=size)
        taking = self.costs.receive_s * np.bincount(receivers, minlength=size)
        ledger.messages += sending + taking
        own_out = self.own.batches_s(np.bincount(senders, minlength=size), 0,
                                     np.bincount(senders, weights=rays, minlength=size), 0)
        own_in = self.own.batches_s(0, np.bincount(receivers, minlength=size),
                                    0, np.bincount(receivers, weights=rays, minlength=size))
        ledger.own += own_out + own_in
        ledger.counters["messages"] += len(senders)
        ledger.counters["bytes"] += int(nbytes.sum())
        return sending + own_out, taking + own_in

    def _insitu_holding(self, owner: np.ndarray, size: int):
        """``spec-insitu``'s ``ownership.Holders`` by ``insitu_holders`` (see the class)."""
        from vastray.schedule.ownership import Holders, insitu_holders

        if isinstance(self.insitu_holders, Holders):  # given (a test's)
            return self.insitu_holders
        if self.insitu_holders == "owner":
            return Holders.owned(owner)
        if self.insitu_holders != "camera":
            raise ValueError(f"insitu_holders must be owner or camera, not "
                             f"{self.insitu_holders!r}")
        c = self.c
        camera = np.nonzero(c.parent < 0)[0]
        rows = ranges(c.crossed_first[camera], self.copies[camera])
        weights = np.bincount(c.crossed_domain[rows].astype(np.int64),
                              minlength=self.n_domains)
        return insitu_holders(owner, weights, size, self.nbytes)

    def _relayed(self, ledger: _Ledger, busy: np.ndarray, source: np.ndarray,
                 destination: np.ndarray, shadow: np.ndarray) -> np.ndarray:
        """``spec-insitu``'s copies moving from ``source`` to ``destination`` nodes ((n,)
        ranks; ``shadow`` (n,) bool, each one's queue) over the two hops of
        ``schedule.relay``, as the nodes' ``_exchange``: a batch per pair of the routes,
        queue and hop, empty or not, the first hop's rays carrying their destination (8
        bytes); a relay forwards once its first-hop batches are in. Returns (P,) when each
        node, from ``busy`` (P,), has its copies in."""
        from vastray.schedule.relay import relay_of, routes

        size = ledger.size
        if size == 1:
            return busy
        moving = source != destination
        source, destination = source[moving], destination[moving]
        kind = shadow[moving].astype(np.int64)
        via = relay_of(size, source, destination)
        first_hops, second_hops = routes(size)
        hop = via != source
        ready = self._hop(ledger, busy, first_hops, source[hop], via[hop], kind[hop], 8)
        hop = via != destination
        return self._hop(ledger, ready, second_hops, via[hop], destination[hop], kind[hop], 0)

    def _hop(self, ledger: _Ledger, busy: np.ndarray, hops, source: np.ndarray,
             destination: np.ndarray, kind: np.ndarray, extra_bytes: int) -> np.ndarray:
        """One hop of ``_relayed``: ``hops`` (``relay.Hops``) its batches, two queues each;
        the rays ((n,) ``source``, ``destination``, ``kind``) in them. A sender pays
        ``CostModel.message_s`` a batch, a receiver ``receive_s``, both their own code; a node
        goes on when it has sent its batches and every batch for it has been sent and taken
        in. Returns (P,) when each node goes on."""
        size = ledger.size
        pairs = hops.source * size + hops.destination  # sorted, as ``Hops``
        at = np.searchsorted(pairs, source * size + destination)
        counts = np.bincount(at * 2 + kind, minlength=2 * len(pairs))  # (pair, queue) rows
        nbytes = counts * (np.tile(self.c.ray_bytes, len(pairs)).astype(float)
                           + extra_bytes) + HEADER_BYTES
        sending, taking = self._charge(ledger, np.repeat(hops.source, 2),
                                       np.repeat(hops.destination, 2), counts, nbytes)
        sent = busy + sending
        arrived = sent.copy()
        np.maximum.at(arrived, hops.destination, sent[hops.source])
        return arrived + taking

    def _round_end(self, ledger: _Ledger, busy: np.ndarray, nbytes: float = 64.0,
                   reductions: int = 1, extra_wire: float = 0.0) -> float:
        """A bulk-synchronous round's span: the busiest node, the wire of its last batch, and
        ``reductions`` all-reductions of ``nbytes``."""
        reduce_s = reductions * self._allreduce_s(ledger.size, nbytes)
        ledger.reduction += reduce_s
        ledger.counters["rounds"] += reductions
        return float(busy.max()) + extra_wire + reduce_s

    def _rounds(self, size: int, cache: int) -> tuple[_Ledger, float]:
        """``domain``: bulk-synchronous rounds per tile (see the module docstring)."""
        from vastray.schedule.ownership import round_robin_owners

        owner = round_robin_owners(self.n_domains, size).astype(np.int64)
        ledger, caches = _Ledger(size), [_Lru(cache, self.n_domains) for _ in range(size)]
        clock = 0.0
        for tile in self._tiles(self.camera_visits):
            tokens = self.camera_visits[tile]
            local_index = self.path_of[tokens] % self.tile
            made_on = local_index % size  # ``interleaved_paths``: every P-th path of the tile
            busy = np.full(size, self._camera_s(len(tokens) / size))
            held = owner[self.domain_of[tokens]]
            busy += self._ship(ledger, made_on, held, tokens)
            arrived = made_on == held
            pending = tokens[~arrived]
            wave = tokens[arrived]
            while True:  # one round
                ledger.held(owner[self.domain_of[np.concatenate([pending, wave])]])
                moved, sources = [], []
                while len(wave):  # the drain: waves of rays that stay on the node
                    at = owner[self.domain_of[wave]]
                    busy += self._activations(ledger, caches, at, wave, offload=True)
                    nxt = self.successors(wave)
                    made = self.succ_first[wave + 1] - self.succ_first[wave]
                    src = np.repeat(at, made)
                    stay = src == owner[self.domain_of[nxt]]
                    moved.append(nxt[~stay])
                    sources.append(src[~stay])
                    wave = nxt[stay]
                if moved:  # the drain's end: a batch per peer and kind (``NodeWork.drain``)
                    leaving = np.concatenate(moved)
                    busy += self._ship(ledger, np.concatenate(sources),
                                       owner[self.domain_of[leaving]], leaving)
                clock += self._round_end(ledger, busy)
                wave = np.concatenate([pending, *moved]) if moved or len(pending) else pending
                pending = np.empty(0, np.int64)
                busy = np.zeros(size)
                if not len(wave):
                    break
        return ledger, clock

    def _dynamic(self, size: int, cache: int) -> tuple[_Ledger, float]:
        """``dynamic``: ray-weighted rounds, the next tile taken in at the end of a round whose
        all-reduced totals let it (``takes_next_tile``), at most ``MAX_TILES`` tiles in flight
        (``actors.dynamic_frame``; see the module docstring)."""
        from vastray.actors import dynamic_frame
        from vastray.actors.dynamic_frame import takes_next_tile
        from vastray.schedule.dynamic import RayWeightedRounds

        policy = RayWeightedRounds(self.fill_busy)
        ledger, caches = _Ledger(size), [_Lru(cache, self.n_domains) for _ in range(size)]
        clock = 0.0
        tiles = self._tiles(self.camera_visits)
        live: list[int] = []  # tiles in flight, in order
        tokens, at = np.empty(0, np.int64), np.empty(0, np.int64)
        busy = np.zeros(size)
        taken = [0]  # the next tile to take in

        def take_in() -> None:
            nonlocal tokens, at
            index = taken[0]
            taken[0] += 1
            live.append(index)
            fresh = self.camera_visits[tiles[index]]
            tokens = np.concatenate([tokens, fresh])
            at = np.concatenate([at, (self.path_of[fresh] % self.tile) % size])
            busy[:] += self._camera_s(len(fresh) / size)

        take_in()
        while True:
            domain = self.domain_of[tokens]
            ledger.held(at)
            wanted = np.bincount(domain, minlength=self.n_domains)
            holder = np.full(self.n_domains, size, np.int64)
            for n in range(size - 1, -1, -1):  # the lowest rank holding each
                if caches[n].held:
                    holder[list(caches[n].held)] = n
            plan = policy.from_totals(wanted, holder, size)
            # the all-reduction: wanted and holders a domain, the rays waiting a tile in flight
            clock += self._round_end(ledger, busy, 16.0 * self.n_domains + 8.0 * len(live))
            waiting = np.bincount(self.path_of[tokens] // self.tile,
                                  minlength=max(live) + 1 if live else 0)
            while live and not waiting[live[0]]:  # retire, in tile order
                live.pop(0)
            take = (taken[0] < len(tiles) and len(live) < dynamic_frame.MAX_TILES
                    and takes_next_tile(wanted, holder, size, self.tile))
            busy = np.zeros(size)
            if plan.finished:
                if not take:
                    break
                take_in()
                continue
            target = np.full(self.n_domains, -1, np.int64)
            if plan.assign:
                target[list(plan.assign)] = list(plan.assign.values())
            go = target[domain] >= 0
            # the swap: a node knows what it receives from the summed counts, so the
            # round's one all-reduction is the next round's (``DynamicFrame.run``)
            source, destination = at[go], target[domain[go]]
            busy += self._ship(ledger, source, destination, tokens[go])
            # a node traces once the last batch for it is sent
            np.maximum.at(busy, destination, busy[source])
            traced = tokens[go]
            where = target[domain[go]]
            busy += self._activations(ledger, caches, where, traced, offload=True)
            nxt = self.successors(traced)
            nxt_at = np.repeat(where, self.succ_first[traced + 1] - self.succ_first[traced])
            tokens = np.concatenate([tokens[~go], nxt])
            at = np.concatenate([at[~go], nxt_at])
            if take:
                take_in()
        return ledger, clock

    def _insitu(self, size: int) -> tuple[_Ledger, float]:
        """``spec-insitu``: per tile, an iteration per bounce of speculative copies (see the
        module docstring)."""
        from vastray.schedule.ownership import insitu_owners

        c = self.c
        owner = insitu_owners(self.lo, self.hi, self.triangles, size).astype(np.int64)
        holding = self._insitu_holding(owner, size)
        ledger, caches = _Ledger(size), [_Lru(self.n_domains) for _ in range(size)]
        clock = 0.0
        copies = self.copies
        seg_visits = self.visits
        first, child = self.children
        # each segment's holder: a camera ray's maker; a spawned one's, its parent's last
        # domain's owner (the node whose hit won the t-buffer MIN)
        last_domain = np.where(seg_visits > 0, c.visit_domain[np.maximum(c.visit_first[1:] - 1,
                                                                         0)], -1)
        segments = np.nonzero(c.parent < 0)[0]
        tiles = c.path[segments] // self.tile
        # the t-buffer MIN and o-buffer OR cover the paths in flight (``insitu._reduce_buffers``):
        # an 8-byte key a path and a bit a shadow slot (the most shadow rays a hit spawned)
        shadow = child[c.kind[child] != RADIANCE]
        slots = max(1, int(np.bincount(c.parent[shadow]).max(initial=0)) if len(shadow) else 1)
        for t in np.unique(tiles):
            live = segments[tiles == t]
            active = len(live)  # paths the buffers cover: the tile's, then those that hit
            holder = (c.path[live] % self.tile) % size
            busy = np.full(size, self._camera_s(len(live) / size))
            # in situ: a node loads its own domains before its first trace
            if t == tiles.min():
                for n in range(size):
                    mine = holding.held_by(n)
                    caches[n].held.update(dict.fromkeys(mine.tolist()))
                    load = float(self.load_s[mine].sum())
                    busy[n] += load
                    ledger.load[n] += load
                ledger.counters["loads"] += int(holding.count.sum())
            while len(live):
                rows = ranges(c.crossed_first[live], copies[live])
                copy_seg = np.repeat(live, copies[live])
                copy_domain = c.crossed_domain[rows].astype(np.int64)
                copy_from = np.repeat(holder, copies[live])
                at = holding.destination(copy_domain, c.path[copy_seg])
                kind_radiance = c.kind[copy_seg] == RADIANCE
                if self.insitu_routes == "relay":
                    busy = self._relayed(ledger, busy, copy_from, at, ~kind_radiance)
                else:  # straight, the counts summed first (before session 52)
                    busy += self._batches(ledger, copy_from, at, ~kind_radiance)
                    counts = self._allreduce_s(size, 8.0 * size)
                    ledger.reduction += counts
                    ledger.counters["rounds"] += 1
                    clock += counts
                # a query call per node, domain and kind holding copies; the node's local
                # closest hits shaded once per path; the iteration's bookkeeping
                key = (at * self.n_domains + copy_domain) * 2 + ~kind_radiance
                keys, total = np.unique(key, return_counts=True)
                cost = np.where(keys % 2 == 0,
                                self.activation.query_seconds(RADIANCE, total),
                                self.activation.query_seconds(1 - RADIANCE, total))
                per_node = np.bincount(keys // 2 // self.n_domains, weights=cost,
                                       minlength=size).astype(float)
                shaded = np.unique(at[kind_radiance] * len(c) + copy_seg[kind_radiance])
                per_node += np.bincount(shaded // len(c), minlength=size) * self.costs.shade_ray_s
                per_node += np.where(np.bincount(at, minlength=size) > 0,
                                     self.activation.fixed_s, 0.0)
                busy += per_node
                ledger.trace += per_node
                ledger.counters["activations"] += len(keys)
                ledger.counters["traced"] += len(copy_seg)
                clock += self._round_end(ledger, busy, active * (8.0 + slots / 8.0))
                busy = np.zeros(size)
                spawned = child[ranges(first[live], first[live + 1] - first[live])]
                active = len(np.unique(c.path[spawned]))
                parent_of = np.repeat(live, first[live + 1] - first[live])
                holder = holding.destination(np.maximum(last_domain[parent_of], 0),
                                             c.path[parent_of])
                keep = copies[spawned] > 0
                live, holder = spawned[keep], holder[keep]
        return ledger, clock

    def _sort_first(self, size: int, cache: int, speculative: bool,
                    scheduler: str) -> tuple[_Ledger, float]:
        """``image`` / ``spec-ooc``: every node its tiles, alone, one after another through
        its cache (``ownership.sort_first_tile_paths``, as ``actors.sort_first``; see the
        module docstring)."""
        from vastray.schedule.ownership import sort_first_block, sort_first_tile_paths

        ledger = _Ledger(size)
        paths = self.c.n_paths
        block = sort_first_block(paths, self.tile, size)
        camera_path = self.path_of[self.camera_visits]
        path_block = camera_path // block
        by_path = np.argsort(camera_path, kind="stable")
        sorted_path = camera_path[by_path]
        from vastray.schedule import image_cost

        weight_before = (self.band_weights() if size > 1 and scheduler in image_cost.CUT_BY_COST
                         else None)
        span = np.zeros(size)
        # a repeated frame (``Crossings.repeated``) gives nodes whose blocks are the same
        # paths of the base frame the same work: replayed once, charged to each
        period = getattr(self.c, "period", 0)
        same_work: dict = {}
        for rank in range(size):
            tiles = list(sort_first_tile_paths(paths, self.tile, rank, size, weight_before))
            runs = all(int(ids[-1]) - int(ids[0]) + 1 == len(ids) for ids in tiles)
            key = None
            if period and runs:
                key = tuple((int(ids[0]) % period, len(ids)) for ids in tiles)
            elif period and period % block == 0:
                key = tuple((tuple(int(x) % period for x in ids[::block]), len(ids))
                            for ids in tiles)
            if key is not None and key in same_work:
                seconds, trace, load, counters = same_work[key]
                ledger.trace[rank], ledger.load[rank] = trace, load
                for name, value in counters.items():
                    ledger.counters[name] += value
                span[rank] = seconds
                continue
            before = dict(ledger.counters)
            lru = _Lru(cache, self.n_domains)
            seconds = self._camera_s(sum(len(ids) for ids in tiles))
            for ids in tiles:
                decision_s = self.activation.tile_decision_s(scheduler, len(ids))
                if runs:  # a run of paths: the camera visits of its paths, in order
                    first, stop = np.searchsorted(sorted_path, [ids[0], ids[-1] + 1])
                    tokens = self.camera_visits[np.sort(by_path[first:stop])]
                else:
                    tokens = self.camera_visits[np.isin(path_block, ids[::block] // block)]
                if speculative:
                    seconds += self._speculative_node(ledger, rank, lru, tokens, decision_s)
                else:
                    seconds += self._image_node(ledger, rank, lru, tokens, decision_s)
            span[rank] = seconds
            ledger.counters["loads"] += lru.loads
            if key is not None:
                same_work[key] = (seconds, ledger.trace[rank], ledger.load[rank],
                                  {k: v - before[k] for k, v in ledger.counters.items()})
        return ledger, float(span.max())

    def band_weights(self):
        """``weight_before`` of the sort-first bands' cuts (``ownership.weighted_band_cuts``):
        each path weighs 1 + ``image_cost.PER_DOMAIN`` x the domains its camera ray's line
        crosses, as recorded (the product reads the same count off a coarse grid of camera
        rays against the boxes, ``image_cost.pixel_weights``)."""
        from vastray.schedule.image_cost import PER_DOMAIN

        c = self.c
        camera = np.nonzero(c.parent < 0)[0]
        weight = np.ones(c.n_paths, np.int64)
        weight[c.path[camera]] += PER_DOMAIN * self.copies[camera].astype(np.int64)
        before = np.concatenate([[0], np.cumsum(weight)])
        return lambda ids: before[ids]

    def _node_activation(self, ledger: _Ledger, rank: int, lru: _Lru, domain: int,
                         radiance: int, shadow: int, decision_s: float | None = None) -> float:
        """One activation of ``domain`` on node ``rank``, its load included where ``lru``
        misses; its decision ``decision_s`` (default: the recording's)."""
        cost = self._trace_s(radiance, shadow, decision_s)
        ledger.trace[rank] += cost
        ledger.own[rank] += self.own.activation_s
        cost += self.own.activation_s
        ledger.counters["activations"] += 1
        ledger.counters["traced"] += radiance + shadow
        if lru.touch(domain):
            ledger.load[rank] += self.load_s[domain]
            cost += self.load_s[domain]
        return cost

    def _image_node(self, ledger: _Ledger, rank: int, lru: _Lru, tokens: np.ndarray,
                    decision_s: float | None) -> float:
        """One sort-first node's ``image`` schedule: the fullest domain next, cached first."""
        queues = _Queues(self.n_domains)
        queues.push(self.domain_of[tokens], tokens)
        seconds = 0.0
        while True:
            domain = queues.fullest(lru.mask)
            if domain is None:
                return seconds
            batch = queues.pop(domain)
            radiance = int(np.count_nonzero(self.radiance_of[batch]))
            seconds += self._node_activation(ledger, rank, lru, domain, radiance,
                                             len(batch) - radiance, decision_s)
            nxt = self.successors(batch)
            queues.push(self.domain_of[nxt], nxt)

    def _speculative_node(self, ledger: _Ledger, rank: int, lru: _Lru, tokens: np.ndarray,
                          decision_s: float | None) -> float:
        """One sort-first node's ``spec-ooc`` schedule: copies in every crossed domain; a
        segment commits once the domains it needs are traced, its children start then, and
        its copies left are dropped."""
        c = self.c
        segs = self.seg_of[tokens]
        need = self.visits.copy()  # domains each segment still needs traced
        done = np.zeros(len(c), bool)
        queues = _Queues(self.n_domains)
        self._queue_copies(queues, segs)
        seconds = 0.0
        first, child = self.children
        visited = np.zeros(self.n_domains, bool)  # this round's domains so far
        while True:
            domain = queues.next_in_round(lru.mask, visited)
            if domain is None:
                if not queues.parts:
                    return seconds
                visited[:] = False  # a new round
                continue
            visited[domain] = True
            batch = queues.pop(domain)
            batch = batch[~done[batch]]
            if not len(batch):
                continue
            radiance = int(np.count_nonzero(c.kind[batch] == RADIANCE))
            seconds += self._node_activation(ledger, rank, lru, domain, radiance,
                                             len(batch) - radiance, decision_s)
            needed = self._visits_domain(batch, domain)
            np.subtract.at(need, batch[needed], 1)
            finished = np.unique(batch[needed][need[batch[needed]] == 0])
            done[finished] = True
            spawned = child[ranges(first[finished], first[finished + 1] - first[finished])]
            spawned = spawned[self.visits[spawned] > 0]
            self._queue_copies(queues, spawned)

    def _visits_domain(self, segs: np.ndarray, domain: int) -> np.ndarray:
        """(m,) bool: whether each of ``segs`` is traced in ``domain`` by the lossless
        schedule (its hit needs that domain before it is final)."""
        counts = self.visits[segs]
        rows = ranges(self.c.visit_first[segs], counts)
        hit = self.c.visit_domain[rows] == domain
        out = np.zeros(len(segs), bool)
        out[np.repeat(np.arange(len(segs)), counts)[hit]] = True
        return out

    def _queue_copies(self, queues: _Queues, segs: np.ndarray) -> None:
        """Queue a copy of each of ``segs`` into every domain its line crosses, each weighing
        SpRay's traversal score M - j in its domain, j its place along the line (M = D)."""
        c = self.c
        counts = self.copies[segs]
        rows = ranges(c.crossed_first[segs], counts)
        place = rows - np.repeat(c.crossed_first[segs], counts)
        queues.push(c.crossed_domain[rows].astype(np.int64), np.repeat(segs, counts),
                    self.n_domains - place)

    def _async(self, size: int, cache: int) -> tuple[_Ledger, float]:
        """``async`` (Galaxy): per-node event simulation, no rounds (see the module
        docstring)."""
        from vastray.schedule.ownership import round_robin_owners

        owner = round_robin_owners(self.n_domains, size).astype(np.int64)
        ledger, caches = _Ledger(size), [_Lru(cache, self.n_domains) for _ in range(size)]
        queues = [_Queues(self.n_domains) for _ in range(size)]
        tiles = self._tiles(self.camera_visits)
        next_tile = [0] * size
        inbox: list[list] = [[] for _ in range(size)]  # (arrival, tokens)
        free_at = np.zeros(size)
        events = [(0.0, n) for n in range(size)]
        heapq.heapify(events)
        sleeping = np.zeros(size, bool)
        end = 0.0
        while events:
            now, n = heapq.heappop(events)
            if now < free_at[n]:
                continue
            box = inbox[n]
            if box:
                arrived = [t for a, t in box if a <= now]
                inbox[n] = [(a, t) for a, t in box if a > now]
                for tokens in arrived:
                    queues[n].push(self.domain_of[tokens], tokens)
            q = queues[n]
            cost = self.costs.receive_s * len(arrived) if box else 0.0  # taking them in
            ledger.messages[n] += cost
            if box:  # and queueing them
                took = self.own.batches_s(0, len(arrived), 0, sum(len(t) for t in arrived))
                ledger.own[n] += took
                cost += took
            out = None
            if next_tile[n] < len(tiles) and q.total < self.tile:
                tile = tiles[next_tile[n]]
                next_tile[n] += 1
                tokens = self.camera_visits[tile]
                tokens = tokens[(self.path_of[tokens] % self.tile) % size == n]
                cost += self._camera_s(len(tokens))
                out = tokens
            else:
                domain = q.fullest(caches[n].mask)
                if domain is not None:
                    batch = q.pop(domain)
                    radiance = int(np.count_nonzero(self.radiance_of[batch]))
                    cost += self._node_activation(ledger, n, caches[n], domain, radiance,
                                                  len(batch) - radiance)
                    if size > 1:
                        cost += self.costs.offload_s
                    out = self.successors(batch)
            if out is None:  # idle: wake at the next arrival
                sleeping[n] = True
                if inbox[n]:
                    heapq.heappush(events, (min(a for a, _ in inbox[n]), n))
                    sleeping[n] = False
                continue
            dest = owner[self.domain_of[out]]
            local = dest == n
            q.push(self.domain_of[out[local]], out[local])
            if not local.all():
                far = out[~local]
                batch_key = dest[~local] * 2 + ~self.radiance_of[far]  # a batch per queue
                order = np.argsort(batch_key, kind="stable")
                far, batch_key = far[order], batch_key[order]
                cuts = np.flatnonzero(np.diff(batch_key)) + 1
                for group in np.split(np.arange(len(far)), cuts):
                    tokens = far[group]
                    m = int(batch_key[group[0]] // 2)
                    nbytes = self._ray_bytes(tokens)
                    send = self.costs.message_s(nbytes)
                    cut = self.own.batches_s(1, 0, len(tokens), 0)
                    cost += send + cut
                    ledger.messages[n] += send
                    ledger.own[n] += cut
                    ledger.counters["messages"] += 1
                    ledger.counters["bytes"] += int(nbytes)
                    arrival = now + cost + self.network.wire_s(nbytes)
                    inbox[m].append((arrival, tokens))
                    if sleeping[m] or free_at[m] <= arrival:
                        sleeping[m] = False
                        heapq.heappush(events, (max(arrival, free_at[m]), m))
            free_at[n] = now + cost
            end = max(end, free_at[n])
            heapq.heappush(events, (free_at[n], n))
        ledger.counters["loads"] = sum(cache.loads for cache in caches)
        waves = 2 * self._wave_s(size)  # termination: two waves over the tree
        ledger.reduction += waves
        ledger.counters["rounds"] += 2
        return ledger, end + waves


class _Queues:
    """A node's rays waiting per domain: (D,) counts and each domain's token arrays."""

    def __init__(self, n_domains: int):
        self.counts = np.zeros(n_domains, np.int64)
        #: (D,) SpRay's front-to-back traversal score of the rays waiting (``push``'s weights)
        self.score = np.zeros(n_domains, np.int64)
        self.parts: dict[int, list[np.ndarray]] = {}
        self.total = 0

    def push(self, domains: np.ndarray, tokens: np.ndarray,
             weights: np.ndarray | None = None) -> None:
        """Queue (n,) ``tokens`` into (n,) ``domains``; ``weights`` (n,) int: each one's
        share of its domain's ``score``."""
        n = len(tokens)
        if not n:
            return
        if weights is not None:
            np.add.at(self.score, domains, weights)
        if n == 1 or (domains[0] == domains).all():
            d = int(domains[0])
            self.parts.setdefault(d, []).append(tokens)
            self.counts[d] += n
            self.total += n
            return
        order = np.argsort(domains, kind="stable")
        domains, tokens = domains[order], tokens[order]
        bounds = np.concatenate([[0], np.flatnonzero(np.diff(domains)) + 1, [n]]).tolist()
        parts = self.parts
        for start, stop in zip(bounds[:-1], bounds[1:], strict=True):
            d = int(domains[start])
            parts.setdefault(d, []).append(tokens[start:stop])
        firsts = domains[bounds[:-1]]
        self.counts[firsts] += np.diff(bounds)
        self.total += n

    def pop(self, domain: int) -> np.ndarray:
        parts = self.parts.pop(domain)
        self.total -= int(self.counts[domain])
        self.counts[domain] = 0
        self.score[domain] = 0
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def next_in_round(self, cached: np.ndarray, visited: np.ndarray) -> int | None:
        """``spec-ooc``'s next domain of a round (``SpeculativeSchedule.next_domain``, every
        domain once a round): among those with rays not ``visited`` ((D,) bool) this round,
        a cached one ((D,) bool ``cached``) first, then the highest ``score``, the lowest id
        on ties; None when none is left this round."""
        if not self.parts:
            return None
        waiting = (self.counts > 0) & ~visited
        if not waiting.any():
            return None
        here = waiting & cached
        pool = here if here.any() else waiting
        return int(np.argmax(np.where(pool, self.score, -1)))

    def fullest(self, cached: np.ndarray) -> int | None:
        """The fullest domain (the lowest id on ties), a cached one ((D,) bool ``cached``)
        with rays first (``schedule.image.fullest``)."""
        if not self.parts:
            return None
        here = self.counts * cached
        return int(np.argmax(here if here.any() else self.counts))


@dataclass(frozen=True)
class NodeOwnCosts:
    """What a node's own code costs beyond its traces, decisions, loads and messages' CPU
    (``sim.meter``): its frame's set-up (``per_node_s``, once a frame), a ray batch it cuts
    and sends (``sent_s``, and ``ray_sent_s`` a ray in it) or takes in and queues
    (``received_s``, ``ray_received_s``), an activation's bookkeeping around the trace
    (``activation_s``). Fitted per scheduler on the simulator that runs the nodes' code
    (``fit_node_own_costs``); zero: charged as nothing."""

    per_node_s: float = 0.0
    sent_s: float = 0.0
    received_s: float = 0.0
    activation_s: float = 0.0
    ray_sent_s: float = 0.0
    ray_received_s: float = 0.0

    def batches_s(self, sent, received, rays_sent, rays_received):
        """Seconds of batches sent and received carrying those rays (scalars or arrays)."""
        return (self.sent_s * sent + self.received_s * received
                + self.ray_sent_s * rays_sent + self.ray_received_s * rays_received)


#: The counters ``fit_node_own_costs`` regresses a node's own seconds on, after its frame's
#: set-up (``NodeOwnCosts``' fields in order).
_OWN_COUNTERS = ("batches_sent", "batches_received", "activations", "rays_sent",
                 "rays_received")


def fit_node_own_costs(store, settings, domains, node_counts, options_of,
                       schedulers=None) -> dict[str, NodeOwnCosts]:
    """``NodeOwnCosts`` of each of ``schedulers`` (default: every replayed one), fitted (least
    squares, none negative) to what each node's own code took in simulations of ``settings``
    on each of ``node_counts`` virtual nodes running the product's code (every other cost
    free, so nothing else is charged), against its ray batches and rays sent and received
    and its activations: several node counts, so that batches and rays (whose ratio changes
    with P) are told apart.

    Parameters
    ----------
    store, settings : the frame simulated; domains : the store's domains built.
    node_counts : virtual nodes (not those the replay is checked at: the fit stays out of
        sample).
    options_of : (scheduler, nodes, paths) -> the job's options (the bench's scaling options).
    """
    from vastray.sim.simulate import simulate

    own_only = replace(CostModel.free(), node_cpu_scale=1.0)
    fitted = {}
    for scheduler in schedulers or REPLAY_SCHEDULERS:
        rows, own = [], []
        for i, nodes in enumerate(node_counts):
            options = options_of(scheduler, nodes, settings.paths)
            if i == 0:  # once uncharged: this process's first use of the code
                simulate(store, options, nodes, own_only, settings, max_pass_spp=None,
                         domains=domains)
            result = simulate(store, options, nodes, own_only, settings, max_pass_spp=None,
                              domains=domains)
            rows += [[1.0, *(c.get(k, 0) for k in _OWN_COUNTERS)]
                     for c in result.node_counters]
            own.append(result.own_seconds)
        solution = _nonnegative_lstsq(np.array(rows, float), np.concatenate(own))
        fitted[scheduler] = NodeOwnCosts(*map(float, solution))
    return fitted


@dataclass(frozen=True)
class ActivationCosts:
    """What one activation costs on a store: ``fixed_s`` (radiance rays among its rays),
    ``fixed_shadow_s`` (shadow rays only), and per ray traced; ``decision_s`` choosing it;
    and one Embree call alone (``query``: (fixed, per ray) for closest hits and for
    occlusion; what ``spec-insitu`` makes per domain, its shading apart)."""

    fixed_s: float
    fixed_shadow_s: float
    radiance_s: float
    shadow_s: float
    decision_s: float = 0.0
    query: tuple = ((0.0, 0.0), (0.0, 0.0))
    #: a sort-first node's decision per activation by scheduler, measured at a few tile
    #: sizes: scheduler -> ((paths, seconds), ...) ascending (``sort_first_decisions``: the
    #: product's loop with its cache, ``likely_next`` and spec-ooc's filtering); a
    #: scheduler not in it pays ``decision_s``
    sort_first_decision_s: dict = field(default_factory=dict)

    def tile_decision_s(self, scheduler: str, paths: int) -> float | None:
        """``scheduler``'s decision per activation on a node of ``paths`` paths: the
        measurements interpolated in log(paths), the nearest one outside them; None where it
        was not measured."""
        points = self.sort_first_decision_s.get(scheduler)
        if not points:
            return None
        sizes, seconds = zip(*points, strict=True)
        return float(np.interp(math.log(max(paths, 1)), np.log(sizes), seconds))

    def query_seconds(self, kind: int, rays):
        """Seconds of query calls of ``kind`` over ``rays`` rays each."""
        fixed, per_ray = self.query[kind]
        return np.where(np.asarray(rays) > 0, fixed + np.asarray(rays) * per_ray, 0.0)

    @classmethod
    def of(cls, costs: CostModel) -> ActivationCosts:
        """The cost model's constants (``CostModel.trace_s``)."""
        return cls(costs.activation_s, costs.shadow_activation_s,
                   costs.trace_ray_s + costs.shade_ray_s, costs.shadow_ray_s, 0.0,
                   ((0.0, costs.trace_ray_s), (0.0, costs.shadow_ray_s)))

    def seconds(self, radiance, total):
        """Seconds of activations of ``radiance`` radiance rays among ``total`` (scalars or
        arrays alike)."""
        return (np.where(radiance > 0, self.fixed_s, self.fixed_shadow_s)
                + radiance * self.radiance_s + (total - radiance) * self.shadow_s)


def fit_activation_costs(crossings: Crossings, costs: CostModel) -> ActivationCosts:
    """The four costs of ``ActivationCosts`` fitted (least squares, none negative) to the
    recording run's own activations on this store: what the real schedule code costs on its
    domains, bounces and batch sizes. A cost the fit cannot tell (no activation of that kind)
    stays the cost model's constant."""
    rays = crossings.activation_rays.astype(float)
    constants = ActivationCosts.of(costs)
    if len(rays) < 4:
        return constants
    design = np.column_stack([rays[:, 0] > 0, rays[:, 0] == 0, rays[:, 0], rays[:, 1]])
    solution = _nonnegative_lstsq(design.astype(float), crossings.activation_cpu_s)
    told = design.any(axis=0)
    values = np.where(told, solution, [constants.fixed_s, constants.fixed_shadow_s,
                                       constants.radiance_s, constants.shadow_s])
    query = []
    for kind in (RADIANCE, 1 - RADIANCE):
        calls = crossings.query_rays[:, 0] == kind
        if calls.sum() >= 2:
            rays = crossings.query_rays[calls, 1].astype(float)
            query.append(tuple(float(v) for v in _nonnegative_lstsq(
                np.column_stack([np.ones_like(rays), rays]), crossings.query_cpu_s[calls])))
        else:
            query.append(constants.query[kind])
    decision = float(np.mean(crossings.decision_cpu_s)) if len(crossings.decision_cpu_s) else 0.0
    return ActivationCosts(*(float(v) for v in values), decision, tuple(query))


def sort_first_decisions(store, settings, domains, cache: int | None = None,
                         sizes=(256, 4096), schedulers=None) -> dict[str, tuple]:
    """What a sort-first node's decisions cost per activation on ``store``, by scheduler and
    tile size (``ActivationCosts.sort_first_decision_s``): one virtual node renders a tile of
    each of ``sizes`` paths (``settings``' first rows) through a cache of ``cache`` domains
    (None: the product's default) on the simulator, which runs the product's loop (its
    choice, the preloader's guess, spec-ooc's filtering, eviction by demand) and charges
    nothing but the CPU time those decisions take (``decision_scale`` 1, every other cost 0);
    the decision seconds over the activations. The recording's own decisions are
    ``ImageSchedule.next_domain`` alone, every domain in memory: on 1,439 domains a tenth of
    what spec-ooc's take (``replay_error`` −0.48 for spec-ooc against −0.10 for image).

    Parameters
    ----------
    store, settings : the recorded frame's store and settings.
    domains : the store's domains built (``sim.cache.Domains``).
    cache : domains a node caches; sizes : the tiles' paths (each at most the frame's).
    schedulers : whose decisions (default: every sort-first one).
    """
    from vastray.actors.job_options import JobOptions
    from vastray.sim.simulate import simulate

    only_decisions = replace(CostModel.free(), decision_scale=1.0)
    if schedulers is None:
        schedulers = [spec.name for spec in registry.SPECS
                      if spec.simulation is Simulation.SORT_FIRST]

    def decided(scheduler: str, paths: int) -> tuple[int, float, int]:
        rows = max(1, min(settings.height, -(-paths // (settings.width * settings.spp))))
        tile = replace(settings, height=rows)
        options = JobOptions(scheduler=scheduler, cache=cache, max_samples_in_flight=tile.paths)
        result = simulate(store, options, 1, only_decisions, tile, max_pass_spp=None,
                          domains=domains)
        return tile.paths, result.counters["schedule_s"], result.counters.get("activations", 0)

    out = {}
    for scheduler in schedulers:
        # once uncharged: this process's first use of the schedule's compiled code would be
        # charged to the first tile's decisions (863 us an activation, then 230-330 us, for
        # spec-ooc on 256 paths of an 18-domain store)
        decided(scheduler, min(sizes))
        points = {}
        for paths in sizes:
            tile_paths, seconds, activations = decided(scheduler, paths)
            if activations:
                points[tile_paths] = seconds / activations
        out[scheduler] = tuple(sorted(points.items()))
    return out


def _nonnegative_lstsq(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """argmin |a x - b| with x >= 0, for a few columns: least squares on the columns left,
    dropping the most negative one until none is."""
    x = np.zeros(a.shape[1])
    columns = [c for c in range(a.shape[1]) if a[:, c].any()]
    while columns:
        solution = np.linalg.lstsq(a[:, columns], b, rcond=None)[0]
        if (solution >= 0).all():
            x[columns] = solution
            break
        columns.pop(int(np.argmin(solution)))
    return x
