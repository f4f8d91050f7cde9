"""SpRay's front-to-back traversal score (schedule/traversal.py), shared by spec-ooc's round
order and the temporal scheduler's ``spray`` priority: hand counts on two boxes, and the
order spec-ooc had before the score was shared."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from vastray.schedule.geometry import DomainGeometry
from vastray.schedule.spec_ooc import traversal_order
from vastray.schedule.traversal import count_ahead, traversal_score


def two_boxes() -> DomainGeometry:
    """Domain 0 = [0, 1]^3, domain 1 = [1, 2] x [0, 1] x [0, 1]."""
    lo = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    return DomainGeometry(lo, lo + 1.0, np.ones(2, bool), origin_bound=3.0)


def test_the_score_of_a_hand_made_ray_set_is_the_hand_count():
    origins = np.array([[-1, .5, .5], [3, .5, .5], [-1, .5, .5], [-1, .5, .5], [.5, .5, .5]],
                       np.float32)
    directions = np.array([[1, 0, 0], [-1, 0, 0], [1, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    # ray 2 is already past domain 0's entry (t = 1); ray 3 ends (a hit) before domain 1's
    # entry (t = 2); ray 4 starts inside domain 0 and leaves it upwards
    limit = np.array([np.inf, np.inf, np.inf, 1.5, np.inf], np.float32)
    start = np.array([0, 0, 1.5, 0, 0], np.float32)
    counter = np.zeros((2, 2), np.int64)
    count_ahead(counter, two_boxes(), origins, directions, limit, start)
    # domain 0 is first along rays 0, 3, 4 and second along ray 1; domain 1 is first along
    # rays 1, 2 and second along ray 0
    assert counter.tolist() == [[3, 1], [2, 1]]
    # M = 2: first place weighs 2, second 1
    assert traversal_score(counter).tolist() == [3 * 2 + 1, 2 * 2 + 1]


def test_counting_adds_to_the_counter():
    counter = np.zeros((2, 2), np.int64)
    origins = np.array([[-1, .5, .5]], np.float32)
    directions = np.array([[1, 0, 0]], np.float32)
    for _ in range(2):
        count_ahead(counter, two_boxes(), origins, directions, np.array([np.inf], np.float32),
                    np.zeros(1, np.float32))
    assert counter.tolist() == [[2, 0], [0, 2]]


def test_rays_that_miss_every_box_count_nowhere():
    counter = np.zeros((2, 2), np.int64)
    count_ahead(counter, two_boxes(), np.array([[-1, 5, .5]], np.float32),
                np.array([[1, 0, 0]], np.float32), np.array([np.inf], np.float32),
                np.zeros(1, np.float32))
    assert not counter.any()
    assert traversal_score(counter).tolist() == [0, 0]


def old_traversal_order(counter, resident=frozenset(), domains=None):
    """spec-ooc's round order as written before the score was shared (commit f44783e)."""
    m = counter.shape[1]
    ids = np.arange(len(counter)) if domains is None else np.asarray(domains, np.int64)
    score = counter[ids] @ (m - np.arange(m))
    away = ~np.isin(ids, np.fromiter(resident, np.int64, len(resident)))
    return ids[np.lexsort((ids, -score, away))].tolist()


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 9), st.integers(0, 2**32 - 1), st.booleans())
def test_spec_ooc_orders_domains_as_before(n, seed, subset):
    rng = np.random.default_rng(seed)
    counter = rng.integers(0, 4, (n, n)).astype(np.int64) * (rng.random((n, n)) < 0.5)
    resident = frozenset(int(d) for d in np.flatnonzero(rng.random(n) < 0.3))
    domains = [int(d) for d in rng.permutation(n)[:rng.integers(1, n + 1)]] if subset else None
    assert traversal_order(traversal_score(counter), resident, domains) == \
        old_traversal_order(counter, resident, domains)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 6), max_size=40))
def test_ranks_count_each_pairs_place_among_its_rays_pairs(rays):
    """``_ranks`` (one pass over runs) gives each pair of a ray-sorted list its position
    among the pairs of the same ray: a binary search of every pair, as it was computed."""
    from vastray.schedule.geometry import _ranks

    ray = np.sort(np.asarray(rays, np.int64))
    expected = np.arange(len(ray)) - np.searchsorted(ray, ray, side="left")
    got = _ranks(ray)
    assert got.dtype == np.int32 and np.array_equal(got, expected)
