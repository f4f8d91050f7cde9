"""The binary tree over node ranks that reductions and broadcasts follow.

Rank 0 is the root; rank r's children are 2r + 1 and 2r + 2. A reduction climbs the tree in
ceil(log2 P) steps (each node combines its children's values with its own and passes the
result up); the broadcast walks back down the same edges.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np


def parent(rank: int) -> int | None:
    return None if rank == 0 else (rank - 1) // 2


def children(rank: int, size: int) -> list[int]:
    return [c for c in (2 * rank + 1, 2 * rank + 2) if c < size]


def depth(size: int) -> int:
    """Levels a value climbs from the deepest leaf to the root: ceil(log2 P) at most."""
    return 0 if size <= 1 else int(math.floor(math.log2(size)))


#: Element-wise combiners of the reductions the schedulers need.
COMBINE: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "min": np.minimum,
    "or": np.bitwise_or,
    "sum": np.add,
}


def reduce_in_tree(values: list[np.ndarray], op: str) -> tuple[np.ndarray, int]:
    """Reference evaluation of the tree reduction over ``values`` (one per rank), exactly in
    the order the nodes combine them. Returns the result and the number of levels used."""
    combine = COMBINE[op]
    size = len(values)
    partial = [np.array(v, copy=True) for v in values]
    for rank in reversed(range(size)):  # children before parents
        for child in children(rank, size):
            partial[rank] = combine(partial[rank], partial[child])
    return partial[0], depth(size)
