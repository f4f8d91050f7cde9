"""Temporal-coherence scheduling (schedule/temporal/): screen tiles, box projection,
Algorithm 1 (note A6, A7), the frame statistics and Eq 1-4 with the Table 2 priorities (A8)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vastray.render.camera import Camera
from vastray.schedule.temporal import (
    ASSIGNMENTS,
    PRIORITIES,
    Assignment,
    FrameStats,
    PriorityInputs,
    assign_temporal,
    best,
    bootstrap_priority,
    dep_prime,
    eye_domain,
    load_time,
    pixel_tiles,
    potential,
    priority,
    projected_rects,
    resident_after_load,
    screen_tiles,
    sequential_owners,
    spatial_owners,
    victim,
)

MB = 1e6


# -- screen tiles ------------------------------------------------------------------------------
def test_eight_nodes_at_16_9_are_a_4_by_2_grid_in_row_major_order():
    tiles = screen_tiles(1920, 1080, 8)
    xs, ys = [0, 480, 960, 1440, 1920], [0, 540, 1080]
    expected = [(xs[c], ys[r], xs[c + 1], ys[r + 1]) for r in range(2) for c in range(4)]
    assert tiles.dtype == np.int64
    assert tiles.tolist() == [list(t) for t in expected]


def test_screen_tile_grid_follows_the_aspect_ratio():
    def grid(w, h, n):
        t = screen_tiles(w, h, n)
        return len(np.unique(t[:, 0])), len(np.unique(t[:, 1]))

    assert grid(1920, 1080, 2) == (2, 1)
    assert grid(1080, 1920, 2) == (1, 2)
    assert grid(1080, 1920, 8) == (2, 4)
    assert grid(100, 100, 4) == (2, 2)
    assert grid(320, 180, 16) == (4, 4)  # 4x4 (ratio 1) beats 8x2 (ratio 4) for 16:9
    assert grid(300, 100, 3) == (3, 1)
    assert grid(100, 100, 7) == (7, 1)  # a prime: a tie between 7x1 and 1x7 goes to columns
    assert grid(3, 100, 7) == (1, 7)  # tiles at least one pixel wide win over a closer ratio


def test_pixel_tiles_index_pixels_row_major_from_the_top():
    tiles = screen_tiles(1920, 1080, 8)
    tile = pixel_tiles(tiles, 1920, 1080)
    assert tile.shape == (1920 * 1080,) and tile.dtype == np.int64
    assert tile[10 * 1920 + 1900] == 3  # top row, right column
    assert tile[1079 * 1920 + 0] == 4  # bottom row, left column
    assert tile[540 * 1920 + 479] == 4 and tile[539 * 1920 + 480] == 1


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 300), st.integers(1, 200), st.integers(1, 40))
def test_screen_tiles_cover_the_image_exactly_once(width, height, n):
    tiles = screen_tiles(width, height, n)
    assert tiles.shape == (n, 4)
    tile = pixel_tiles(tiles, width, height)
    area = (tiles[:, 2] - tiles[:, 0]) * (tiles[:, 3] - tiles[:, 1])
    assert (area >= 0).all() and area.sum() == width * height
    assert (tile >= 0).all()  # every pixel covered, and the areas add up: no overlap either
    assert np.array_equal(np.bincount(tile, minlength=n), area)
    if (area == 0).any():  # more tiles than the image has pixels across or down
        assert n > min(width, height)
        return
    a = len(np.unique(tiles[:, 0]))
    b = n // a
    assert a * b == n
    # uneven splits spread the remainder: widths (heights) differ by at most one pixel
    widths, heights = tiles[:, 2] - tiles[:, 0], tiles[:, 3] - tiles[:, 1]
    assert widths.max() - widths.min() <= 1 and heights.max() - heights.min() <= 1
    # row-major: tile r * a + c
    assert np.array_equal(tiles[:, 0], tiles[:a, 0][np.arange(n) % a])
    assert np.array_equal(tiles[:, 1], tiles[::a, 1][np.arange(n) // a])
    # no other a' x b' grid with tiles of at least one pixel is closer to the aspect ratio
    target = np.log(width / height)
    for a2 in range(1, n + 1):
        if n % a2 == 0 and a2 <= width and n // a2 <= height:
            assert abs(np.log(a / b) - target) <= abs(np.log(a2 / (n // a2)) - target) + 1e-12


# -- projection --------------------------------------------------------------------------------
def test_projected_rects_agree_with_camera_generate():
    """A tiny box on a camera ray projects into that ray's pixel (row 0 at the top)."""
    cam = Camera(np.array([1.0, 2.0, 3.0]), np.array([0.2, -0.1, -1.0]), np.array([0.0, 1.0, 0.0]),
                 50.0, 64, 36)
    rng = np.random.default_rng(4)
    pixel = rng.integers(0, 64 * 36, 200).astype(np.uint32)
    origins, dirs = cam.generate(pixel, np.zeros(200, np.uint32), seed=7)
    points = origins + dirs * rng.uniform(1.0, 20.0, (200, 1))
    rects = projected_rects(cam, points - 1e-9, points + 1e-9)
    cx, cy = (rects[:, 0] + rects[:, 2]) / 2, (rects[:, 1] + rects[:, 3]) / 2
    x, y = pixel % 64, pixel // 64
    assert np.all((cx >= x - 1e-6) & (cx <= x + 1 + 1e-6))
    assert np.all((cy >= y - 1e-6) & (cy <= y + 1 + 1e-6))
    assert rects.shape == (200, 4) and rects.dtype == np.float64


