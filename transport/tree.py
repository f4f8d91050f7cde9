"""The binary tree over node ranks that reductions and broadcasts follow.

Rank 0 is the root; rank r's children are 2r + 1 and 2r + 2. A reduction climbs the tree in
ceil(log2 P) steps (each node combines its children's values with its own and passes the
result up); the broadcast walks back down the same edges.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def parent(rank: int) -> int | None:
    return None if rank == 0 else (rank - 1) // 2


def children(rank: int, size: int) -> list[int]:
    return [c for c in (2 * rank + 1, 2 * rank + 2) if c < size]


#: Element-wise combiners of the reductions the schedulers need.
COMBINE: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "max": np.maximum,
    "min": np.minimum,
    "or": np.bitwise_or,
    "sum": np.add,
}
