"""Virtual portals (notes §5, acceptance A10, A11's merge): binning of exit points and
directions, the 8 equal-solid-angle bins, record/predict, MAX merge, and the tree "max"; the
prediction accuracy (ACC and Simple/total, notes §9) and the crossing log of instrumented
frames."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.schedule.portals import (
    ANGLES,
    FACES,
    Accuracy,
    CrossingLog,
    Portals,
    luminance,
    prediction_accuracy,
)
from vastray.transport.tree import COMBINE

from scenes import allreduce_over_sockets

LO = np.array([[0.0, 0.0, 0.0], [1.0, -2.0, 3.0], [-5.0, -5.0, -5.0]])
HI = np.array([[1.0, 1.0, 1.0], [3.0, 2.0, 3.5], [5.0, 5.0, 5.0]])
NORMALS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], float)


def face_centre(box: int, face: int) -> np.ndarray:
    centre = (LO[box] + HI[box]) / 2
    axis = face // 2
    centre[axis] = HI[box, axis] if face % 2 else LO[box, axis]
    return centre


def uniform_hemisphere(rng, n: int, normal: np.ndarray) -> np.ndarray:
    """Directions uniform over the hemisphere around ``normal`` (uniform sphere, flipped)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.where((d @ normal)[:, None] < 0, -d, d)


def exits(rng, n: int, boxes=(0, 1, 2)):
    """Rays from random interior points: (domain, exit point, direction, true face)."""
    dom = rng.choice(boxes, n)
    lo, hi = LO[dom], HI[dom]
    o = lo + rng.random((n, 3)) * (hi - lo)
    d = rng.normal(size=(n, 3))
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (hi - o) / d, (lo - o) / d)
    axis = np.argmin(t, axis=1)
    rows = np.arange(n)
    face = 2 * axis + (d[rows, axis] > 0)
    return dom, o + t[rows, axis][:, None] * d, d, face


# --- A10: binning -----------------------------------------------------------------------------


@pytest.mark.parametrize("face", range(6))
@pytest.mark.parametrize("box", range(3))
def test_face_centre_along_the_normal_is_cell_16_16_upper_cos_bin(box, face):
    portals = Portals(len(LO))
    cell = portals.cells([box], face_centre(box, face)[None], NORMALS[face][None] * 2.5, LO, HI)
    d, f, i, j, angle = (int(x[0]) for x in portals.unravel(cell))
    assert (d, f, i, j) == (box, face, 16, 16)
    assert angle // 4 == 1  # cos(theta) = 1: the upper bin
    assert cell.dtype == np.int64 and cell.shape == (1,)


def test_exit_face_is_right_for_all_six_faces():
    rng = np.random.default_rng(1)
    portals = Portals(len(LO))
    dom, points, d, face = exits(rng, 60_000)
    got_dom, got_face, i, j, angle = portals.unravel(portals.cells(dom, points, d, LO, HI))
    np.testing.assert_array_equal(got_face, face)
    np.testing.assert_array_equal(got_dom, dom)
    assert set(np.unique(face)) == set(range(6))
    assert i.min() == 0 and i.max() == 31 and j.min() == 0 and j.max() == 31
    assert set(np.unique(angle)) == set(range(ANGLES))


def test_spatial_cells_are_the_floor_of_32u():
    portals = Portals(1)
    lo, hi = LO[:1], HI[:1]
    rng = np.random.default_rng(2)
    uv = rng.random((1000, 2))
    uv[:4] = [[0, 0], [1, 1], [0.5, 1 / 32], [31.5 / 32, 0.999999]]  # corners, edges: clamped
    points = np.column_stack([np.ones(len(uv)), uv])  # the +x face: u = y, v = z
    d = np.tile([1.0, 0.2, -0.3], (len(uv), 1))
    _, face, i, j, _ = portals.unravel(portals.cells(np.zeros(len(uv), int), points, d, lo, hi))
    assert (face == FACES.index("+x")).all()
    np.testing.assert_array_equal(i, np.clip(np.floor(32 * uv[:, 0]), 0, 31))
    np.testing.assert_array_equal(j, np.clip(np.floor(32 * uv[:, 1]), 0, 31))


