"""The all-reductions' butterfly (``transport.tree``, ``actors.tree_reduce``): every rank has
one partner per step, the relation is symmetric and covers every rank; P nodes making several
all-reductions in a row, their partials delivered in any order (a partner already in the
next call), all end each call with the same arrays, bit for bit (float sums and the signs of
zeros included)."""

from __future__ import annotations

import asyncio
import random
from collections import defaultdict

import numpy as np
import pytest
from hypothesis import HealthCheck, given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

from vastray.actors import protocol
from vastray.actors.tree_reduce import TreeReduceActor
from vastray.transport.codec import decode, encode
from vastray.transport.tree import butterfly, butterfly_steps, exchange_partner


@pytest.mark.parametrize("size", range(1, 41))
def test_every_rank_has_one_symmetric_partner_a_step_and_every_rank_takes_part(size):
    core, steps = butterfly(size)
    assert core <= size < 2 * core and core == 1 << steps
    for rank in range(size):
        partners = {}
        for step in range(-1, steps + 1):
            partner = exchange_partner(rank, size, step)
            if partner is not None:
                assert 0 <= partner < size and partner != rank
                assert exchange_partner(partner, size, step) == rank
                partners[step] = partner
        if rank >= core:  # an extra rank: folds in and gets the result back, from one rank
            assert set(partners) == {-1, steps} and partners[-1] == partners[steps] < core
        else:
            assert all(step in partners for step in range(steps))
            assert (-1 in partners) == (rank < size - core) == (steps in partners)
    # every rank's partial reaches every rank: the exchange graph's steps compose to all
    reach = [{rank} for rank in range(size)]
    for step in [-1, *range(steps), steps]:
        before = [set(r) for r in reach]
        for rank in range(size):
            partner = exchange_partner(rank, size, step)
            if partner is not None and (step != -1 or rank < core) and (step != steps
                                                                       or rank >= core):
                reach[rank] |= before[partner]
    assert all(r == set(range(size)) for r in reach)
    assert butterfly_steps(size) == steps + (2 if size > core else 0)


class ShuffledNetwork:
    """Management actors of ``size`` nodes whose messages arrive after random delays: in any
    order, across pairs and steps, but each message once."""

    def __init__(self, size: int, rng: random.Random):
        self.rng = rng
        self.boxes = [defaultdict(asyncio.Queue) for _ in range(size)]
        self.in_flight: set[asyncio.Task] = set()
        self.sent = 0

    def management(self, rank: int):
        network = self

        class Management:
            async def to_peer(self, peer: int, frames) -> None:
                message = decode([bytes(f) for f in frames])
                protocol.check_peer_kind(message, rank, peer, len(network.boxes))
                network.sent += 1
                task = asyncio.ensure_future(network._deliver(peer, message))
                network.in_flight.add(task)
                task.add_done_callback(network.in_flight.discard)

            async def receive(self, kind: str, what: str):
                return await asyncio.wait_for(network.boxes[rank][kind].get(), 10.0)

        return Management()

    async def _deliver(self, peer: int, message) -> None:
        await asyncio.sleep(self.rng.random() * 0.002)
        self.boxes[peer][message.kind].put_nowait(message)


@hsettings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(size=st.integers(1, 13), calls=st.integers(1, 4), seed=st.integers(0, 2**32 - 1))
def test_all_reductions_in_a_row_agree_bit_for_bit_whatever_the_delivery_order(size, calls,
                                                                               seed):
    rng = random.Random(seed)
    data = np.random.default_rng(seed)
    values = [[{"sum": data.random(17) * 10.0 ** data.integers(-6, 6, 17),
                "min": data.integers(0, 1 << 40, 5), "or": data.integers(0, 256, 3, np.uint8),
                # signed zeros: MAX of +0.0 and -0.0 keeps the first operand's sign
                "max": np.where(data.random(8) < 0.5, -0.0, 0.0)}
               for _ in range(size)] for _ in range(calls)]
    ops = {"sum": "sum", "min": "min", "or": "or", "max": "max"}

    async def node(network, rank):
        actor = TreeReduceActor(network.management(rank), rank, size)
        results = []
        for call in range(calls):
            await asyncio.sleep(rng.random() * 0.002)  # nodes reach each call at other times
            results.append(await actor.allreduce(values[call][rank], ops))
        assert not actor._early_partials  # every partial taken by the call it belongs to
        return results

    async def run():
        network = ShuffledNetwork(size, rng)
        out = await asyncio.gather(*[node(network, r) for r in range(size)])
        return out, network.sent

    results, sent = asyncio.run(run())
    core, steps = butterfly(size)
    assert sent == calls * (core * steps + 2 * (size - core))
    for call in range(calls):
        first = results[0][call]
        np.testing.assert_allclose(first["sum"], np.sum([v["sum"] for v in values[call]], 0),
                                   rtol=1e-13)
        np.testing.assert_array_equal(first["min"],
                                      np.minimum.reduce([v["min"] for v in values[call]]))
        np.testing.assert_array_equal(first["or"],
                                      np.bitwise_or.reduce([v["or"] for v in values[call]]))
        for rank in range(1, size):
            for name in ops:
                assert results[rank][call][name].tobytes() == first[name].tobytes()


def test_arrays_without_a_combiner_are_refused():
    actor = TreeReduceActor(None, 0, 1)
    with pytest.raises(ValueError, match="must name the same arrays"):
        asyncio.run(actor.allreduce({"a": np.zeros(2), "b": np.zeros(2)}, {"a": "sum"}))


def test_a_partial_from_a_rank_not_the_partner_of_its_step_is_refused():
    message = decode(encode(protocol.EXCHANGE, {"x": np.zeros(1)},
                            {"rank": 3, "call": 0, "step": 0}))
    protocol.check_peer_kind(message, 3, 2, 4)  # 2 XOR 1 = 3
    with pytest.raises(protocol.ProtocolError, match="not node 1's partner at that step"):
        protocol.check_peer_kind(message, 3, 1, 4)
    fold = decode(encode(protocol.EXCHANGE, {}, {"rank": 5, "call": 0, "step": -1}))
    protocol.check_peer_kind(fold, 5, 1, 6)  # the extra rank 5 folds into 5 - 4
    with pytest.raises(protocol.ProtocolError):
        protocol.check_peer_kind(fold, 5, 0, 6)
