"""Navrátil's dynamic ray-weighted schedule (Navrátil et al. 2012, "Dynamic Scheduling for
Large-Scale Distributed-Memory Ray Tracing", Figs. 5-6): the round-by-round decision of which
domain each node processes, from the rays waiting for each domain and the domains each node
has loaded.

A pure policy: it sees numbers, never sockets. Every node all-reduces two vectors over the
tree of ranks (rays waiting per domain, summed; the lowest rank holding each domain) and asks
``RayWeightedRounds.from_totals`` for the round's assignment, so every node computes the same
one with no coordinator (``actors.dynamic_frame.DynamicFrame``); each node then swaps rays so
that every domain's rays are on the node it was assigned to, and traces them there.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np


def image_plane_start(n_domains: int, rank: int) -> np.ndarray:
    """(D,) where node ``rank`` queues the rays it makes before the first round: all of them
    stay with it (an image-plane start), whichever domain they wait for, until a round's
    assignment moves them."""
    return np.full(n_domains, rank)


@dataclass(frozen=True)
class Round:
    """One round's decision.

    Parameters
    ----------
    assign : domain -> the node that processes it this round (its rays go there). Its order
        is the order each node processes its domains in: the kept domains first (ascending
        ids), then the newly assigned ones, most-wanted first.
    finished : no node has a ray waiting for any domain: the tile is done, nothing moves.
    """

    assign: dict[int, int]
    finished: bool


class RayWeightedRounds:
    """ScheduleNextRound (Navrátil et al. 2012, Fig. 5) for nodes that cache several domains.

    The paper's processes hold one domain each; ours hold a cache of several, so each node
    reports its whole resident set and "keep loaded domains where they are wanted" applies to
    every resident domain:

    1. A domain is *wanted* when some node has rays waiting for it; its weight is the sum of
       those rays over all nodes (Fig. 6's ray counts).
    2. A wanted domain resident somewhere stays with the lowest-ranked node holding it (no
       load: Fig. 5's "keep").
    3. The nodes none of whose resident domains is wanted (the paper's ``to_evict``), in rank
       order, each get one of the other wanted domains, most-wanted first; ties go to the
       lower domain id. Wanted domains left over when those nodes run out wait for a later
       round; nodes left over when the domains run out idle this round.

    The round is *finished* when no node reported any queue: every ray of the tile is done.
    """

    def next_round(self, queues: Mapping[int, Mapping[int | str, int]],
                   loaded: Mapping[int, Sequence[int]]) -> Round:
        """The round's assignment.

        Parameters
        ----------
        queues : node -> {domain: rays waiting for it on that node}; domains may be given as
            strings (as they arrive over the wire).
        loaded : node -> the domains resident in its cache; every node of the job is a key.

        Returns
        -------
        The round: domain -> node, and whether the tile is finished.
        """
        n_domains = 1 + max([int(d) for q in queues.values() for d in q]
                            + [int(d) for held in loaded.values() for d in held], default=-1)
        size = 1 + max(loaded, default=-1)
        wanted = np.zeros(n_domains, np.int64)
        for per_node in queues.values():
            for domain, count in per_node.items():
                wanted[int(domain)] += count
        holder = np.full(n_domains, size, np.int64)
        for node, held in loaded.items():
            for domain in held:
                holder[int(domain)] = min(holder[int(domain)], node)
        return self.from_totals(wanted, holder, size)

    def from_totals(self, wanted: np.ndarray, holder: np.ndarray, size: int) -> Round:
        """The round's assignment from vectors every node can all-reduce.

        Parameters
        ----------
        wanted : (D,) rays waiting for each domain, summed over the nodes.
        holder : (D,) the lowest rank holding each domain in its cache (``size``: none).
        size : the number of nodes.
        """
        wanted_ids = np.flatnonzero(wanted)
        held = wanted_ids[holder[wanted_ids] < size]
        assign = {int(d): int(holder[d]) for d in held}
        unheld = wanted_ids[holder[wanted_ids] >= size]
        to_assign = unheld[np.lexsort((unheld, -wanted[unheld]))]
        busy = set(assign.values())
        to_evict = [n for n in range(size) if n not in busy]
        for domain, node in zip(to_assign, to_evict, strict=False):
            assign[int(domain)] = node
        return Round(assign, finished=not wanted.any())
