"""Navrátil's dynamic ray-weighted schedule (Navrátil et al. 2012, "Dynamic Scheduling for
Large-Scale Distributed-Memory Ray Tracing", Figs. 5-6): the round-by-round decision of which
domain each node processes, from the rays waiting for each domain and the domains each node
has loaded.

A pure policy: it sees numbers, never sockets. The coordinator gathers every node's report
of a round, asks ``RayWeightedRounds.next_round`` for the round's assignment and sends it out
(``actors.termination``); each node then swaps rays so that every domain's rays are on the
node it was assigned to, and traces them there.
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
        is the order each node processes its domains in: the kept domains first (in the order
        the reports named them), then the newly assigned ones, most-wanted first.
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
        wanted: dict[int, int] = {}
        for per_node in queues.values():
            for domain, count in per_node.items():
                wanted[int(domain)] = wanted.get(int(domain), 0) + count
        holder: dict[int, int] = {}
        for node in sorted(loaded):
            for domain in sorted(loaded[node]):
                holder.setdefault(int(domain), node)
        assign = {d: holder[d] for d in wanted if d in holder}
        to_assign = sorted((d for d in wanted if d not in holder),
                           key=lambda d: (-wanted[d], d))
        busy = set(assign.values())
        to_evict = [n for n in sorted(loaded) if n not in busy]
        for domain, node in zip(to_assign, to_evict, strict=False):
            assign[domain] = node
        return Round(assign, finished=not any(queues.values()))
