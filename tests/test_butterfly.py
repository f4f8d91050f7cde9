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
from vastray.transport import tree
from vastray.transport.codec import decode, encode
from vastray.transport.tree import butterfly, butterfly_steps, exchange_partner, scatters


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


def reduce_on(size: int, calls: int, seed: int, lengths=(17, 5, 3, 8)):
    """Each of ``size`` nodes' results of ``calls`` all-reductions in a row over a shuffled
    network, the values, the ops and the messages sent."""
    rng = random.Random(seed)
    data = np.random.default_rng(seed)
    n_sum, n_min, n_or, n_max = lengths
    values = [[{"sum": data.random(n_sum) * 10.0 ** data.integers(-6, 6, n_sum),
                "min": data.integers(0, 1 << 40, n_min).reshape(-1, 1)[:, [0, 0]],
                "or": data.integers(0, 256, n_or, np.uint8),
                # signed zeros: MAX of +0.0 and -0.0 keeps the first operand's sign
                "max": np.where(data.random(n_max) < 0.5, -0.0, 0.0)}
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
    return results, values, ops, sent


def check_agreement(size, calls, results, values, ops):
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
                assert results[rank][call][name].shape == first[name].shape
                assert results[rank][call][name].tobytes() == first[name].tobytes()


@hsettings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(size=st.integers(1, 13), calls=st.integers(1, 4), seed=st.integers(0, 2**32 - 1))
def test_all_reductions_in_a_row_agree_bit_for_bit_whatever_the_delivery_order(size, calls,
                                                                               seed):
    results, values, ops, sent = reduce_on(size, calls, seed)
    core, steps = butterfly(size)
    assert sent == calls * (core * steps + 2 * (size - core))
    check_agreement(size, calls, results, values, ops)


@hsettings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(size=st.integers(4, 13), calls=st.integers(1, 3), seed=st.integers(0, 2**32 - 1),
       lengths=st.tuples(*[st.integers(0, 40)] * 4))
def test_a_scattered_reduction_gives_the_butterfly_s_bits_whatever_the_delivery_order(
        size, calls, seed, lengths, monkeypatch_module):
    """Long arrays reduce by halving then doubling (Rabenseifner's): every node ends with
    the whole arrays, bit for bit those of the butterfly's whole-array steps (float sums'
    grouping and zeros' signs included), in twice the steps; ranges a node holds may be
    empty where arrays are shorter than the nodes."""
    butterfly_results = reduce_on(size, calls, seed, lengths)
    with monkeypatch_module.context() as patch:
        patch.setattr(tree, "SCATTER_MIN_BYTES", 0)
        assert scatters(size, 0)
        results, values, ops, sent = reduce_on(size, calls, seed, lengths)
    core, steps = butterfly(size)
    assert sent == calls * (2 * core * steps + 2 * (size - core))
    check_agreement(size, calls, results, values, ops)
    for rank in range(size):
        for call in range(calls):
            for name in ops:
                assert (results[rank][call][name].tobytes()
                        == butterfly_results[0][rank][call][name].tobytes())


def test_short_arrays_and_two_nodes_keep_the_butterfly():
    assert not scatters(2, 1 << 30)  # one step: nothing to halve
    assert not scatters(1024, 64)
    assert scatters(4, tree.SCATTER_MIN_BYTES)


@pytest.fixture(scope="module")
def monkeypatch_module():
    with pytest.MonkeyPatch.context() as patch:
        yield patch


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


def test_a_scattered_partial_of_the_wrong_length_is_refused_naming_the_array():
    from vastray.actors.tree_reduce import _checked
    from vastray.transport.tree import scatter_ranges

    assert scatter_ranges(2, 10, 2) == [((0, 5), (5, 10)), ((2, 5), (0, 2))]
    assert scatter_ranges(1, 10, 2) == [((5, 10), (0, 5)), ((5, 7), (7, 10))]
    halves = {"t": scatter_ranges(0, 10, 1)[0]}  # this rank keeps [0, 5), its partner [5, 10)
    assert _checked({"t": np.zeros(5)}, halves, 0)["t"].shape == (5,)
    with pytest.raises(protocol.ProtocolError, match="'t' should hold 5 values"):
        _checked({"t": np.zeros(4)}, halves, 1)
    with pytest.raises(protocol.ProtocolError, match="'t' should hold"):
        _checked({}, halves, 0)