@pytest.mark.parametrize("face", range(6))
def test_uniform_hemisphere_fills_the_8_angle_bins_equally(face):
    rng = np.random.default_rng(10 + face)
    n = 80_000
    portals = Portals(len(LO))
    d = uniform_hemisphere(rng, n, NORMALS[face])
    points = np.tile(face_centre(1, face), (n, 1))
    angle = portals.unravel(portals.cells(np.ones(n, int), points, d, LO, HI))[4]
    counts = np.bincount(angle, minlength=ANGLES)
    sigma = np.sqrt(n * (1 / 8) * (7 / 8))
    assert np.all(np.abs(counts - n / 8) < 4 * sigma), counts


def test_angle_bins_split_cos_at_half_and_phi_by_quadrant():
    portals = Portals(1)
    lo, hi = LO[:1], HI[:1]
    point = face_centre(0, FACES.index("+z"))[None]  # +z face: t_u = x, t_v = y
    s = np.sqrt(1 - 0.4 ** 2)
    cases = {  # direction -> (cos bin, phi quadrant)
        (0.3, 0.3, 0.9): (1, 0), (-0.3, 0.3, 0.9): (1, 1), (-0.3, -0.3, 0.9): (1, 2),
        (0.3, -0.3, 0.9): (1, 3), (s, 0.0, 0.4): (0, 0), (0.0, s, 0.4): (0, 1),
        (-s, -1e-9, 0.4): (0, 2), (0.0, -s, 0.4): (0, 3),
    }
    for direction, (cos_bin, quadrant) in cases.items():
        angle = int(portals.unravel(portals.cells([0], point, [direction], lo, hi))[4][0])
        assert (angle // 4, angle % 4) == (cos_bin, quadrant), direction


def test_nbytes_is_values_plus_the_mask():
    for d in (1, 3, 128):
        portals = Portals(d)
        assert portals.values.nbytes == d * 6 * 32 * 32 * 8 * 4  # A10: D x 196,608 B
        assert portals.recorded.nbytes == d * 6 * 32 * 32 * 8     # the bool mask, 1 B a cell
        assert portals.nbytes == d * 6 * 32 * 32 * 8 * 5
        assert portals.to_arrays()["portal_recorded"].nbytes == d * 6 * 32 * 32  # 1 bit sent
    assert Portals(2, resolution=8).shape == (2, 6, 8, 8, 8)


# --- record / predict / merge -----------------------------------------------------------------


def test_record_then_predict_round_trip_keeps_the_maximum():
    rng = np.random.default_rng(3)
    portals = Portals(len(LO))
    dom, points, d, _ = exits(rng, 20_000)
    cells = portals.cells(dom, points, d, LO, HI)
    values = rng.random(len(cells)).astype(np.float32) * 5
    portals.record(cells, values)
    expected = np.full(portals.values.size, -np.inf, np.float32)
    np.maximum.at(expected, cells, values)
    np.testing.assert_array_equal(portals.predict(cells), expected[cells])
    assert portals.predict(cells).dtype == np.float32
    assert portals.recorded.sum() == len(np.unique(cells))


def test_unrecorded_cells_predict_inf():
    portals = Portals(2)
    assert np.isinf(portals.predict(np.arange(0, portals.values.size, 997))).all()
    portals.record([5, 5, 9], [0.0, 0.0, 0.25])  # a recorded zero (a miss) is not unrecorded
    np.testing.assert_array_equal(portals.predict([5, 9, 6]), [0.0, 0.25, np.inf])
    portals.record([7], [np.nan])
    assert portals.predict([7])[0] == np.inf


def test_refresh_keeps_the_maximum_and_forgets_cells_not_recorded_for_memory_frames():
    kept = Portals(1, 2)
    kept.record([1, 2], [0.4, 0.9])
    frame = Portals(1, 2)
    frame.record([2, 3], [0.1, 0.3])  # cell 2 again (lower), cell 3 new
    kept.refresh(frame, memory=2)
    np.testing.assert_array_equal(kept.predict([1, 2, 3, 4]),
                                  np.float32([0.4, 0.9, 0.3, np.inf]))
    assert kept.age.reshape(-1)[[1, 2, 3]].tolist() == [1, 0, 0]
    kept.refresh(Portals(1, 2), memory=2)  # a frame that recorded nothing
    np.testing.assert_array_equal(kept.predict([1, 2, 3]),
                                  np.float32([np.inf, 0.9, 0.3]))  # 1: 2 frames
    assert kept.values.reshape(-1)[1] == 0 and not kept.recorded.reshape(-1)[1]
    again = Portals(1, 2)
    again.record([1], [0.05])  # a forgotten cell is recorded afresh, not maxed with its past
    kept.refresh(again, memory=2)
    np.testing.assert_array_equal(kept.predict([1]), [np.float32(0.05)])
    assert kept.copy().age.tolist() == kept.age.tolist()
    with pytest.raises(ValueError, match="at least 1 frame"):
        kept.refresh(again, memory=0)
    with pytest.raises(ValueError, match="shape"):
        kept.refresh(Portals(2, 2), memory=2)


def random_portals(rng, n_domains=2, resolution=4, fill=0.3) -> Portals:
    p = Portals(n_domains, resolution)
    cells = rng.choice(p.values.size, int(fill * p.values.size), replace=False)
    p.record(cells, rng.random(len(cells)).astype(np.float32))
    return p


def test_max_merge_is_commutative_associative_and_idempotent():
    rng = np.random.default_rng(4)
    a, b, c = (random_portals(rng) for _ in range(3))
    assert a.copy().merge(b) == b.copy().merge(a)
    assert a.copy().merge(b).merge(c) == a.copy().merge(b.copy().merge(c))
    assert a.copy().merge(a) == a
    merged = a.copy().merge(b)
    np.testing.assert_array_equal(merged.values, np.maximum(a.values, b.values))
    np.testing.assert_array_equal(merged.recorded, a.recorded | b.recorded)
    with pytest.raises(ValueError, match="shape"):
        a.merge(Portals(3, 4))


def test_recording_split_over_nodes_equals_one_recording():
    """A5's portal half: any split of the records over nodes, merged, equals one process."""
    rng = np.random.default_rng(5)
    whole = Portals(len(LO), 8)
    dom, points, d, _ = exits(rng, 5000)
    cells = whole.cells(dom, points, d, LO, HI)
    values = rng.random(len(cells)).astype(np.float32)
    whole.record(cells, values)
    node = rng.integers(0, 3, len(cells))
    parts = []
    for k in range(3):
        p = Portals(len(LO), 8)
        p.record(cells[node == k], values[node == k])
        parts.append(p)
    assert parts[2].copy().merge(parts[0]).merge(parts[1]) == whole


def test_arrays_round_trip_through_the_reduce_combiners():
    rng = np.random.default_rng(6)
    a, b = random_portals(rng, 3, 5), random_portals(rng, 3, 5)
    assert Portals.from_arrays(a.to_arrays()) == a
    x, y = a.to_arrays(), b.to_arrays()
    combined = {k: COMBINE[op](x[k], y[k]) for k, op in Portals.REDUCE.items()}
    assert Portals.from_arrays(combined) == a.copy().merge(b)
    with pytest.raises(ValueError, match="float32"):
        Portals.from_arrays({**x, "portal_values": x["portal_values"].astype(np.float64)})


def test_tree_max_combiner():
    a = np.array([1.0, -2.0, np.inf, 0.0], np.float32)
    b = np.array([0.5, -1.0, 3.0, 0.0], np.float32)
    np.testing.assert_array_equal(COMBINE["max"](a, b), [1.0, -1.0, np.inf, 0.0])
    assert set(COMBINE) >= {"max", "min", "or", "sum"}


@pytest.mark.parametrize("size", [1, 2, 3, 5])
async def test_portals_allreduce_over_real_sockets(size):
    """The tree all-reduce of P nodes (ZeroMQ, one event loop) with "max" and "or" gives every
    node the merge of all nodes' portals."""
    rng = np.random.default_rng(size)
    portals = [random_portals(rng, 2, 4) for _ in range(size)]
    results, _ = await allreduce_over_sockets([p.to_arrays() for p in portals], Portals.REDUCE)
    expected = portals[0].copy()
    for p in portals[1:]:
        expected.merge(p)
    for result in results:
        assert Portals.from_arrays(result) == expected


def test_luminance():
    rgb = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [0.5, 0.25, 2.0]], np.float32)
    y = luminance(rgb)
    assert y.dtype == np.float32 and y.shape == (5,)
    np.testing.assert_allclose(y, [0.2126, 0.7152, 0.0722, 1.0,
                                   0.2126 * 0.5 + 0.7152 * 0.25 + 0.0722 * 2.0], rtol=1e-6)
    assert luminance(np.zeros((0, 3))).shape == (0,)
    with pytest.raises(ValueError):
        luminance(np.ones(3))


