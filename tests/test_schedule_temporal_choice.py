"""The temporal scheduler's per-node policy (schedule/temporal/choice.py) and per-frame
assignment (``assign_frame``) on hand-made inputs: no store, no sockets, no processes."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.render.camera import Camera
from vastray.schedule.temporal import (
    Assignment,
    CacheView,
    FrameStats,
    TemporalChoice,
    assign_affinity,
    assign_frame,
    assign_temporal,
    eye_domain,
    groups_fit,
    projected_rects,
    screen_tiles,
    sequential_owners,
    spatial_owners,
)
from vastray.schedule.temporal.choice import worth_loading


def policy(kind: str = "queue+resident", n: int = 3, previous: FrameStats | None = None,
           local: np.ndarray | None = None) -> TemporalChoice:
    """A node's policy over ``n`` domains of 1 MB, all local and equally near by default."""
    local = np.ones(n, bool) if local is None else local
    return TemporalChoice(kind, previous, 0, local, np.zeros(n), np.full(n, 1e6))


def choose(p: TemporalChoice, waiting, resident=(), capacity: int | None = 1, arrived=None):
    """``p.choose`` with no loads yet this frame (None capacity: no cache)."""
    n = len(waiting)
    cache = None if capacity is None else CacheView(frozenset(resident), capacity)
    return p.choose(np.asarray(waiting, np.int64), cache, np.zeros(n),
                    np.zeros(n, np.int64) if arrived is None else np.asarray(arrived))


# -- the d* rule --------------------------------------------------------------------------------
def test_the_fullest_domain_is_active_and_the_next_fullest_is_preloaded():
    p = policy()
    c = choose(p, [5, 1, 3])
    assert (c.active, c.preload) == (0, 2)
    assert c.protect == {0, 2}
    assert p.upcoming == 2
    # the priorities the cache evicts by: Q_CUR, the active domain no candidate
    assert c.priorities.tolist() == [-np.inf, 1.0, 3.0]


def test_d_star_is_activated_when_it_has_rays():
    p = policy()
    choose(p, [5, 1, 3])  # d* = 2
    assert choose(p, [9, 0, 1], resident={0}).active == 2  # though domain 0 holds more


def test_without_rays_d_star_gives_way_to_the_best_scored_domain():
    p = policy()
    choose(p, [5, 1, 3])  # d* = 2
    assert choose(p, [1, 4, 0], resident={0}).active == 0  # resident: queue+resident's first


def test_with_one_slot_d_star_is_not_the_domain_the_load_just_evicted():
    p = policy()
    choose(p, [5, 1, 3])  # d* = 2
    # Domain 2 is activated; loading it into the one slot evicts domain 0. Counted as cached,
    # 0 would outrank 1 (queue+resident puts cached domains first) and be d*: loaded again
    # right after its eviction.
    c = choose(p, [2, 3, 3], resident={0}, capacity=1)
    assert c.active == 2
    assert p.upcoming == 1 and c.preload == 1
    assert c.priorities.tolist() == [2.0, 3.0, -np.inf]  # 0 no longer counted as cached


def test_the_evicted_domain_would_be_d_star_with_a_second_slot():
    # the same queues with room for both: nothing is evicted, 0 stays cached and leads
    p = policy()
    choose(p, [5, 1, 3], capacity=2)
    c = choose(p, [2, 3, 3], resident={0}, capacity=2)
    assert (c.active, p.upcoming, c.preload) == (2, 0, None)  # 0 is resident: no load


def test_rays_only_in_foreign_domains_activate_the_fullest():
    p = policy(kind="queue", local=np.array([True, False, False]))
    c = choose(p, [0, 2, 7])
    assert c.active == 2  # no candidate has rays: the fullest queue
    assert c.preload is None and c.protect == {2}


def test_without_a_cache_d_star_is_preloaded_unguarded():
    p = policy(kind="queue")
    c = choose(p, [5, 1, 3], capacity=None)
    assert (c.active, c.preload) == (0, 2)


