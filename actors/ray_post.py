"""Ray batches between nodes: the one send path of every domain-decomposition runtime, and the
one place its traffic is counted (batches, rays and bytes each way, seconds spent sending)."""

from __future__ import annotations

import time

import numpy as np

from vastray.actors import protocol
from vastray.actors.job_options import DEFAULT_MAX_BATCH_RAYS
from vastray.schedule.soa import SoA, join_bound
from vastray.transport.codec import PEER_FRAME_LIMIT, encode, frames_nbytes


def traffic_counters() -> dict:
    """The report's traffic counters, at zero."""
    return {"batches_sent": 0, "batches_received": 0, "rays_sent": 0, "bytes_sent": 0,
            "rays_received": 0, "bytes_received": 0, "send_s": 0.0}


class RayPost:
    """Sends a node's ray batches to its peers and counts them both ways.

    Parameters
    ----------
    management : the node's management actor (``to_peer``).
    rank : this node's rank (every batch names it).
    stats : the node's report counters (``traffic_counters``' names are added to).
    max_batch : most rays in one batch of ``ship`` (larger outboxes are split).
    """

    def __init__(self, management, rank: int, stats: dict,
                 max_batch: int = DEFAULT_MAX_BATCH_RAYS):
        self.management, self.rank, self.stats = management, rank, stats
        self.max_batch = max(1, int(max_batch))
        for name, zero in traffic_counters().items():
            stats.setdefault(name, zero)
        #: batches sent per destination since the last ``take_sent_to``.
        self.sent_to: dict[int, int] = {}

    async def send(self, node: int, queue: str, meta: dict, domains: np.ndarray | None = None,
                   rays: SoA | None = None) -> None:
        """One batch to ``node``: ``rays`` ((m,) rows) bound for ``domains`` ((m,) ids) of its
        ``queue`` ("radiance" or "shadow"), or an empty batch (None: protocols that expect
        one batch per peer). ``meta`` labels it (its tile, and so on)."""
        arrays = {} if domains is None else {"domain": domains, **rays.fields}
        frames = encode(protocol.RAYS, arrays, {"queue": queue, "rank": self.rank, **meta},
                        PEER_FRAME_LIMIT)
        start = time.perf_counter()
        await self.management.to_peer(node, frames)
        self.stats["send_s"] += time.perf_counter() - start
        self.sent_to[node] = self.sent_to.get(node, 0) + 1
        self.stats["batches_sent"] += 1
        self.stats["rays_sent"] += 0 if domains is None else len(domains)
        self.stats["bytes_sent"] += frames_nbytes(frames)

    def batches(self, outbox: dict[tuple[str, int], list[tuple[np.ndarray, SoA]]]
                ) -> list[tuple[str, int, np.ndarray, SoA]]:
        """A schedule's outbox ((queue, node) -> [(domains, rays)]) as batches (queue, node,
        domains (m,), rays (m,)): the rays for one destination coalesced, at most
        ``max_batch`` a batch."""
        out = []
        for (queue, node), parts in outbox.items():
            domains, rays = join_bound(parts)
            for first in range(0, len(domains), self.max_batch):
                rows = np.arange(first, min(first + self.max_batch, len(domains)))
                out.append((queue, node, domains[rows], rays.take(rows)))
        return out

    async def ship(self, batches: list[tuple[str, int, np.ndarray, SoA]], meta: dict) -> None:
        """Send ``batches`` (``batches``' output), each labelled with ``meta``."""
        for queue, node, domains, rays in batches:
            await self.send(node, queue, meta, domains, rays)

    def take_sent_to(self) -> dict[int, int]:
        """Batches sent per destination since the last call (and start counting again)."""
        sent, self.sent_to = self.sent_to, {}
        return sent

    def received(self, message) -> None:
        """Count a batch taken in (its rays and bytes, when it has any)."""
        self.stats["batches_received"] += 1
        if message.arrays:
            self.stats["rays_received"] += len(message.arrays["domain"])
            self.stats["bytes_received"] += sum(a.nbytes for a in message.arrays.values())