def test_projected_rects_clip_to_the_screen_and_give_boxes_behind_the_eye_everything():
    cam = Camera(np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]), 90.0, 100, 50)
    lo = np.array([[-0.5, -0.25, -2.0],   # in front, centred: aspect 2, tan(45°) = 1
                   [-1.0, -1.0, -1.0],    # straddles the eye plane
                   [0.0, 0.0, 1.0],       # wholly behind
                   [50.0, -0.1, -2.0],    # far to the right: clipped to zero width at x = W
                   [-0.5, -5.0, -2.0]])   # tall: clipped to the screen's height
    hi = np.array([[0.5, 0.25, -1.0],
                   [1.0, 1.0, 1.0],
                   [1.0, 1.0, 2.0],
                   [51.0, 0.1, -1.0],
                   [0.5, 5.0, -1.0]])
    rects = projected_rects(cam, lo, hi)
    # nearest face at depth 1: x = +-0.5 -> +-0.5 / (tan 45° * aspect 2) = +-1/4 of the half width
    # (50 px) around 50; y = +-0.25 -> +-1/4 of the half height (25 px) around 25, up = row 0
    assert np.allclose(rects[0], [37.5, 18.75, 62.5, 31.25])
    assert rects[1].tolist() == [0.0, 0.0, 100.0, 50.0]
    assert rects[2].tolist() == [0.0, 0.0, 100.0, 50.0]
    assert rects[3, 0] == rects[3, 2] == 100.0
    assert rects[4, 1] == 0.0 and rects[4, 3] == 50.0


def test_eye_domain_is_the_lowest_non_empty_box_containing_the_eye():
    lo = np.array([[0.0, 0, 0], [0.5, 0, 0], [-1, -1, -1], [0, 0, 0]])
    hi = np.array([[1.0, 1, 1], [2.0, 1, 1], [2, 2, 2], [1, 1, 1]])
    nonempty = np.array([False, True, True, True])
    assert eye_domain(np.array([0.7, 0.5, 0.5]), lo, hi, nonempty) == 1
    assert eye_domain(np.array([0.2, 0.5, 0.5]), lo, hi, nonempty) == 2
    assert eye_domain(np.array([1.0, 1.0, 1.0]), lo, hi, nonempty) == 1  # boundary counts
    assert eye_domain(np.array([5.0, 0.5, 0.5]), lo, hi, nonempty) is None


# -- Algorithm 1: the note's A6 known answer ---------------------------------------------------
def a6_stats() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    sent = np.zeros((4, 4), np.int64)
    sent[0, 1], sent[1, 0], sent[0, 2], sent[2, 0] = 100, 50, 10, 5
    stats = FrameStats.zeros(4, 2)
    stats.load_bytes[:] = [10 * MB, 40 * MB]
    stats.load_s[:] = [1.0, 2.0]
    return sent, np.array([1.0, 2.0, 3.0, 4.0]) * MB, stats.s_load()