def test_frame_zero_uses_the_bootstrap_priority_and_unknown_kinds_are_refused():
    assert policy(kind="cost-rate").kind == "queue+resident"
    assert policy(kind="cost-benefit").kind == "queue"
    stats = FrameStats.zeros(3, 1)
    assert policy(kind="cost-rate", previous=stats).kind == "cost-rate"
    assert not policy(kind="queue").needs_traversal_score
    assert policy(kind="spray").needs_traversal_score
    with pytest.raises(ValueError, match="unknown priority 'lru'"):
        policy(kind="lru")


def test_spray_scores_come_from_the_traversal_score_given():
    p = policy(kind="spray")
    n = 3
    c = p.choose(np.array([5, 1, 3]), CacheView(frozenset(), 2), np.zeros(n), np.zeros(n),
                 np.array([1.0, 7.0, 4.0]))
    assert (c.active, c.preload) == (1, 2)  # by score, not by queue length


def cost_rate_policy() -> TemporalChoice:
    """Four 1 MB domains after a frame in which each processed 100 rays in 1 s and was loaded
    once, the node loaded 1 MB/s, and domain 3 (not this node's) sent 50 rays to domain 2."""
    sent = np.zeros((4, 4), np.int64)
    sent[3, 2] = 50
    stats = FrameStats(sent, np.full(4, 100), np.ones(4), np.full(4, 100), np.ones(4),
                       np.array([1e6]), np.array([1.0]))
    return policy("cost-rate", 4, stats, np.array([True, True, True, False]))


def test_cost_rate_prefers_the_cached_domain_and_counts_the_rays_still_to_come():
    c = choose(cost_rate_policy(), [9, 2, 1, 0], resident={0, 1}, capacity=2)
    # work per second of loading: cached 1 -> 2 rays / 100 rays/s / 1 ms = 20; domain 2 must
    # load (1 s) and expects its 1 ray plus the 50 of Q_POT: 51 / 100 / 1 = 0.51
    assert c.active == 0 and c.preload is None  # d* = 1 is cached already
    np.testing.assert_allclose(c.priorities, [-np.inf, 20.0, 0.51, -np.inf])
    c = choose(cost_rate_policy(), [9, 2, 1, 0], resident={0, 1}, capacity=2,
               arrived=[0, 0, 50, 0])
    np.testing.assert_allclose(c.priorities[2], 0.01)  # the 50 rays came: Q_POT = 0


# -- the preload guard --------------------------------------------------------------------------
def test_the_guard_refuses_a_preload_that_would_evict_a_higher_scored_domain():
    scores = np.array([5.0, 1.0, 3.0])
    full = CacheView(frozenset({0, 2}), 2)
    assert not worth_loading(1, scores, frozenset({0, 1}), full)  # would evict 2 (3 > 1)
    assert worth_loading(2, np.array([5.0, 4.0, 3.0, 1.0]), frozenset({0, 2}),
                         CacheView(frozenset({0, 3}), 2))  # evicts 3 (1 < 3)
    assert worth_loading(1, scores, frozenset({0, 1}), CacheView(frozenset({0}), 2))  # room
    assert not worth_loading(2, scores, frozenset({0, 2}), full)  # resident already
    assert not worth_loading(None, scores, frozenset({0}), full)
    # everything resident is protected: nothing can make room
    assert not worth_loading(1, scores, frozenset({0, 1, 2}), full)


def test_cost_rate_activates_by_the_rays_queued_now_and_preloads_by_the_prediction():
    # Domain 2 holds 1 ray and expects 50 (Q_POT); domain 1 holds 2. Both are cached. The
    # active domain is picked for the rays it holds; Q_POT still ranks d*, what comes next.
    p = cost_rate_policy()
    c = choose(p, [0, 2, 1, 0], resident={1, 2}, capacity=2)
    assert c.active == 1
    assert p.upcoming == 2  # d*: 51 predicted rays
    again = choose(p, [0, 3, 1, 0], resident={1, 2}, capacity=2)
    assert again.active == 1  # d* holds a ray, but not the most: no carry-over for cost-rate


def test_a_tie_with_the_victim_is_no_reason_to_load():
    assert not worth_loading(1, np.array([5.0, 3.0, 3.0]), frozenset({0, 1}),
                             CacheView(frozenset({0, 2}), 2))


