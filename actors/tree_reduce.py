"""A node's tree-reduce actor: all-reductions of arrays (MIN, MAX, OR and SUM) over the
butterfly of ranks, every node ending with the result after log2 C exchange steps (C the
largest power of two <= P; two more where P is not one), and the film summed up the binary
tree of ranks to rank 0 in ceil(log2 P) steps (``transport.tree``)."""

from __future__ import annotations

import numpy as np

from vastray.actors import protocol
from vastray.actors.film_wire import film_frames, film_from
from vastray.actors.management import ManagementActor
from vastray.transport.codec import PEER_FRAME_LIMIT, encode
from vastray.transport.tree import (
    COMBINE,
    butterfly,
    children,
    exchange_partner,
    gather_step,
    parent,
    scatter_ranges,
    scatters,
)


class TreeReduceActor:
    """Combines partial results: all-reductions over the butterfly of ranks, films up the
    binary tree."""

    def __init__(self, management: ManagementActor, rank: int, size: int):
        self.management, self.rank, self.size = management, rank, size
        #: message steps the last all-reduce waited on at this node
        #: (``transport.tree.butterfly_steps`` at a rank that folds in an extra one, 2 at an
        #: extra rank, log2 C at the others)
        self.steps = 0
        #: all-reductions begun, numbering each one's partials: every node makes the same
        #: calls in the same order (they are collective), and a partner may already be in the
        #: next one
        self._calls = 0
        #: partials that came before this node asked for them, by (call, step)
        self._early_partials: dict[tuple[int, int], object] = {}
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
        """Combine ``arrays`` over all nodes (``ops``: name -> "max" | "min" | "or" | "sum");
        every node returns the same arrays, bit for bit.

        Recursive doubling: at step s this node sends its partial to rank XOR 2^s, receives
        that node's, and combines the two; after log2 C steps every core rank holds the
        combination of all. The two partners of a step combine the same two partials in the
        same order, the lower rank's first, so they (and by induction all nodes) hold
        identical bits whatever the combiner: float sums, whose grouping differs from a serial
        sum's but is fixed by P, and MAX or MIN of a +0.0 and a -0.0, which keep the first's
        sign. Ranks beyond C fold into rank - C first and are sent the result last.
        """
        if set(arrays) != set(ops):
            raise ValueError(f"all-reduce: arrays {sorted(arrays)} and combiners {sorted(ops)} "
                             "must name the same arrays")
        total = {k: np.array(v, copy=True) for k, v in arrays.items()}
        call, self._calls = self._calls, self._calls + 1
        core, steps = butterfly(self.size)
        if self.rank >= core:  # an extra rank: its partner combines for it
            await self._send(call, -1, total)
            self.steps = 2
            return {k: np.array(v) for k, v in (await self._partial(call, steps)).items()}
        self.steps = steps
        folds = exchange_partner(self.rank, self.size, -1) is not None
        if folds:
            total = _combined(total, await self._partial(call, -1), ops)
            self.steps += 2
        if scatters(self.size, sum(v.nbytes for v in total.values())):
            total = await self._scattered(call, total, ops)
        else:
            for step in range(steps):
                await self._send(call, step, total)
                theirs = await self._partial(call, step)
                lower_first = self.rank < exchange_partner(self.rank, self.size, step)
                total = (_combined(total, theirs, ops) if lower_first
                         else _combined(theirs, total, ops))
        if folds:
            await self._send(call, steps, total)
            # the send may still read these arrays (ZeroMQ sends large frames without a
            # copy): the caller gets its own
            total = {k: v.copy() for k, v in total.items()}
        return total

    async def _scattered(self, call: int, total: dict[str, np.ndarray], ops: dict[str, str]
                         ) -> dict[str, np.ndarray]:
        """The core ranks' part of a long all-reduction (``transport.tree.scatters``):
        recursive halving, each step sending the half of the range the partner keeps and
        combining the half this rank keeps, then recursive doubling, each step sending the
        range this rank holds and taking the partner's. Every element is combined by the
        same partners in the same order as the butterfly's whole-array steps (the lower
        rank's partial first), so the bits are the butterfly's; arrays are flattened and
        each is split alone. Sends read ``flat`` without a copy (ZeroMQ's large frames):
        the halving writes only the half it keeps, and the doubling writes a half it sent
        while halving only once the partner's reply, which needed that half, has come."""
        steps = butterfly(self.size)[1]
        self.steps += steps  # the gather walks the steps back
        flat = {k: np.ascontiguousarray(v).reshape(-1).copy() for k, v in total.items()}
        ranges = {k: scatter_ranges(self.rank, len(v), steps) for k, v in flat.items()}
        for step in range(steps):
            halves = {k: ranges[k][step] for k in flat}
            await self._send(call, step, {k: flat[k][slice(*halves[k][1])] for k in flat})
            theirs = _checked(await self._partial(call, step), halves, 0)  # for my half
            lower_first = not (self.rank >> step) & 1
            for k, ((lo, hi), _) in halves.items():
                mine = flat[k][lo:hi]
                flat[k][lo:hi] = (COMBINE[ops[k]](mine, theirs[k]) if lower_first
                                  else COMBINE[ops[k]](theirs[k], mine))
        for step in reversed(range(steps)):
            halves = {k: ranges[k][step] for k in flat}
            label = gather_step(step, self.size)
            await self._send(call, label, {k: flat[k][slice(*halves[k][0])] for k in flat})
            theirs = _checked(await self._partial(call, label), halves, 1)
            for k, (_, (lo, hi)) in halves.items():
                flat[k][lo:hi] = theirs[k]
        # copies: the last sends may still read ``flat`` (large frames go without a copy),
        # and a caller may write into what it gets
        return {k: flat[k].reshape(total[k].shape).copy() for k in total}

    async def _send(self, call: int, step: int, arrays: dict[str, np.ndarray]) -> None:
        partner = exchange_partner(self.rank, self.size, step)
        await self.management.to_peer(partner, encode(
            protocol.EXCHANGE, arrays, {"rank": self.rank, "call": call, "step": step},
            PEER_FRAME_LIMIT))

    async def _partial(self, call: int, step: int) -> dict[str, np.ndarray]:
        """The arrays this node's partner sent at ``step`` of all-reduce ``call`` (those of
        other steps are kept until asked for)."""
        while (call, step) not in self._early_partials:
            message = await self.management.receive(
                protocol.EXCHANGE, f"all-reduce partial from node "
                f"{exchange_partner(self.rank, self.size, step)}")
            key = (int(message.meta["call"]), int(message.meta["step"]))
            self._early_partials[key] = message.arrays
        return self._early_partials.pop((call, step))


def _checked(partial: dict[str, np.ndarray], halves: dict, which: int) -> dict[str, np.ndarray]:
    """``partial`` if each array holds as many values as its range ``halves[k][which]``;
    else a ``ProtocolError`` naming the array."""
    for k, ranges in halves.items():
        lo, hi = ranges[which]
        if k not in partial or len(partial[k]) != hi - lo:
            raise protocol.ProtocolError(f"scattered all-reduce: {k!r} should hold {hi - lo} "
                                         "values from the partner")
    return partial


def _combined(first: dict[str, np.ndarray], second: dict[str, np.ndarray],
              ops: dict[str, str]) -> dict[str, np.ndarray]:
    return {name: COMBINE[op](first[name], second[name]) for name, op in ops.items()}