# --- prediction accuracy (ACC, Simple/total) and the crossing log ------------------------------


def test_prediction_accuracy_on_hand_numbers():
    # tau = 0.5: predicted classes L L H H H L; actual L H L H L L (0.5 itself is low)
    predicted = [0.1, 0.5, 0.9, np.inf, 2.0, 0.0]
    actual = [0.2, 0.7, 0.5, 3.0, 0.0, 0.5]
    acc = prediction_accuracy(predicted, actual, 0.5)
    assert acc == Accuracy(crossings=6, agree=3, predicted_low=3, false_low=1, false_high=2,
                           unrecorded=1)
    assert acc.acc == pytest.approx(0.5) and acc.simplified_share == pytest.approx(0.5)
    # a lower threshold: predicted L H H H H L; actual L H H H L H
    acc = prediction_accuracy(predicted, actual, 0.25)
    assert (acc.agree, acc.predicted_low, acc.false_low, acc.false_high) == (4, 2, 1, 1)
    assert acc.acc == pytest.approx(4 / 6) and acc.simplified_share == pytest.approx(1 / 3)


def test_prediction_accuracy_edges():
    empty = prediction_accuracy([], [], 0.5)
    assert empty.crossings == 0 and empty.acc is None and empty.simplified_share is None
    perfect = prediction_accuracy([0.1, 7.0], [0.4, 0.6], 0.5)
    assert perfect.acc == 1.0 and perfect.false_low == perfect.false_high == 0
    nan = prediction_accuracy([np.nan, 0.1], [0.1, np.nan], 0.5)  # NaN is never low
    assert (nan.false_high, nan.false_low, nan.unrecorded) == (1, 1, 0)
    unseen = prediction_accuracy([np.inf, np.inf, 3.0], [0.0, 9.0, 0.0], 0.5)
    assert (unseen.unrecorded, unseen.false_high, unseen.agree) == (2, 2, 1)
    with pytest.raises(ValueError, match="2 predictions but 1"):
        prediction_accuracy([0.1, 0.2], [0.3], 0.5)