# -- the frame's assignment -----------------------------------------------------------------------
def boxes():
    lo = np.array([[x, 0.0, 0.0] for x in range(4)])
    return lo, lo + 1.0, np.array([True, True, False, True]), np.array([1e6, 2e6, 0.0, 3e6])


def frame_inputs() -> tuple[tuple, FrameStats]:
    """``assign_frame``'s arguments before the statistics (2 nodes, a 32x24 image of the
    ``boxes``), and statistics in which domains 0 and 3 traded 10 rays."""
    camera = Camera(np.array([2.0, 0.5, -6.0]), np.array([2.0, 0.5, 0.5]),
                    np.array([0.0, 1.0, 0.0]), 60.0, 32, 24)
    lo, hi, nonempty, nbytes = boxes()
    stats = FrameStats.zeros(4, 2)
    stats.sent[0, 3] = 10
    return (camera, lo, hi, nonempty, nbytes, 32, 24, 2), stats


def test_assign_frame_picks_the_assignment_by_kind():
    args, stats = frame_inputs()
    camera, lo, hi, nonempty, nbytes = args[:5]

    def same(a, b):
        return np.array_equal(a.owner, b.owner) and np.array_equal(a.tiles, b.tiles) \
            and a.replicated == b.replicated

    assert same(assign_frame("sequential", *args, stats),
                sequential_owners(4, 2, nonempty, 32, 24))
    spatial = spatial_owners(lo, hi, 2, nonempty, 32, 24)
    assert same(assign_frame("spatial", *args, stats), spatial)
    assert same(assign_frame("paper", *args, None), spatial)  # frame 0: no statistics
    temporal = assign_temporal(screen_tiles(32, 24, 2), projected_rects(camera, lo, hi),
                               stats.sent, nbytes, stats.s_load(), nonempty,
                               eye_domain(camera.position, lo, hi, nonempty))
    assert same(assign_frame("paper", *args, stats), temporal)
    assert temporal.owner[0] != temporal.owner[3]  # the pair that trades rays is split
    with pytest.raises(ValueError, match="unknown assignment 'random'"):
        assign_frame("random", *args, stats)


# -- cache affinity -------------------------------------------------------------------------------
def paper_split() -> Assignment:
    """Algorithm 1's answer for 2 nodes and 4 one-megabyte domains: node 0 gets {0, 1} and
    tile 0, node 1 gets {2, 3} and tile 1."""
    return Assignment(np.array([0, 0, 1, 1]), np.array([[0, 0, 16, 24], [16, 0, 32, 24]]))


MB4 = np.full(4, 1e6)


def test_affinity_binds_each_unit_to_the_node_that_holds_it():
    held = np.array([[0, 0, 1, 1], [1, 1, 0, 0]])  # the nodes hold each other's units
    a = assign_affinity(paper_split(), held, np.zeros((4, 4)), MB4, np.ones(2), 100.0)
    assert a.owner.tolist() == [1, 1, 0, 0]
    assert a.tiles.tolist() == [[16, 0, 32, 24], [0, 0, 16, 24]]  # tiles go with their units


def test_affinity_keeps_a_held_domain_unless_moving_it_saves_more_than_its_load():
    held = np.array([[1, 1, 1, 0], [0, 0, 0, 0]])  # node 0 still holds domain 2
    sent = np.zeros((4, 4))
    sent[2, 1] = 50  # keeping 2 with {0, 1} trades 50 rays inside node 0's group
    kept = assign_affinity(paper_split(), held, sent, MB4, np.ones(2), rays_per_reload=100.0)
    assert kept.owner.tolist() == [0, 0, 0, 1]  # half a load's worth of rays: not worth a load
    moved = assign_affinity(paper_split(), held, sent, MB4, np.ones(2), rays_per_reload=20.0)
    assert moved.owner.tolist() == [0, 0, 1, 1]  # 2.5 loads' worth: Algorithm 1's placement
    slow = assign_affinity(paper_split(), held, sent, MB4, np.array([1.0, 4.0]), 20.0)
    # the new owner loads 4x faster: a move costs a quarter of the 2.5 loads it saves on node 0
    assert slow.owner.tolist() == [0, 0, 1, 1]
    never = assign_affinity(paper_split(), held, sent, MB4, np.ones(2), np.inf)
    assert never.owner.tolist() == [0, 0, 0, 1]  # no loads last frame: nothing pays a move