def check_a6(a: Assignment, tiles: np.ndarray):
    assert a.replicated is None
    assert a.owner.tolist() == [0, 1, 0, 1]  # node0 {D0, D2}, node1 {D1, D3}
    assert np.array_equal(a.tiles, tiles)  # node0 tile 0, node1 tile 1
    assert np.flatnonzero(a.owns(0)).tolist() == [0, 2]
    assert np.flatnonzero(a.owns(1)).tolist() == [1, 3]


def test_a6_known_answer_from_given_rectangles():
    sent, volume, speed = a6_stats()
    assert speed.tolist() == [10 * MB, 20 * MB]
    tiles = np.array([[0, 0, 100, 100], [100, 0, 200, 100]])
    rects = np.array([[10.0, 10, 90, 90], [60, 10, 100, 90], [100, 10, 140, 90], [110, 10, 190, 90]])
    check_a6(assign_temporal(tiles, rects, sent, volume, speed, np.ones(4, bool)), tiles)


def test_a6_known_answer_from_a_camera():
    """Four unit boxes in a row seen from the front: D0 is the largest in the left tile (it is the
    farthest off axis, so its side shows), D3 in the right one."""
    lo = np.array([[i, 0.0, 0.0] for i in range(4)])
    hi = lo + 1.0
    cam = Camera(np.array([2.0, 0.5, 6.0]), np.array([2.0, 0.5, 0.5]), np.array([0.0, 1.0, 0.0]),
                 60.0, 200, 100)
    tiles = screen_tiles(200, 100, 2)
    rects = projected_rects(cam, lo, hi)
    assert tiles.tolist() == [[0, 0, 100, 100], [100, 0, 200, 100]]
    assert eye_domain(cam.position, lo, hi, np.ones(4, bool)) is None
    sent, volume, speed = a6_stats()
    check_a6(assign_temporal(tiles, rects, sent, volume, speed, np.ones(4, bool)), tiles)
    # the growth step picked D2 for unit 0 because it exchanged the FEWEST rays with D0: with
    # s(0,2) large instead, D1 joins D0
    sent2 = sent.copy()
    sent2[0, 2] = 1000
    # (unit 0 = {D0, D1}, 3 MB -> slow node 0; unit 1 = {D3, D2}, 7 MB -> fast node 1)
    a = assign_temporal(tiles, rects, sent2, volume, speed, np.ones(4, bool))
    assert a.owner.tolist() == [0, 0, 1, 1]


def test_frame_zero_without_statistics_still_assigns_every_domain_evenly():
    rng = np.random.default_rng(1)
    d, n = 37, 4
    tiles = screen_tiles(160, 90, n)
    rects = np.sort(rng.uniform(0, 160, (d, 4)), axis=1)[:, [0, 1, 2, 3]]
    nonempty = np.ones(d, bool)
    nonempty[[3, 8]] = False
    a = assign_temporal(tiles, rects, np.zeros((d, d), np.int64), np.ones(d), np.ones(n), nonempty)
    assert (a.owner[~nonempty] == -1).all()
    counts = np.bincount(a.owner[nonempty], minlength=n)
    assert counts.sum() == 35 and counts.max() - counts.min() <= 1


def test_a_domain_best_for_several_tiles_stays_with_the_tile_that_overlaps_it_most():
    tiles = np.array([[0, 0, 10, 10], [10, 0, 20, 10], [20, 0, 30, 10]])
    # D0 covers tile 1 fully (100) and tile 0 partly (60); D1 is tile 0's second best (50);
    # D2 is tile 2's best; D3 overlaps tile 0 by 20.
    rects = np.array([[4.0, 0, 20, 10], [0, 0, 5, 10], [20, 0, 30, 10], [0, 0, 2, 10]])
    sent = np.zeros((4, 4), np.int64)
    a = assign_temporal(tiles, rects, sent, np.array([1.0, 1, 1, 1]), np.ones(3), np.ones(4, bool))
    node_of_tile = {tuple(t): i for i, t in enumerate(a.tiles.tolist())}
    assert a.owner[0] == node_of_tile[(10, 0, 20, 10)]  # D0 stays with tile 1 (100 > 60)
    assert a.owner[1] == node_of_tile[(0, 0, 10, 10)]  # tile 0 takes its best untaken, D1
    assert a.owner[2] == node_of_tile[(20, 0, 30, 10)]