def test_accuracy_counters_round_trip_and_add():
    rng = np.random.default_rng(9)
    a = prediction_accuracy(rng.random(50), rng.random(50), 0.5)
    b = prediction_accuracy(rng.random(30), rng.random(30), 0.5)
    counters = a.counters("acc_")
    assert set(counters) == {"acc_crossings", "acc_agree", "acc_predicted_low",
                             "acc_false_low", "acc_false_high", "acc_unrecorded"}
    assert all(type(v) is int for v in counters.values())  # JSON and frame sums
    assert Accuracy.from_counters(counters, "acc_") == a
    assert Accuracy.from_counters(counters, "replay_") is None
    both = a + b
    assert both.crossings == 80 and both.agree == a.agree + b.agree
    rows = [(rng.random(50), rng.random(50)), (rng.random(30), rng.random(30))]
    joined = prediction_accuracy(np.concatenate([p for p, _ in rows]),
                                 np.concatenate([q for _, q in rows]), 0.5)
    assert joined == prediction_accuracy(*rows[0], 0.5) + prediction_accuracy(*rows[1], 0.5)


def test_a12_portal_recorded_from_the_crossings_never_predicts_them_low():
    # The replay property on its own: whatever the crossings, a portal recorded from them
    # predicts each at least its own value, so no threshold gives a false low.
    rng = np.random.default_rng(10)
    portals = Portals(len(LO), resolution=4)  # coarse: many crossings share a cell
    dom, points, d, _ = exits(rng, 5_000)
    cells = portals.cells(dom, points, d, LO, HI)
    actual = (rng.exponential(0.5, len(cells)) * (rng.random(len(cells)) < 0.7)).astype(
        np.float32)
    portals.record(cells, actual)
    for tau in (0.0, 0.1, 0.5, 1.0, 2.0):
        acc = prediction_accuracy(portals.predict(cells), actual, tau)
        assert acc.false_low == 0
        assert acc.agree == acc.crossings - acc.false_high
    assert prediction_accuracy(portals.predict(cells), actual, 0.5).false_high > 0