def test_affinity_without_held_domains_is_algorithm_1():
    paper = paper_split()
    a = assign_affinity(paper, np.zeros((2, 4)), np.ones((4, 4)), MB4, np.ones(2), 1.0)
    assert np.array_equal(a.owner, paper.owner) and np.array_equal(a.tiles, paper.tiles)


def test_affinity_never_moves_the_replicated_domain_or_empty_ones():
    paper = Assignment(np.array([0, -1, 1, 1]), np.array([[0, 0, 16, 24], [16, 0, 32, 24]]),
                       replicated=2)
    held = np.array([[0, 0, 1, 0], [0, 0, 0, 0]])
    a = assign_affinity(paper, held, np.zeros((4, 4)), MB4, np.ones(2), 100.0)
    assert a.owner.tolist() == [0, -1, 1, 1] and a.replicated == 2


def test_assign_frame_affinity_follows_what_the_nodes_held():
    args, stats = frame_inputs()
    stats.loads[:] = 2
    stats.proc_rays[:] = 1000  # 1,000 rays per reload: 10 rays traded are not worth a move
    paper = assign_frame("paper", *args, stats)
    holder = paper.owner[3]
    stats.held[holder, 0] = 1  # domain 0 is held where Algorithm 1 put domain 3
    affinity = assign_frame("affinity", *args, stats)
    assert affinity.owner[0] == holder  # its unit (and tile) went to the node holding it
    assert affinity.owner[3] != holder  # and the pair that trades rays is still split
    stats.held[holder, 3] = 1  # now the holder holds both: it keeps them unless that costs
    stats.sent[0, 3] = 10_000  # 10 reloads' worth of rays traded: the pair is split
    split = assign_frame("affinity", *args, stats)
    assert split.owner[0] != split.owner[3] and holder in split.owner[[0, 3]]
    stats.loads[:] = 1  # every domain loaded once: no reloads, so trading costs nothing
    assert assign_frame("affinity", *args, stats).owner[[0, 3]].tolist() == [holder, holder]
    assert np.array_equal(assign_frame("affinity", *args, None).owner,
                          assign_frame("spatial", *args, None).owner)  # frame 0


# -- fit: the static groups while they fit the caches ---------------------------------------------
def test_groups_fit_counts_each_nodes_domains_and_the_replicated_one():
    tiles = np.zeros((2, 4), np.int64)
    two_and_one = Assignment(np.array([0, 0, -1, 1]), tiles)
    assert groups_fit(two_and_one, 2) and not groups_fit(two_and_one, 1)
    assert groups_fit(two_and_one, None)  # no bound
    # domain 3 is replicated: node 0 may load it too, so node 0's working set is 3 domains
    replicated = Assignment(np.array([0, 0, -1, 1]), tiles, replicated=3)
    assert groups_fit(replicated, 3) and not groups_fit(replicated, 2)


def test_fit_is_spatial_while_each_group_fits_its_cache_and_affinity_where_not():
    args, stats = frame_inputs()  # 2 nodes, 3 non-empty domains: spatial groups of 2 and 1
    stats.loads[:] = 2
    stats.proc_rays[:] = 1000
    spatial = assign_frame("spatial", *args, stats)
    affinity = assign_frame("affinity", *args, stats)
    assert not np.array_equal(spatial.owner, affinity.owner)  # the test can tell them apart
    for capacity in (2, 3, None):  # the largest group, 2 domains, fits
        fit = assign_frame("fit", *args, stats, capacity)
        assert np.array_equal(fit.owner, spatial.owner) and fit.replicated is None
    small = assign_frame("fit", *args, stats, 1)  # it does not: Algorithm 1 with affinity
    assert np.array_equal(small.owner, affinity.owner)
    assert np.array_equal(small.tiles, affinity.tiles) and small.replicated == affinity.replicated
    # frame 0 has no statistics: spatial whatever the cache
    assert np.array_equal(assign_frame("fit", *args, None, 1).owner, spatial.owner)
