"""``schedule.relay``: the two-hop routes spec-insitu's copies travel."""

import numpy as np
import pytest

from vastray.schedule.relay import grid_width, relay_of, routes


def _pairs(hops) -> set[tuple[int, int]]:
    return set(zip(hops.source.tolist(), hops.destination.tolist(), strict=True))


@pytest.mark.parametrize("size", [1, 2, 3, 4, 5, 7, 8, 9, 16, 17, 31, 64, 100])
def test_every_copy_arrives_in_at_most_two_hops_the_routes_name(size):
    first, second = _pairs(routes(size)[0]), _pairs(routes(size)[1])
    width = grid_width(size)
    for source in range(size):
        for destination in range(size):
            if source == destination:
                continue
            via = int(relay_of(size, source, destination))
            assert 0 <= via < size
            if via == destination:
                assert (source, destination) in first
            elif via == source:
                assert (source, destination) in second
            else:
                assert (source, via) in first and (via, destination) in second
                # across the source's row, then down the destination's column (or, from a
                # short last row, up the source's column, then across the destination's row)
                assert (via // width == source // width and via % width == destination % width
                        or via % width == source % width
                        and via // width == destination // width)
    assert not any(s == d for s, d in first | second)


@pytest.mark.parametrize("size", [4, 9, 16, 64, 1024])
def test_on_a_square_grid_a_node_talks_to_its_row_and_its_column(size):
    """2 (w - 1) batches out and in a node, against P - 1 sent straight."""
    first, second = routes(size)
    width = grid_width(size)
    assert width * width == size
    for rank in (0, size // 2, size - 1):
        out = first.to(rank) + second.to(rank)
        assert sorted(first.to(rank)) == [r for r in range(size)
                                          if r // width == rank // width and r != rank]
        assert sorted(second.to(rank)) == [r for r in range(size)
                                           if r % width == rank % width and r != rank]
        assert len(out) == first.count_from(rank) + second.count_from(rank) == 2 * (width - 1)


@pytest.mark.parametrize("size", [2, 3, 5, 10, 17, 50, 1000])
def test_a_short_last_row_keeps_the_fan_out_near_twice_the_width(size):
    first, second = routes(size)
    width = grid_width(size)
    for rank in range(size):
        assert len(first.to(rank)) + len(second.to(rank)) <= 3 * (width - 1)
        assert first.count_from(rank) + second.count_from(rank) <= 3 * (width - 1)
    assert len(first.source) + len(second.source) <= size * (size - 1)


def test_routes_need_a_node():
    with pytest.raises(ValueError, match="at least 1 node"):
        grid_width(0)
    assert [grid_width(n) for n in (1, 2, 4, 5, 1024, 1025)] == [1, 2, 2, 3, 32, 33]
    assert np.array_equal(relay_of(4, np.array([0, 0, 3]), np.array([3, 1, 0])), [1, 1, 2])


def _batch(meta: dict, **arrays):
    from vastray.actors import protocol
    from vastray.transport.codec import decode, encode

    base = {"queue": "radiance", "tile": 0, "depth": 1}
    return decode(encode(protocol.RAYS, arrays, {**base, **meta}))


def test_a_node_takes_only_the_copies_its_routes_bring_it():
    """``actors.insitu.check_copies`` on 4 nodes (a 2 x 2 grid: node 1 relays node 0's copies
    for node 3): a first hop names each ray's destination, and only one this node relays to
    from its sender or itself; a second hop only this node's domains; a batch of another
    iteration, from a stranger or with an index past the tile is refused, naming why."""
    from vastray.actors.insitu import check_copies
    from vastray.actors.protocol import ProtocolError
    from vastray.schedule.ownership import Holders

    owner = np.array([0, 1, 2, 3])
    local = owner == 1

    owned = Holders.owned(owner)

    def check(message, rank=1, holders=owned):
        return check_copies(message, 0, 1, holders, rank, 4, 10, 2, owner == rank)

    path = np.array([1, 2])
    assert check(_batch({"hop": 1, "rank": 0}, domain=np.array([1, 3]), path=path,
                        to=np.array([1, 3]))) == 1
    assert check(_batch({"hop": 2, "rank": 3}, domain=np.array([1, 1]), path=path)) == 2
    assert check(_batch({"hop": 1, "rank": 0})) == 1  # an empty batch: counted
    assert local.sum() == 1
    refused = [
        (_batch({"hop": 1, "rank": 2}, domain=np.array([3, 3]), path=path,
                to=np.array([3, 3])), "does not relay"),  # 2 sends to 3 straight
        (_batch({"hop": 1, "rank": 0}, domain=np.array([2, 3]), path=path,
                to=np.array([3, 3])), "destination does not hold"),
        (_batch({"hop": 2, "rank": 3}, domain=np.array([1, 2]), path=path), "destination does not hold"),
        (_batch({"hop": 1, "rank": 0}, domain=np.array([1, 1]), path=path), "'to'"),
        (_batch({"hop": 3, "rank": 0}), "hop must be 1 or 2"),
        (_batch({"hop": 1, "rank": 0, "depth": 0}), "iteration 0 in tile 0 iteration 1"),
        (_batch({"hop": 1, "rank": 7}), "not a peer"),
        (_batch({"hop": 1, "rank": 1}), "not a peer"),
        (_batch({"hop": 2, "rank": 3}, domain=np.array([1, 1]), path=np.array([1, 10])),
         "path outside"),
        (_batch({"hop": 2, "rank": 3}, domain=np.array([1, 9]), path=path), "beyond"),
    ]
    for message, why in refused:
        with pytest.raises(ProtocolError, match=why):
            check(message)
    # domain 1 held by nodes 1 and 3: node 1 takes its even paths, node 3 its odd ones
    shared = Holders(np.array([0, 1, 3, 4, 5]), np.array([0, 1, 3, 2, 3]))
    even, odd = np.array([2, 4]), np.array([2, 3])
    assert check(_batch({"hop": 2, "rank": 3}, domain=np.array([1, 1]), path=even),
                 holders=shared) == 2
    with pytest.raises(ProtocolError, match="does not hold"):
        check(_batch({"hop": 2, "rank": 3}, domain=np.array([1, 1]), path=odd), holders=shared)
