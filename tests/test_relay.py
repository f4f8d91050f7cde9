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
