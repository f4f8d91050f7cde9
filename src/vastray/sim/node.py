"""A virtual node: the actors' own node code (``render_owned_domains``, ``render_spec_insitu``,
``NodeWork``, the asynchronous and temporal frames, the ray post, the tree-reduce actor) run
over a management actor whose sockets are the simulated network, a domain loop whose trace is
charged in virtual time and a preloader whose loads are.

Ray batches are encoded and decoded by the real codec, so their size on the wire is the real
one; what tracing costs is the cost model's: the CPU time the simulator spends running the
activation's real trace where ``CostModel.trace_scale`` is set (simulating on the calibrated
machine), else the constants of ``CostModel.trace_s`` for its radiance and shadow queries,
plus a node runtime's hand-off of the trace to a worker thread (``CostModel.offload_s``).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

from vastray.actors import protocol
from vastray.actors.domain_loop import DomainLoop, DomainOrder, Queries, hands_off
from vastray.actors.node_state import NodeState
from vastray.actors.node_work import NodeWork
from vastray.scene.embree.launch import cpu_time
from vastray.sim.cache import Domains, VirtualPreloader
from vastray.sim.cluster import Cluster
from vastray.transport.codec import decode, frames_nbytes


class SimManagement:
    """The management actor's interface over the simulated network: mailboxes by kind, sends
    to peers and to the coordinator.

    Parameters
    ----------
    cluster : the virtual nodes.
    rank : this node.
    timeout : virtual seconds a receive waits before it fails.
    """

    def __init__(self, cluster: Cluster, rank: int, timeout: float = 1e6):
        self.cluster, self.rank, self.timeout = cluster, rank, timeout
        self.rejections = protocol.Rejections()

    def mailbox(self, kind: str) -> asyncio.Queue:
        return self.cluster.mailboxes[self.rank][kind]

    async def receive(self, kind: str, what: str):
        try:
            return await asyncio.wait_for(self.mailbox(kind).get(), self.timeout)
        except TimeoutError:
            raise TimeoutError(f"node {self.rank}: no {what} within {self.timeout:.0f} "
                               "virtual seconds") from None

    async def wait_any(self, futures: list, what: str) -> set:
        """Wait until one of ``futures`` is done (returns those done), at most ``timeout``
        virtual seconds."""
        done, _ = await asyncio.wait(futures, timeout=self.timeout,
                                     return_when=asyncio.FIRST_COMPLETED)
        if not done:
            raise TimeoutError(f"node {self.rank}: no {what} within {self.timeout:.0f} "
                               "virtual seconds")
        return done

    async def to_peer(self, rank: int, frames: list) -> None:
        await self.cluster.send(self.rank, rank, self._decoded(frames), frames_nbytes(frames))

    async def to_coordinator(self, frames: list) -> None:
        await self.cluster.send(self.rank, self.cluster.coordinator, self._decoded(frames),
                                frames_nbytes(frames))

    def _decoded(self, frames: list):
        """The message of ``frames``, decoded here as its receiver would (the message's cost,
        ``CostModel.message_s``, charges that; the node's own CPU does not)."""
        with self.cluster.meter.simulators_own():
            return decode(frames)


class VirtualDomainLoop(DomainLoop):
    """The domain loop on the virtual clock: a domain's rays are traced for real, and the
    activation costs ``CostModel.trace_charge`` on the node's core (``offload_s`` more on a
    node runtime, whose real loop traces on a worker thread); the schedule's
    decisions cost the CPU time they take here (``decided``).
    ``node_runtime``: the loop of a node runtime (whose set-up, ``node_setup_s``, its first
    trace pays), not the one-process runtime's that the sort-first nodes run."""

    def __init__(self, cluster: Cluster, rank: int, preloader: VirtualPreloader, stats: dict,
                 node_runtime: bool = True):
        super().__init__(preloader, stats, offload=False)
        self.cluster, self.rank = cluster, rank
        self.clock = cluster.now
        self.node_runtime = node_runtime

    async def decided(self, cpu_seconds: float) -> None:
        # with the tile starts and bookkeeping since the last decision (``start_tile``,
        # ``bookkeeping``)
        cpu_seconds, self.uncharged_cpu_s = cpu_seconds + self.uncharged_cpu_s, 0.0
        await self.cluster.decided(self.rank, cpu_seconds)

    async def trace(self, order: DomainOrder, domain: int, bvh) -> Queries:
        # decided before the trace, as the real loop decides it: after it, the domain's rays
        # are gone and every activation would look small
        handed = self.node_runtime and hands_off(order, domain)
        cpu = cpu_time()
        queries = order.trace(domain, bvh)
        cpu = cpu_time() - cpu
        self.stats["trace_cpu_s"] = self.stats.get("trace_cpu_s", 0.0) + cpu
        self.cluster.meter.account(self.rank, cpu)
        if not queries:  # a domain only loaded (in situ), or nothing left for it
            return queries
        costs = self.cluster.costs
        seconds = costs.trace_charge(queries.radiance, queries.shadow, cpu)
        if handed:  # as the real node's loop does
            seconds += costs.offload_s
            self.stats["handed_off"] = self.stats.get("handed_off", 0) + 1
        await self.cluster.trace(self.rank, seconds,
                                 runtime="node" if self.node_runtime else "tile")
        return queries


class SimNode(NodeWork):
    """``NodeWork`` on a virtual node: its domain loop is ``VirtualDomainLoop``."""

    def __init__(self, management: SimManagement, rank: int, stats: dict,
                 preloader: VirtualPreloader, max_batch: int, early: dict):
        super().__init__(management, rank, stats, preloader, max_batch, early)
        self.loop = VirtualDomainLoop(management.cluster, rank, preloader, stats)


@dataclass
class SimNodeState(NodeState):
    """A virtual node's ``NodeState``: its preloader, domain loop and node work are the
    simulator's, and work traced outside the domain loop is charged.

    Parameters
    ----------
    cluster, rank : the virtual nodes and this one.
    domains : the built domains every virtual node traces against.
    """

    cluster: Cluster | None = None
    rank: int = 0
    domains: Domains | None = None

    def preloader_for(self, store, capacity: int, keep, options, rank: int,
                      fast_builds: bool = False):
        """The virtual node's preloader. Its loads cost what the calibration measured, with
        Embree's default BVH: ``fast_builds`` (``--bvh``) is not modelled."""
        if self.preloader is None:
            self.preloader = VirtualPreloader(self.cluster, self.rank, self.domains, capacity,
                                              preload=options.preload,
                                              bandwidth=options.load_bytes_per_second(rank),
                                              build_ahead=options.build_ahead)
        return self.preloader

    def domain_loop(self, preloader, stats: dict) -> DomainLoop:
        return VirtualDomainLoop(self.cluster, self.rank, preloader, stats)

    def tile_loop(self, preloader, stats: dict) -> DomainLoop:
        return VirtualDomainLoop(self.cluster, self.rank, preloader, stats, node_runtime=False)

    def node_work(self, management, rank: int, stats: dict, preloader, max_batch: int):
        return SimNode(management, rank, stats, preloader, max_batch, self.early)

    async def traced(self, radiance: dict[int, int], shadow: dict[int, int],
                     cpu_seconds: float = 0.0) -> None:
        if not (radiance or shadow):
            return
        self.cluster.meter.account(self.rank, cpu_seconds)
        costs = self.cluster.costs
        if costs.trace_scale:
            seconds = cpu_seconds * costs.trace_scale
        else:
            seconds = sum(costs.trace_s(radiance.get(d, 0), shadow.get(d, 0))
                          for d in radiance | shadow)
        await self.cluster.trace(self.rank, seconds, runtime="in_situ")

    async def decided(self, cpu_seconds: float) -> None:
        await self.cluster.decided(self.rank, cpu_seconds)

    def close(self) -> None:
        """Nothing to stop: a virtual preloader has no thread."""