def test_crossing_log_keeps_each_paths_cell_and_largest_value():
    log = CrossingLog(6)
    log.crossed([4, 1, 2], [30, 10, 20])
    log.lit([1, 1, 4, 5], [0.25, 0.75, np.nan, 9.0])  # path 5 crossed nowhere: not listed
    cells, values = log.crossings()
    np.testing.assert_array_equal(cells, [10, 20, 30])
    np.testing.assert_array_equal(values, [0.75, 0.0, np.inf])  # 2: dark; 4: NaN -> +inf
    assert cells.dtype == np.int64 and values.dtype == np.float32


def test_crossing_logs_of_nodes_combine_by_the_tree_combiners():
    # A crossing is logged on the node where its hit became final; its light on the nodes
    # where its shadow rays came through: the MAX of the logs is one process's log.
    whole, parts = CrossingLog(5), [CrossingLog(5), CrossingLog(5)]
    for log, paths, cells in ((whole, [0, 3], [7, 8]), (parts[0], [0], [7]),
                              (parts[1], [3], [8])):
        log.crossed(paths, cells)
    for log, paths, values in ((whole, [0, 3, 0], [0.2, 0.6, 0.4]), (parts[1], [0], [0.2]),
                               (parts[0], [3, 0], [0.6, 0.4])):
        log.lit(paths, values)
    a, b = (p.to_arrays() for p in parts)
    combined = {k: COMBINE[op](a[k], b[k]) for k, op in CrossingLog.REDUCE.items()}
    merged = CrossingLog.from_arrays(combined)
    for got, want in zip(merged.crossings(), whole.crossings(), strict=True):
        np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError):
        CrossingLog.from_arrays({"crossing_cell": np.zeros(3, np.int64),
                                 "crossing_value": np.zeros(2, np.float32)})


def test_portal_size_is_checked_before_a_render_with_what_fits():
    from vastray.schedule.portals import MAX_PORTAL_BYTES, check_portal_size, portal_bytes

    assert portal_bytes(64, 128) == 64 * 6 * 128 * 128 * 8 * 5  # float32 value + bool flag
    check_portal_size(64, 128)  # 240 MiB: fits
    with pytest.raises(ValueError, match="--portal-resolution 47 or less"):
        check_portal_size(1000, 64)  # 938 MiB for 1,000 domains
    assert portal_bytes(1000, 47) <= MAX_PORTAL_BYTES < portal_bytes(1000, 48)


def test_portals_are_recorded_every_interval_and_whenever_none_exist():
    from vastray.schedule.portals import records_portals

    assert [records_portals(f, 3, True) for f in range(7)] == [True, False, False, True,
                                                                False, False, True]
    assert records_portals(5, 3, have_portals=False)  # a resumed job: nothing to predict with