def test_eye_inside_a_box_replicates_it_and_seeds_units_by_rays_sent():
    d, n = 6, 2
    tiles = screen_tiles(100, 50, n)
    rects = np.tile([0.0, 0.0, 100.0, 50.0], (d, 1))
    sent = np.zeros((d, d), np.int64)
    sent[4, 5] = 30   # s(4) = 30: the largest after the eye domain
    sent[5, 4] = 20   # s(5) = 20: second; 4 and 5 trade rays, so they end up apart anyway
    sent[2, 0] = 100  # the eye domain 2 sends the most, but it is replicated, not a seed
    a = assign_temporal(tiles, rects, sent, np.ones(d), np.array([1.0, 2.0]), np.ones(d, bool),
                        eye=2)
    assert a.replicated == 2
    assert a.owns(0)[2] and a.owns(1)[2]
    assert a.owner[4] != a.owner[5]  # seeds of different units
    others = np.array([0, 1, 3, 4, 5])
    counts = np.bincount(a.owner[others], minlength=n)
    assert counts.tolist() in ([3, 2], [2, 3])
    assert a.owner[2] == 1  # the fastest node is the replicated domain's routing default
    with pytest.raises(ValueError):
        assign_temporal(tiles, rects, sent, np.ones(d), np.ones(n), np.arange(d) != 2, eye=2)


# -- Algorithm 1: the note's A7 properties -----------------------------------------------------
@st.composite
def assignment_cases(draw):
    d = draw(st.integers(1, 40))
    n = draw(st.integers(1, 6))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    nonempty = rng.random(d) < draw(st.sampled_from([0.5, 0.9, 1.0]))
    sent = np.where(rng.random((d, d)) < 0.3, rng.integers(0, 50, (d, d)), 0).astype(np.int64)
    if draw(st.booleans()):
        sent[:] = 0  # frame 0
    volume = rng.integers(1, 4, d).astype(np.float64)  # small integers: ties in bytes happen
    speed = rng.integers(1, 3, n).astype(np.float64)  # ... and ties in speed
    w, h = draw(st.sampled_from([(320, 180), (64, 64), (50, 200)]))
    rects = np.sort(rng.uniform(-20, w + 20, (d, 2)), axis=1)
    rows = np.sort(rng.uniform(-20, h + 20, (d, 2)), axis=1)
    rects = np.clip(np.stack([rects[:, 0], rows[:, 0], rects[:, 1], rows[:, 1]], axis=1),
                    0, [w, h, w, h])
    eye = None
    if nonempty.any() and draw(st.booleans()):
        eye = int(rng.choice(np.flatnonzero(nonempty)))
    return screen_tiles(w, h, n), (w, h), rects, sent, volume, speed, nonempty, eye


@settings(max_examples=80, deadline=None)
@given(assignment_cases())
def test_a7_assign_temporal_properties(case):
    tiles, (w, h), rects, sent, volume, speed, nonempty, eye = case
    n = len(tiles)
    a = assign_temporal(tiles, rects, sent, volume, speed, nonempty, eye)
    b = assign_temporal(tiles, rects, sent, volume, speed, nonempty, eye)
    assert np.array_equal(a.owner, b.owner) and np.array_equal(a.tiles, b.tiles)  # deterministic
    assert a.owner.dtype == np.int64 and a.replicated == eye
    # every non-empty domain in exactly one group (the replicated one in all), empties in none
    assert (a.owner[~nonempty] == -1).all()
    assert ((a.owner[nonempty] >= 0) & (a.owner[nonempty] < n)).all()
    member = np.stack([a.owns(r) for r in range(n)])
    count = member.sum(axis=0)
    expected = np.where(nonempty, 1, 0)
    if eye is not None:
        expected[eye] = n
    assert np.array_equal(count, expected)
    # group sizes (without the replicated domain) differ by at most one
    grouped = nonempty.copy()
    if eye is not None:
        grouped[eye] = False
    sizes = np.bincount(a.owner[grouped], minlength=n)
    assert sizes.max() - sizes.min() <= 1
    # units matched by bytes to nodes by speed: faster node, no fewer bytes
    group_bytes = member.astype(float) @ volume
    order = np.argsort(-speed, kind="stable")
    assert np.all(np.diff(group_bytes[order]) <= 1e-9)
    # the nodes' tiles are the screen tiles, each once: they cover the image exactly once
    assert sorted(map(tuple, a.tiles.tolist())) == sorted(map(tuple, tiles.tolist()))
    assert (pixel_tiles(a.tiles, w, h) >= 0).all()


