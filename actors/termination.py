"""Termination detection at the coordinator for the round-based schedulers (``domain``,
``dynamic``): when every node is done with a tile (a round barrier), and for ``dynamic`` the
round's schedule sent to every node (the decision itself is ``schedule.dynamic``'s). The
asynchronous frames (``async``, ``temporal``) detect their end over the tree of ranks
without the coordinator (``actors.tree_termination``)."""

from __future__ import annotations

from vastray.actors import protocol
from vastray.schedule.dynamic import RayWeightedRounds
from vastray.transport.codec import encode


class Termination:
    """Termination detection for domain decomposition, per tile.

    ``domain``: a round ends when every node has reported; each node is told how many ray
    batches were sent to it; a round in which no batch moved ends the tile.

    ``barriers`` counts the points where every node waits for all the others: each round of
    ``domain`` and ``dynamic``.
    """

    def __init__(self, size: int, router, identities: dict[int, bytes], token: bytes):
        self.size, self.router, self.identities, self.token = size, router, identities, token
        self.rounds: dict[int, dict] = {}
        self.barriers = 0
        self.policy = RayWeightedRounds()

    #: The node reports it answers (``handle``).
    KINDS = (protocol.ROUND, protocol.QUEUES)

    async def handle(self, kind: str, meta: dict) -> None:
        """Take a node's report of one of ``KINDS``: a round's end, ``dynamic``'s queues."""
        handler = {protocol.ROUND: self.round_done, protocol.QUEUES: self.queues}[kind]
        await handler(meta)

    async def _send(self, rank: int, kind: str, meta: dict) -> None:
        await self.router.send_multipart([self.identities[rank], self.token,
                                          *encode(kind, {}, meta)])

    async def round_done(self, meta: dict) -> None:
        reports = self.rounds.setdefault(meta["tile"], {})
        reports[int(meta["rank"])] = meta["sent_to"]
        if len(reports) < self.size:
            return
        expect = {r: sum(sent.get(str(r), 0) for sent in reports.values())
                  for r in range(self.size)}
        finished = sum(expect.values()) == 0
        del self.rounds[meta["tile"]]
        self.barriers += 1
        for rank in range(self.size):
            await self._send(rank, protocol.GO, {"expect": expect[rank], "finished": finished})

    async def queues(self, meta: dict) -> None:
        """dynamic: once every node has reported, send this round's schedule (``policy``),
        with how many ray batches each node will receive."""
        reports = self.rounds.setdefault(meta["tile"], {})
        reports[int(meta["rank"])] = meta
        if len(reports) < self.size:
            return
        del self.rounds[meta["tile"]]
        self.barriers += 1
        waiting = {r: _summed(m["radiance"], m["shadow"]) for r, m in reports.items()}
        plan = self.policy.next_round(waiting, {r: m["loaded"] for r, m in reports.items()})
        expect = dict.fromkeys(range(self.size), 0)
        for rank, report in reports.items():
            for name in ("radiance", "shadow"):  # one batch per queue and destination
                for node in {plan.assign.get(int(d), rank) for d in report[name]} - {rank}:
                    expect[node] += 1
        for rank in range(self.size):
            await self._send(rank, protocol.SCHEDULE, {
                "assign": {str(d): p for d, p in plan.assign.items()}, "size": self.size,
                "finished": plan.finished, "expect": expect[rank]})


def _summed(radiance: dict, shadow: dict) -> dict[str, int]:
    """Rays waiting per domain on a node, both queues together (as ``next_round`` takes)."""
    total = dict(radiance)
    for domain, count in shadow.items():
        total[domain] = total.get(domain, 0) + count
    return total
