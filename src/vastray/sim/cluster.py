"""P virtual nodes and their coordinator in virtual time: cores and the network.

Costs come from a ``CostModel``. With ``cores`` set, every node and the coordinator share
that many cores, as the operating system shares them among node processes on one machine
(``SharedCores``; a node's own work, whichever of its threads does it, runs at one process's
speed: its GIL; where the nodes are no more than the cores, each is bound to its share of
them, as ``vastray render --nodes`` binds local nodes, and no job of it is wider);
otherwise each has one core of its own, which everything the node computes shares (its
traces, its preloader's BVH builds, its sends and decisions: one core's processor sharing,
as a one-core node's threads share it). A message costs its sender's core the one-way time
measured between two processes (encoding, copies, decoding; ``CostModel.message_s``), then
its receiver's core what the nodes' management actors add (``CostModel.receive_s``), and is
delivered, in order between any two endpoints (as ZeroMQ's). A tree reduction costs what
its messages cost: the actors' own tree-reduce sends them.
"""

from __future__ import annotations

import asyncio
from collections import defaultdict

import numpy as np

from vastray.scene.cpu_binding import node_cpu_blocks
from vastray.sim.cores import SharedCores
from vastray.sim.costs import CostModel
from vastray.sim.meter import NodeMeter, start_simulator_task
from vastray.transport.codec import Message

#: Each node runtime and the cost model's constant for its set-up.
RUNTIMES = {"node": "node_setup_s", "tile": "tile_setup_s", "in_situ": "insitu_setup_s"}


class Cluster:
    """The shared state of P virtual nodes (see the module docstring). Endpoint P is the
    coordinator.

    Parameters
    ----------
    size : P, the number of nodes.
    costs : what work costs.
    first_touch_s : what each fresh node pays once, at its first trace, to first touch the
        memory of its paths in flight (``CostModel.first_touch_s`` of the render's
        ``simulate.paths_in_flight``).
    """

    def __init__(self, size: int, costs: CostModel, first_touch_s: float = 0.0):
        self.size, self.costs = size, costs
        self.first_touch_s = first_touch_s
        self.coordinator = size  # the coordinator's endpoint
        #: with the machine's cores shared, the cores each node is bound to (as
        #: ``vastray render --nodes`` binds local nodes, ``scene.cpu_binding``): none of its
        #: jobs is wider, and others' processes share the cores as beside bound processes;
        #: None: unbound
        blocks = (node_cpu_blocks(size, list(range(costs.cores)), costs.cores)
                  if costs.cores else None)
        bound_nodes = (size, len(blocks[0])) if blocks else None
        self.bound_width = float(bound_nodes[1]) if bound_nodes else None
        self._cores = (SharedCores(costs.cores, costs.throughput, costs.others, bound_nodes)
                       if costs.cores else None)
        #: without a shared machine, each endpoint's one core
        self._own: defaultdict[int, SharedCores] = defaultdict(lambda: SharedCores(1))
        #: each endpoint's mailboxes by message kind (as a management actor's)
        self.mailboxes = [defaultdict(asyncio.Queue) for _ in range(size + 1)]
        self.compute_s = np.zeros(size + 1)  # (P + 1,) seconds each endpoint computed
        self._warm = np.zeros(size + 1, bool)  # (P + 1,) whether each has traced yet
        self._sending = defaultdict(asyncio.Lock)  # endpoint -> its sends, in order
        self._receiving = defaultdict(asyncio.Lock)  # endpoint -> its arrivals, in order
        self._arrivals: set[asyncio.Future] = set()  # messages on their way in
        self.messages = 0
        self.bytes = 0
        #: each node's own code measured beyond the named work (``sim.meter``); charged
        #: only where ``costs.node_cpu_scale`` is set
        self.meter = NodeMeter(costs.node_cpu_scale)

    @staticmethod
    def now() -> float:
        return asyncio.get_running_loop().time()

    async def compute(self, rank: int, seconds: float, width: float = 1.0) -> None:
        """Endpoint ``rank`` works ``seconds`` on its one core (shared by whatever else it
        computes meanwhile), or sharing the machine's cores (``SharedCores``: as fast as the
        machine's measured throughput lets; a job ``width`` cores wide alone, an Embree
        build, uses cores no other process is using, up to that); with what its own code
        computed since its last charge (``NodeMeter.take``)."""
        seconds += self.meter.take(rank) if rank < self.size else 0.0
        if seconds <= 0:
            return
        self.compute_s[rank] += seconds
        with self.meter.simulators_own():
            if self._cores is None:
                done = self._own[rank].start(seconds)
            else:
                if self.bound_width is not None and rank < self.size:
                    width = min(width, self.bound_width)
                done = self._cores.start(seconds, owner=rank, width=width)
        await done

    async def trace(self, rank: int, seconds: float, runtime: str) -> None:
        """Node ``rank`` traces for ``seconds`` (``CostModel.trace_charge`` of its activations).
        Its first trace also pays a fresh process's first use (``warmup_s``) and the set-up
        of its ``runtime`` (one of ``RUNTIMES``: ``node_setup_s`` for the domain-decomposition
        runtimes, ``tile_setup_s`` for sort-first nodes, ``insitu_setup_s`` for in-situ ones):
        a node that never traces never loads the kernels. It pays ``first_touch_s`` then too."""
        if not self._warm[rank]:
            self._warm[rank] = True
            costs = self.costs
            seconds += costs.warmup_s + getattr(costs, RUNTIMES[runtime]) + self.first_touch_s
        await self.compute(rank, seconds)

    async def decided(self, rank: int, cpu_seconds: float) -> None:
        """Node ``rank``'s schedule decided for ``cpu_seconds`` of CPU (measured as the real
        schedule code ran here, in the node's current step): charged to its core times
        ``CostModel.decision_scale``."""
        self.meter.account(rank, cpu_seconds)
        await self.compute(rank, cpu_seconds * self.costs.decision_scale)

    async def flush(self, rank: int) -> None:
        """Charge node ``rank`` what its own code computed since its last charge (the end of
        a busy span: nothing after it would take it along)."""
        await self.compute(rank, 0.0)

    async def send(self, source: int, destination: int, message: Message, nbytes: int) -> None:
        """Post ``message`` (decoded, ``nbytes`` on the wire) from ``source`` to
        ``destination``'s mailbox of its kind: the sender's core spends the message's cost
        (``CostModel.message_s``: measured one way between two processes, encoding, copies
        and decoding lumped on the sender), then the receiver's core its ``receive_s``, and
        it is delivered."""
        async with self._sending[source]:  # a sender's messages leave one after another
            await self.compute(source, self.costs.message_s(nbytes))
        self.messages += 1
        self.bytes += nbytes
        if not self.costs.receive_s:
            self.mailboxes[destination][message.kind].put_nowait(message)
            return
        with self.meter.simulators_own():
            arrival = start_simulator_task(self._arrive(destination, message))
        self._arrivals.add(arrival)
        arrival.add_done_callback(self._arrivals.discard)

    async def _arrive(self, destination: int, message: Message) -> None:
        """``destination`` takes ``message`` in (``CostModel.receive_s`` on its core, as its
        management actor routes it), then it is in its mailbox; a node takes its messages
        in one after another, in the order they were sent."""
        async with self._receiving[destination]:
            await self.compute(destination, self.costs.receive_s)
            self.mailboxes[destination][message.kind].put_nowait(message)