def test_assign_temporal_handles_4096_domains():
    """Completes on the largest domain count the project runs (measured ~0.3 s on one core)."""
    d, n = 4096, 8
    rng = np.random.default_rng(2)
    sent = np.zeros((d, d), np.int64)
    pairs = rng.integers(0, d, (100_000, 2))
    sent[pairs[:, 0], pairs[:, 1]] = rng.integers(1, 1000, len(pairs))
    nonempty = rng.random(d) < 0.9
    lo = rng.uniform(-10, 10, (d, 3))
    cam = Camera(np.array([0.0, 0.0, 30.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), 50.0, 320, 180)
    rects = projected_rects(cam, lo, lo + 1.0)
    a = assign_temporal(screen_tiles(320, 180, n), rects, sent, rng.uniform(1, 10, d) * MB,
                        rng.uniform(1, 2, n) * MB, nonempty)
    sizes = np.bincount(a.owner[nonempty], minlength=n)
    assert sizes.sum() == nonempty.sum() and sizes.max() - sizes.min() <= 1
    assert (a.owner[~nonempty] == -1).all()


# -- the Table 2 comparators -------------------------------------------------------------------
def test_sequential_owners_deal_domains_round_robin():
    nonempty = np.array([True, True, False, True, True, True, True])
    a = sequential_owners(7, 3, nonempty, 300, 100)
    assert a.owner.tolist() == [0, 1, -1, 0, 1, 2, 0]
    assert a.replicated is None
    assert np.array_equal(a.tiles, screen_tiles(300, 100, 3))
    assert np.flatnonzero(a.owns(0)).tolist() == [0, 3, 6]


def test_spatial_owners_give_each_node_a_compact_block():
    # a 4x4x4 grid of unit boxes over 8 nodes: Morton runs of 8 are the 2x2x2 octants
    idx = np.stack(np.meshgrid(np.arange(4), np.arange(4), np.arange(4), indexing="ij"), -1)
    lo = idx.reshape(-1, 3).astype(float)
    a = spatial_owners(lo, lo + 1, 8, np.ones(64, bool), 320, 180)
    assert np.array_equal(a.tiles, screen_tiles(320, 180, 8))
    for node in range(8):
        cells = lo[a.owner == node]
        assert len(cells) == 8
        assert np.all(cells.max(axis=0) - cells.min(axis=0) == 1)  # one octant
        assert np.all(cells.min(axis=0) % 2 == 0)


def test_spatial_owners_balance_the_non_empty_domains():
    rng = np.random.default_rng(3)
    lo = rng.uniform(0, 10, (50, 3))
    nonempty = rng.random(50) < 0.7
    a = spatial_owners(lo, lo + 0.5, 6, nonempty, 64, 64)
    assert (a.owner[~nonempty] == -1).all()
    sizes = np.bincount(a.owner[nonempty], minlength=6)
    assert sizes.max() - sizes.min() <= 1
    assert a.replicated is None


def test_names():
    assert PRIORITIES == ("queue", "spray", "queue+act", "cost-benefit", "cost-rate",
                          "queue+resident")
    assert ASSIGNMENTS == ("sequential", "spatial", "paper", "affinity", "fit")


# -- frame statistics --------------------------------------------------------------------------
def node_stats(rng, d=5, p=3) -> FrameStats:
    s = FrameStats.zeros(d, p)
    s.sent[:] = rng.integers(0, 9, (d, d))
    np.fill_diagonal(s.sent, 0)
    s.received[:] = rng.integers(0, 20, d)
    s.loads[:] = rng.integers(0, 3, d)
    s.proc_rays[:] = rng.integers(0, 100, d)
    s.proc_s[:] = rng.uniform(0, 1, d)
    s.load_bytes[:] = rng.uniform(0, 1e6, p)
    s.load_s[:] = rng.uniform(0, 1, p)
    s.held[rng.integers(0, p), rng.integers(0, d)] = 1
    return s


def test_frame_stats_round_trip_and_sum_over_nodes():
    z = FrameStats.zeros(5, 3)
    assert z.sent.shape == (5, 5) and z.sent.dtype == np.int64
    assert z.proc_s.dtype == np.float64 and z.load_bytes.shape == (3,)
    rng = np.random.default_rng(5)
    a, b = node_stats(rng), node_stats(rng)
    arrays = a.to_arrays()
    assert set(arrays) == {"sent", "received", "loads", "proc_rays", "proc_s", "load_bytes",
                           "load_s", "held"}
    back = FrameStats.from_arrays({k: v.tolist() for k, v in arrays.items()})  # e.g. off the wire
    for k, v in back.to_arrays().items():
        assert v.dtype == arrays[k].dtype and np.array_equal(v, arrays[k])
    total = FrameStats.from_arrays({k: v + b.to_arrays()[k] for k, v in arrays.items()})
    assert np.array_equal(total.sent, a.sent + b.sent)
    assert np.array_equal(total.received, a.received + b.received)
    assert np.allclose(total.load_s, a.load_s + b.load_s)
    assert np.array_equal(total.held, a.held + b.held) and total.held.shape == (3, 5)
    with pytest.raises(ValueError):
        FrameStats.from_arrays({**arrays, "sent": np.zeros((5, 4), np.int64)})


def test_transmission_and_pair_ratios():
    s = FrameStats.zeros(3, 1)
    s.sent[:] = [[7, 2, 6], [1, 0, 0], [0, 0, 0]]  # the diagonal (7) is ignored
    s.received[:] = [16, 4, 0]
    assert np.allclose(s.transmission_ratio(), [8 / 16, 1 / 4, 0.0])
    assert np.allclose(s.pair_ratio(), [[0, 0.25, 0.75], [1.0, 0, 0], [0, 0, 0]])
    assert np.allclose(s.pair_ratio(literal=True), [[0, 2 / 16, 6 / 16], [1 / 4, 0, 0], [0, 0, 0]])


def test_speeds_fall_back_to_the_mean_of_the_known_ones():
    s = FrameStats.zeros(4, 3)
    s.proc_rays[:] = [100, 0, 300, 5]
    s.proc_s[:] = [1.0, 2.0, 1.0, 0.0]
    assert np.allclose(s.s_proc(), [100, 200, 300, 200])
    s.load_bytes[:] = [10.0, 0.0, 30.0]
    s.load_s[:] = [1.0, 0.0, 1.0]
    assert np.allclose(s.s_load(), [10, 20, 30])
    z = FrameStats.zeros(2, 2)
    assert z.s_proc().tolist() == [1.0, 1.0] and z.s_load().tolist() == [1.0, 1.0]
    s.proc_rays[:], s.proc_s[:] = [1, 1, 1, 1], [1e12, 1e12, 1e12, 1e12]
    assert np.all(s.s_proc(eps=1e-3) == 1e-3)  # floored


# -- Eq 1-4: the note's A8 ---------------------------------------------------------------------
def test_load_time_is_zero_when_resident():
    t = load_time(np.array([4.0, 6.0, 8.0]) * MB, 2 * MB, np.array([False, True, False]))
    assert t.tolist() == [2.0, 0.0, 4.0]


def test_dep_prime_is_a_normalised_distance_in_0_1():
    lo = np.array([[-1.0, -1, -1], [3, 0, 0], [0, 4, 0], [100, 100, 100]])
    hi = np.array([[1.0, 1, 1], [4, 1, 1], [1, 5, 1], [101, 101, 101]])
    nonempty = np.array([True, True, True, False])  # the empty far box doesn't normalise
    dep = dep_prime(np.zeros(3), lo, hi, nonempty)
    far = np.sqrt(1 + 25 + 1)  # farthest corner of any non-empty box: (1, 5, 1)
    assert dep[0] == 0.0  # the eye's box
    assert np.isclose(dep[1], 3 / far) and np.isclose(dep[2], 4 / far)
    assert np.all((dep >= 0) & (dep < 1))
    rng = np.random.default_rng(6)
    lo = rng.uniform(-5, 5, (200, 3))
    hi = lo + rng.uniform(0, 2, (200, 3))
    dep = dep_prime(rng.uniform(-6, 6, 3), lo, hi, rng.random(200) < 0.8)
    assert np.all((dep >= 0) & (dep < 1))


def test_potential_is_guarded():
    q = potential(np.array([100, 100, 10, 10, 0]), np.array([40, 40, 30, 0, 0]),
                  np.array([4, 2, 3, 1, 0]), np.array([1, 2, 0, 5, 0]))
    assert q.tolist() == [20.0, 60.0, 0.0, 10.0, 0.0]
    rng = np.random.default_rng(7)
    q = potential(*(rng.integers(0, 50, (4, 1000))))
    assert np.all(np.isfinite(q)) and np.all(q >= 0)


def hand_inputs(**kw) -> PriorityInputs:
    """Four local domains; 0 is active with 10 rays; R(0) = 0.5, R(0, .) = (0, .2, .8, 0)."""
    d = 5
    r_pair = np.zeros((d, d))
    r_pair[0] = [0.0, 0.2, 0.8, 0.0, 0.0]
    base = dict(
        q_cur=np.array([10.0, 4, 0, 6, 9]), active=0, q_act=10, R=np.array([0.5, 0, 0, 0, 0]),
        R_pair=r_pair, q_pre=np.array([0.0, 0, 30, 0, 0]), q_cur_recv=np.zeros(d),
        n_pre=np.array([0.0, 0, 3, 0, 0]), n_cur=np.zeros(d), s_proc=np.array([1.0, 2, 4, 1, 1]),
        domain_bytes=np.array([1.0, 4, 2, 20, 1]) * MB, s_load_n=2 * MB,
        resident=np.array([True, False, True, False, False]), dep=np.array([0.0, 0.5, 0.25, 0, 0]),
        local=np.array([True, True, True, True, False]), spray_score=np.array([0.0, 1, 5, 2, 9]))
    base.update(kw)
    return PriorityInputs(**base)


def test_priorities_on_hand_numbers():
    inp = hand_inputs()
    # act term: 10 * 0.5 * (0, .2, .8, 0) = (0, 1, 4, 0); Q_POT(2) = 30 / 3 = 10
    # Q_PRED = (-, 5, 14, 6, -); domain 0 is active, 4 is not local
    neg = -np.inf
    assert priority("queue", inp).tolist() == [neg, 4.0, 0.0, 6.0, neg]
    assert priority("spray", inp).tolist() == [neg, 1.0, 5.0, 2.0, neg]
    assert priority("queue+act", inp).tolist() == [neg, 5.0, 4.0, 6.0, neg]
    # Eq 1: d=1: 0.5 * (5/2 - 4/2) = 0.25; d=2: 0.75 * (14/4 - 0) = 2.625; d=3: 1 * (6 - 10) = -4
    assert np.allclose(priority("cost-benefit", inp), [neg, 0.25, 2.625, -4.0, neg])
    assert best(priority("cost-benefit", inp)) == 2
    assert best(priority("queue", inp)) == 3
    # cost-rate: work over max(T_LOAD, 1 ms): d=1: 0.5 * (5/2) / 2 = 0.625;
    # d=2 (resident): 0.75 * (14/4) / 1e-3 = 2625; d=3: 1 * 6 / 10 = 0.6
    assert np.allclose(priority("cost-rate", inp), [neg, 0.625, 2625.0, 0.6, neg])
    # queue+resident: resident domain 2 (0 rays queued) leads by max Q_CUR + 1 = 11
    assert priority("queue+resident", inp).tolist() == [neg, 4.0, 11.0, 6.0, neg]
    assert best(priority("queue+resident", hand_inputs(resident=np.zeros(5, bool)))) == 3
    # a domain with Q_PRED = 0 is not a candidate; without an active domain there's no act term
    inp2 = hand_inputs(active=None, q_pre=np.zeros(5), q_cur=np.array([0.0, 4, 0, 6, 9]))
    assert priority("queue", inp2).tolist() == [neg, 4.0, neg, 6.0, neg]
    with pytest.raises(ValueError):
        priority("spray", hand_inputs(spray_score=None))
    with pytest.raises(ValueError):
        priority("lru", inp)


def test_eq1_is_literal_a_negative_bracket_favours_the_far_domain():
    """Note S12.4: (1 - Dep') multiplies the bracket even when it is negative."""
    inp = hand_inputs(q_cur=np.array([0.0, 1, 1, 0, 0]), active=None, q_pre=np.zeros(5),
                      s_proc=np.ones(5), domain_bytes=np.array([0.0, 10, 10, 0, 0]) * MB,
                      resident=np.zeros(5, bool), dep=np.array([0.0, 0.1, 0.9, 0, 0]))
    p = priority("cost-benefit", inp)
    assert np.allclose(p[1:3], [0.9 * (1 - 5), 0.1 * (1 - 5)])
    assert best(p) == 2  # the far one


def test_cost_rate_ranks_work_per_load_second_and_keeps_near_ahead():
    """The ratio form: a cached domain ranks by its work alone (ahead of one that must be
    loaded unless that promises T_LOAD / 1 ms times more); among domains to load, more work
    per second of loading wins, where Eq. 1 as written prefers the cheap load with less work;
    nearer wins at equal work and cost, where Eq. 1's negative bracket prefers the far one."""
    inp = hand_inputs(q_cur=np.array([0.0, 100, 2, 10, 0]), active=None, q_pre=np.zeros(5),
                      s_proc=np.full(5, 1000.0), domain_bytes=np.array([0.0, 20, .5, 4, 0]) * MB,
                      s_load_n=100 * MB, resident=np.zeros(5, bool), dep=np.zeros(5))
    # work = (0.1, 0.002, 0.01) s; T_LOAD = (0.2, 0.005, 0.04) s
    assert np.allclose(priority("cost-benefit", inp)[1:4], [-0.1, -0.003, -0.03])
    assert best(priority("cost-benefit", inp)) == 2  # the cheap load with 2 rays
    rate = priority("cost-rate", inp)
    assert np.allclose(rate[1:4], [0.5, 0.4, 0.25]) and best(rate) == 1
    cached = hand_inputs(**{**inp.__dict__, "resident": np.array([False, True, False, False,
                                                                   False])})
    assert best(priority("cost-rate", cached)) == 1  # 0.1 s of work / 1 ms
    far = hand_inputs(**{**inp.__dict__, "q_cur": np.array([0.0, 0, 10, 10, 0]),
                         "domain_bytes": np.array([0.0, 0, 4, 4, 0]) * MB,
                         "dep": np.array([0.0, 0, 0.9, 0.1, 0])})
    assert best(priority("cost-rate", far)) == 3  # near
    assert best(priority("cost-benefit", far)) == 2  # far (note S12.4)
    assert np.all(priority("cost-rate", far)[2:4] > 0)


def test_frame_0_priorities_need_no_statistics():
    assert bootstrap_priority("cost-benefit") == "queue"  # the paper's bootstrap frame
    assert bootstrap_priority("queue+act") == "queue"
    assert bootstrap_priority("cost-rate") == "queue+resident"  # keeps its cache rule
    for kind in ("queue", "spray", "queue+resident"):
        assert bootstrap_priority(kind) == kind
    assert {bootstrap_priority(k) for k in PRIORITIES} <= set(PRIORITIES)


def test_resident_after_load_drops_the_victim_of_the_active_domains_load():
    p = np.array([5.0, 1.0, 9.0, 3.0])
    # one slot: loading 2 evicts 0, which must not count as cached for d*
    assert resident_after_load({0}, 1, 2, p) == {2}
    assert resident_after_load({0, 1, 3}, 3, 2, p) == {0, 2, 3}  # the lowest (1) goes
    assert resident_after_load({0, 1}, 3, 2, p) == {0, 1, 2}  # room: nothing goes
    assert resident_after_load({0, 2}, 2, 2, p) == {0, 2}  # already cached


def test_best_and_victim():
    neg = -np.inf
    assert best(np.array([neg, 3.0, 3.0, 1.0])) == 1  # ties -> lower id
    assert best(np.array([neg, neg])) is None
    assert best(np.array([])) is None
    p = np.array([5.0, neg, 2.0, 2.0, 7.0, neg])
    assert victim(p, [0, 2, 3, 4], set()) == 2  # lowest, ties -> lower id
    assert victim(p, [0, 2, 3, 4], {2}) == 3
    assert victim(p, [0, 1, 4, 5], {0}) == 1  # non-candidates go first, lower id
    assert victim(p, [4], {4}) is None


def test_a_node_keeps_the_rays_of_the_replicated_and_of_empty_domains():
    from vastray.schedule.temporal import Assignment

    a = Assignment(owner=np.array([0, 1, -1, 1]), tiles=np.zeros((2, 4), np.int64),
                   replicated=3)
    assert a.routes_from(0).tolist() == [0, 1, 0, 0]
    assert a.routes_from(1).tolist() == [0, 1, 1, 1]
    assert a.owner.tolist() == [0, 1, -1, 1]  # the assignment itself is left as it was
