"""Belady's optimal replacement (MIN): the fewest loads a cache of a given size needs to serve
a sequence of domain accesses, evicting at each miss the resident domain used again furthest
in the future. The bound an out-of-core schedule's own access sequence allows: its loads over
this count is what a better eviction rule could still save (``bench/ooc.py``)."""

from __future__ import annotations

import heapq
from collections.abc import Sequence

import numpy as np


def next_uses(sequence: Sequence[int]) -> np.ndarray:
    """(n,) int64: for each access, the position of the next access to the same domain (n
    where there is none)."""
    seq = np.asarray(sequence, np.int64)
    n = len(seq)
    out = np.full(n, n, np.int64)
    if n == 0:
        return out
    order = np.lexsort((np.arange(n), seq))  # by domain, then position
    same = seq[order[1:]] == seq[order[:-1]]
    out[order[:-1][same]] = order[1:][same]
    return out


def belady_loads(sequence: Sequence[int], capacity: int) -> int:
    """The fewest loads a cache of ``capacity`` domains makes serving ``sequence`` (each
    access needs its domain resident; the cache starts empty; no loading ahead).

    Parameters
    ----------
    sequence : (n,) domain ids in the order they were accessed.
    capacity : domains the cache holds (>= 1).
    """
    if capacity < 1:
        raise ValueError(f"capacity must be at least 1 domain, got {capacity}")
    following = next_uses(sequence)
    resident: dict[int, int] = {}  # domain -> the position of its next access
    furthest: list[tuple[int, int]] = []  # max-heap of (-next access, domain), stale allowed
    loads = 0
    for position, domain in enumerate(int(d) for d in sequence):
        if domain not in resident:
            loads += 1
            if len(resident) == capacity:
                while True:  # pop stale entries until a resident domain's current next use
                    negative_next, victim = heapq.heappop(furthest)
                    if resident.get(victim) == -negative_next:
                        del resident[victim]
                        break
        resident[domain] = int(following[position])
        heapq.heappush(furthest, (-resident[domain], domain))
    return loads
