"""Per-domain ray queues: what goes in comes out, per domain, in push order."""

import numpy as np
import pytest

from vastray.schedule.soa import DomainQueues, SoA


def _rays(ids: np.ndarray) -> SoA:
    return SoA(id=ids.astype(np.int64), origin=np.repeat(ids[:, None], 3, 1).astype(np.float32))


def test_each_domain_pops_its_rays_in_push_order():
    rng = np.random.default_rng(3)
    queues = DomainQueues(5)
    expected = {d: [] for d in range(5)}
    next_id = 0
    for n in (40, 1, 0, 17, 64):
        domain = rng.integers(0, 5, n)
        ids = np.arange(next_id, next_id + n)
        next_id += n
        queues.push(domain, _rays(ids))
        for d in range(5):
            expected[d].extend(ids[domain == d].tolist())
    assert queues.counts().tolist() == [len(expected[d]) for d in range(5)]
    assert queues.total() == next_id
    for d in range(5):
        peeked = [c["id"] for c in queues.peek(d)]
        got = queues.pop(d)
        want = expected[d]
        if not want:
            assert got is None and peeked == []
            continue
        assert got["id"].tolist() == want
        assert np.concatenate(peeked).tolist() == want  # peek showed the same, in order
        assert (got["origin"] == np.asarray(want, np.float32)[:, None]).all()
        assert queues.count(d) == 0 and queues.pop(d) is None
    assert queues.total() == 0


def test_a_one_destination_push_is_not_changed_by_the_callers_later_field_swaps():
    queues = DomainQueues(3)
    rays = _rays(np.arange(4))
    queues.push(np.full(4, 2), rays)
    rays["id"] = np.full(4, -1)  # the caller rebinds a field after the push
    assert queues.pop(2)["id"].tolist() == [0, 1, 2, 3]


def test_nbytes_counts_each_held_block_once_until_its_last_run_is_popped():
    queues = DomainQueues(4)
    rays = _rays(np.arange(100))
    queues.push(np.arange(100) % 4, rays)
    assert queues.nbytes() == rays.nbytes()  # one sorted block, four runs
    for d in range(3):
        queues.pop(d)
        assert queues.nbytes() == rays.nbytes()  # domain 3 still holds the block
    queues.pop(3)
    assert queues.nbytes() == 0


def test_join_bound_joins_domains_and_rays_in_order_and_says_none_for_nothing():
    from vastray.schedule.soa import join_bound

    parts = [(np.array([3, 1]), SoA(path=np.array([10, 11]))),
             (np.array([2]), SoA(path=np.array([12])))]
    domains, rays = join_bound(parts)
    assert domains.tolist() == [3, 1, 2] and rays["path"].tolist() == [10, 11, 12]
    assert join_bound([]) is None


def test_a_mostly_popped_push_is_not_held_whole_by_the_rays_left_of_it():
    """Issue 37: one push spread over many domains was held whole until its last domain was
    served (455 MB held for 17 MB queued in a spec-ooc render); now the rays left are copied
    out once the popped ones kept alive pass the floor and half the queued bytes."""
    from vastray.schedule.soa import WASTE_FLOOR

    n, domains = 800_000, 40
    queues = DomainQueues(domains)
    rays = _rays(np.arange(n))
    assert rays.nbytes() > 2 * WASTE_FLOOR
    queues.push(np.arange(n) % domains, rays)
    for d in range(domains - 1):
        queues.pop(d)
    left = rays.nbytes() // domains
    assert queues.nbytes() <= 1.5 * left  # the last domain's rays, not the whole push
    assert queues.pop(domains - 1)["id"].tolist() == list(range(domains - 1, n, domains))
    assert queues.nbytes() == 0 and queues.total() == 0


def test_a_growing_array_keeps_every_block_in_order_across_reallocations():
    from vastray.schedule.soa import GrowingArray

    grown = GrowingArray(np.int32, capacity=3)
    blocks = [np.arange(k, dtype=np.int32) + 10 * k for k in (2, 0, 5, 1, 9)]
    for block in blocks:
        grown.append(block)
    assert len(grown) == sum(len(b) for b in blocks)
    assert np.array_equal(grown.values, np.concatenate(blocks))
    grown.values[[0, -1]] -= 1  # a view: assignments stay
    assert grown.values[0] == blocks[0][0] - 1 and grown.values[-1] == blocks[-1][-1] - 1


def test_take_by_mask_or_indices_copies_the_rows_fancy_indexing_would():
    rng = np.random.default_rng(5)
    rays = SoA(id=np.arange(50, dtype=np.int64), origin=rng.random((50, 3), dtype=np.float32),
               level=rng.integers(0, 4, 50).astype(np.int8))
    mask = rng.random(50) < 0.4
    for rows in (mask, np.flatnonzero(mask)[::-1], np.array([3, 3, -1]), np.zeros(50, bool),
                 np.array([], np.int64)):
        taken = rays.take(rows)
        for name, field in rays.fields.items():
            assert taken[name].dtype == field.dtype and taken[name].shape[1:] == field.shape[1:]
            assert np.array_equal(taken[name], field[rows])
            assert not np.shares_memory(taken[name], field)  # a copy: the caller may write
    with pytest.raises(IndexError, match="a mask of 49 rows for 50 rays"):
        rays.take(mask[:49])
    with pytest.raises(IndexError):
        rays.take(np.array([50]))
