"""A node's tree-reduce actor: reductions over the binary tree of ranks in ceil(log2 P) steps
(MIN, MAX, OR and SUM of arrays, and the film, summed up the tree to rank 0)."""

from __future__ import annotations

import numpy as np

from vastray.actors import protocol
from vastray.actors.film_wire import film_frames, film_from
from vastray.actors.management import ManagementActor
from vastray.transport.codec import PEER_FRAME_LIMIT, encode
from vastray.transport.tree import COMBINE, children, parent


class TreeReduceActor:
    """Combines partial results up the binary tree of ranks (ceil(log2 P) steps)."""

    def __init__(self, management: ManagementActor, rank: int, size: int):
        self.management, self.rank, self.size = management, rank, size
        #: levels the last all-reduce climbed below this node (at the root: the tree's height,
        #: floor(log2 P) <= ceil(log2 P)); carried up in each partial's header.
        self.levels = 0
        #: films from children for a later frame than the one being reduced, by (child rank,
        #: frame ordinal): a child goes on to its next frame without waiting for this node.
        self._early_films: dict[tuple[int, int], object] = {}

    async def reduce_film(self, film, width: int, height: int, ordinal: int = 0):
        """Sum this subtree's films of frame ``ordinal`` (the job's frames counted from 0);
        the root returns the total, others send it up.

        Each child's film is the one it labelled with ``ordinal``, taken in ascending child
        rank, so the sum is the same whatever order films arrive in. (Taking the next film to
        arrive mixed frames in animations: a child one frame ahead sent its next film before
        the other child's film of this frame came, and frames lost or doubled samples.)
        """
        for child in children(self.rank, self.size):
            film.merge(film_from(await self._child_film(child, ordinal), width, height))
        up = parent(self.rank)
        if up is not None:
            await self.management.to_peer(up, film_frames(
                film, {"rank": self.rank, "ordinal": ordinal}, PEER_FRAME_LIMIT))
        return film

    async def _child_film(self, child: int, ordinal: int):
        """The film ``child`` sent for frame ``ordinal`` (those of later frames are kept)."""
        while (child, ordinal) not in self._early_films:
            message = await self.management.receive("film", "film from a child node")
            key = (int(message.meta["rank"]), int(message.meta.get("ordinal", 0)))
            self._early_films[key] = message
        return self._early_films.pop((child, ordinal))

    async def allreduce(self, arrays: dict[str, np.ndarray], ops: dict[str, str]
                        ) -> dict[str, np.ndarray]:
        """Combine ``arrays`` over all nodes (``ops``: name -> "max" | "min" | "or" | "sum")
        up the tree, then broadcast the result down it; every node returns the same arrays."""
        total = {k: np.array(v, copy=True) for k, v in arrays.items()}
        self.levels = 0
        for _ in children(self.rank, self.size):
            message = await self.management.receive(protocol.REDUCE, "partial from a child node")
            self.levels = max(self.levels, int(message.meta.get("levels", 0)) + 1)
            for name, op in ops.items():
                total[name] = COMBINE[op](total[name], message.arrays[name])
        up = parent(self.rank)
        if up is not None:
            await self.management.to_peer(up, encode(
                protocol.REDUCE, total, {"rank": self.rank, "levels": self.levels},
                PEER_FRAME_LIMIT))
            message = await self.management.receive(protocol.BROADCAST, "reduced result")
            total = {k: np.array(v) for k, v in message.arrays.items()}
        for child in children(self.rank, self.size):
            await self.management.to_peer(child, encode(
                protocol.BROADCAST, total, {"rank": self.rank}, PEER_FRAME_LIMIT))
        return total
