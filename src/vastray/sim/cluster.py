"""P virtual nodes and their coordinator in virtual time: cores and the network.

Costs come from a ``CostModel``. Compute holds a core for its cost: with ``cores`` set, every
node and the coordinator share that many (node processes sharing one machine); otherwise each
has its own. A message leaves when its sender's link is free, occupies the link for its
bytes, and arrives a latency later, in order between any two endpoints (as ZeroMQ's). A
tree reduction costs what its messages cost: the actors' own tree-reduce sends them.
"""

from __future__ import annotations

import asyncio
from collections import defaultdict

import numpy as np

from vastray.sim.costs import CostModel
from vastray.transport.codec import Message


class Cluster:
    """The shared state of P virtual nodes (see the module docstring). Endpoint P is the
    coordinator.

    Parameters
    ----------
    size : P, the number of nodes.
    costs : what work costs.
    """

    def __init__(self, size: int, costs: CostModel):
        self.size, self.costs = size, costs
        self.coordinator = size  # the coordinator's endpoint
        self._cores = asyncio.Semaphore(costs.cores) if costs.cores else None
        #: each endpoint's mailboxes by message kind (as a management actor's)
        self.mailboxes = [defaultdict(asyncio.Queue) for _ in range(size + 1)]
        self.compute_s = np.zeros(size + 1)  # (P + 1,) seconds each endpoint computed
        self.messages = 0
        self.bytes = 0
        self._link_free = np.zeros(size + 1)  # (P + 1,) when each outgoing link is free
        self._last_arrival: dict[tuple[int, int], float] = {}

    @staticmethod
    def now() -> float:
        return asyncio.get_running_loop().time()

    async def compute(self, rank: int, seconds: float) -> None:
        """Endpoint ``rank`` works ``seconds`` on a core (waiting for one if the cores are
        shared)."""
        if seconds <= 0:
            return
        self.compute_s[rank] += seconds
        if self._cores is None:
            await asyncio.sleep(seconds)
            return
        async with self._cores:
            await asyncio.sleep(seconds)

    def send(self, source: int, destination: int, message: Message, nbytes: int) -> None:
        """Post ``message`` (decoded, ``nbytes`` on the wire) from ``source`` to
        ``destination``'s mailbox of its kind."""
        now = self.now()
        leaves = max(now, self._link_free[source])
        self._link_free[source] = leaves + nbytes * self.costs.byte_s
        arrives = self._link_free[source] + self.costs.latency_s
        pair = (source, destination)
        arrives = max(arrives, self._last_arrival.get(pair, 0.0))
        self._last_arrival[pair] = arrives
        self.messages += 1
        self.bytes += nbytes
        asyncio.get_running_loop().call_at(
            arrives, self.mailboxes[destination][message.kind].put_nowait, message)
