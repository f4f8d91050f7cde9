"""Belady's optimal load count, against a brute force over every eviction choice."""

from __future__ import annotations

import itertools
from functools import cache

import numpy as np
import pytest

from vastray.schedule.belady import belady_loads, next_uses


def brute_force_loads(sequence: tuple[int, ...], capacity: int) -> int:
    """The fewest loads over every possible eviction choice (exponential: tiny inputs)."""

    @cache
    def best(position: int, resident: frozenset) -> int:
        if position == len(sequence):
            return 0
        domain = sequence[position]
        if domain in resident:
            return best(position + 1, resident)
        if len(resident) < capacity:
            return 1 + best(position + 1, resident | {domain})
        return 1 + min(best(position + 1, (resident - {victim}) | {domain})
                       for victim in resident)

    return best(0, frozenset())


def test_next_uses_points_at_the_next_access_of_the_same_domain():
    assert next_uses([3, 1, 3, 3, 1, 2]).tolist() == [2, 4, 3, 6, 6, 6]
    assert next_uses([]).tolist() == []


@pytest.mark.parametrize("capacity", [1, 2, 3])
def test_belady_matches_the_brute_force_optimum(capacity):
    rng = np.random.default_rng(7)
    for _ in range(60):
        sequence = tuple(int(d) for d in rng.integers(0, 5, rng.integers(1, 11)))
        assert belady_loads(sequence, capacity) == brute_force_loads(sequence, capacity), \
            (sequence, capacity)


def test_belady_beats_lru_on_a_cyclic_sequence():
    # LRU misses every access of a cycle one longer than the cache; MIN keeps most of it
    sequence = list(itertools.chain.from_iterable([[0, 1, 2, 3]] * 5))
    assert belady_loads(sequence, 3) < len(sequence)
    assert belady_loads(sequence, 4) == 4  # everything fits: one load per domain
    assert belady_loads(sequence, 1) == len(sequence)  # no reuse with one slot


def test_belady_refuses_an_empty_cache():
    with pytest.raises(ValueError, match="at least 1"):
        belady_loads([1, 2], 0)
