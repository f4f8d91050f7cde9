"""Two-hop routes for ray batches among P nodes, as ``spec-insitu`` sends its copies.

Sent straight, every node may send a batch to every other in each iteration: P - 1 batches
out and in a node, and the node owning the most-crossed data receives (and its rays' holder
sends) one from nearly every node (issue 38: at 1,024 nodes by replay its 1,592 batches sent
and 1,207 received a frame took 0.31 s of its 0.95 s). Routed over a grid of w = ceil(sqrt P)
columns, a copy from node s to node d goes first to s's row, to the node in d's column
(``relay``), which forwards it down that column to d: a node sends one batch to each node of
its row and one to each node of its column, 2 (w - 1) in all, and receives as many. The
rays make two hops instead of one, but a hop's batch is the many small batches of a row
joined, and the counts are fixed by the routes, so nodes need not sum them over the tree to
know how many batches to wait for (one all-reduction an iteration fewer).

Where P is no square the last row is short: a copy from it whose relay would be a missing
node goes the other way round, first up its source's column to the destination's row.

The routes are a pure function of P: every node computes the same ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np


def relay_of(size: int, source: np.ndarray | int, destination: np.ndarray | int) -> np.ndarray:
    """The node that forwards a copy from ``source`` to ``destination`` (arrays of ranks,
    broadcast together): the node in the source's row and the destination's column (the
    source itself where both share a column: it forwards its own copies; the destination
    where both share a row: the first hop delivers); where that node does not exist (a
    source in a short last row), the node in the destination's row and the source's column,
    which does (the rows above the last are whole)."""
    width = grid_width(size)
    source, destination = np.asarray(source, np.int64), np.asarray(destination, np.int64)
    relay = source // width * width + destination % width
    return np.where(relay < size, relay, destination // width * width + source % width)


def grid_width(size: int) -> int:
    """Columns of the grid of ``size`` nodes: ceil(sqrt(size))."""
    if size < 1:
        raise ValueError(f"routes need at least 1 node, not {size}")
    width = int(np.sqrt(size))
    return width if width * width >= size else width + 1


@dataclass(frozen=True)
class Hops:
    """Every batch of an iteration: (k,) ``source`` and ``destination`` ranks of each hop's
    batches (one per pair and queue, empty or not), sorted by source then destination."""

    source: np.ndarray
    destination: np.ndarray

    def to(self, rank: int) -> list[int]:
        """The nodes ``rank`` sends a batch of this hop to."""
        return self.destination[self.source == rank].tolist()

    def count_from(self, rank: int) -> int:
        """How many batches of this hop ``rank`` receives."""
        return int(np.count_nonzero(self.destination == rank))


@lru_cache(maxsize=8)
def routes(size: int) -> tuple[Hops, Hops]:
    """(first hop, second hop) batches among ``size`` nodes: the first from each source to
    each distinct relay (or destination) of its copies, the second from each relay to each
    destination it forwards to; a node that is its own copies' relay sends them in the second
    hop only. Computed over all P^2 pairs at once (1,024 nodes: a million pairs, once)."""
    ranks = np.arange(size, dtype=np.int64)
    source = np.repeat(ranks, size)
    destination = np.tile(ranks, size)
    apart = source != destination
    source, destination = source[apart], destination[apart]
    relay = relay_of(size, source, destination)
    first = relay != source
    second = relay != destination
    return (_pairs(size, source[first], relay[first]),
            _pairs(size, relay[second], destination[second]))


def _pairs(size: int, source: np.ndarray, destination: np.ndarray) -> Hops:
    key = np.unique(source * size + destination)
    return Hops(key // size, key % size)
