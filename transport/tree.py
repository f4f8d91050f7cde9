"""The patterns over node ranks that reductions follow: the binary tree (films, termination
waves) and the butterfly (all-reductions).

Tree: rank 0 is the root; rank r's children are 2r + 1 and 2r + 2. A film climbs it in
ceil(log2 P) steps (each node adds its children's films to its own and passes the sum up).

Butterfly (recursive doubling): every node ends with the combined arrays after
log2(C) exchange steps, C the largest power of two <= P; at step s rank r < C swaps its
partial with rank r XOR 2^s and combines the two. The P - C ranks beyond C first fold their
arrays into rank r - C (step -1) and get the result back from it (step log2 C). A tree's
reduce-then-broadcast has 2 ceil(log2 P) message steps on its critical path; the butterfly
has log2 C (power-of-two P) or log2 C + 2.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def parent(rank: int) -> int | None:
    return None if rank == 0 else (rank - 1) // 2


def children(rank: int, size: int) -> list[int]:
    return [c for c in (2 * rank + 1, 2 * rank + 2) if c < size]


def butterfly(size: int) -> tuple[int, int]:
    """(C, log2 C) of a butterfly over ``size`` ranks: C, the largest power of two <= size,
    ranks exchange in log2 C steps."""
    steps = max(size, 1).bit_length() - 1
    return 1 << steps, steps


def exchange_partner(rank: int, size: int, step: int) -> int | None:
    """The rank ``rank`` exchanges partials with at ``step`` of a butterfly over ``size``
    ranks (-1: an extra rank's fold into the core; log2 C: the result back out; log2 C + 1 +
    s: step s's partner again, for the gather of a scattered reduction, ``gather_step``), or
    None where it has none at that step. The relation is symmetric."""
    core, steps = butterfly(size)
    if step in (-1, steps):
        if rank >= core:
            return rank - core
        return rank + core if rank + core < size else None
    if steps < step <= 2 * steps:
        step -= steps + 1
    if 0 <= step < steps and rank < core:
        return rank ^ (1 << step)
    return None


def gather_step(step: int, size: int) -> int:
    """The label of the gather's exchange with step ``step``'s partner (a scattered
    reduction's second half, ``scatters``), distinct from every butterfly step's."""
    return butterfly(size)[1] + 1 + step


#: Bytes of an all-reduction's arrays from which it scatters (``scatters``).
SCATTER_MIN_BYTES = 1 << 20


def scatters(size: int, nbytes: int) -> bool:
    """Whether an all-reduction of ``nbytes`` over ``size`` ranks reduces by scattering
    (recursive halving, then recursive doubling back: Rabenseifner's all-reduce, as MPI
    libraries do for long vectors) instead of exchanging whole partials at every step.

    Each of the butterfly's log2 C steps sends the whole array; a scattered reduction's
    2 log2 C steps send halves, quarters, ..., 2 (C - 1) / C of it in all. For a
    spec-insitu t-buffer of 4,194,304 paths (a tile of 4,096 paths on each of 1,024 nodes)
    that is 2 arrays' worth a node instead of 10. Small arrays keep the butterfly: its
    steps are half as many, and there a step's latency is the cost."""
    return butterfly(size)[1] >= 2 and nbytes >= SCATTER_MIN_BYTES


def scatter_ranges(rank: int, length: int, steps: int
                   ) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """(this rank's half, its partner's half) of the range at each step of a scattered
    reduction of ``length`` elements: at step s rank ``rank`` and its partner (rank XOR 2^s)
    hold [lo, hi); the rank whose bit s is 0 keeps [lo, mid), the other [mid, hi), mid =
    lo + (hi - lo) // 2, and the next step splits the half kept; the gather walks the same
    halves back."""
    lo, hi, halves = 0, length, []
    for step in range(steps):
        mid = lo + (hi - lo) // 2
        low, high = (lo, mid), (mid, hi)
        mine, theirs = (low, high) if not (rank >> step) & 1 else (high, low)
        halves.append((mine, theirs))
        lo, hi = mine
    return halves


def butterfly_steps(size: int) -> int:
    """Message steps on an all-reduction's critical path over ``size`` ranks."""
    core, steps = butterfly(size)
    return steps + (2 if size > core else 0)


def tree_steps(size: int) -> int:
    """Message steps of a wave down the binary tree of ``size`` ranks and its answers back
    up (a termination wave; the first design's all-reductions: reduce, then broadcast)."""
    return 2 * ((size - 1).bit_length() if size > 1 else 0)


#: Element-wise combiners of the reductions the schedulers need. The two partners of a
#: butterfly step apply them to the same two partials in the same order (the lower rank's
#: first): MAX and MIN of +0.0 and -0.0 keep the first operand's sign, so the order, not
#: commutativity, makes the partners' bits the same.
COMBINE: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "max": np.maximum,
    "min": np.minimum,
    "or": np.bitwise_or,
    "sum": np.add,
}
