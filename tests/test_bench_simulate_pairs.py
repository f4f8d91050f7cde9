"""``bench/simulate.py``'s rule for how many (real run, simulation) pairs a validation point
takes (``enough_pairs``): never one pair in ``--quick``, a third where two disagree, and the
rule never looks at how large an error is, only at the pairs' spread."""

from __future__ import annotations

import math

import pytest
from bench_modules import load_bench

bench = load_bench("simulate")
QUICK = bench.QUICK_BUDGET_S


def enough(reals, sims, rounds=3, budget=QUICK, others=None):
    return bench.enough_pairs(reals, sims, others or [0.0] * len(reals), rounds, budget)


def test_quick_never_stops_on_one_pair_even_past_its_seconds():
    assert not enough([4.0], [4.0])
    assert enough([4.0, 4.1], [4.0, 4.0])


def test_a_third_pair_where_two_disagree():
    assert not enough([2.0, 2.0], [2.0, 2.6])  # errors 0 and +30 %
    assert enough([2.0, 2.0, 2.0], [2.0, 2.6, 2.1])  # rounds reached


@pytest.mark.parametrize("error", [-0.5, -0.2, 0.0, 0.3, 0.9])
def test_two_pairs_that_agree_stop_whatever_their_error(error):
    sims = [2.0 * (1 + error), 2.0 * (1 + error + 0.05)]
    assert enough([2.0, 2.0], sims)


def test_short_runs_take_pairs_until_their_seconds_add_up():
    short = QUICK / 3
    assert not enough([short, short], [short, short])
    assert enough([short] * 3, [short] * 3)  # the rounds asked for


def test_others_wanting_a_core_take_every_pair():
    assert not enough([2.0, 2.0], [2.0, 2.0], others=[0.0, 0.6])


def test_the_full_bench_takes_every_pair_asked_for():
    assert not enough([2.0, 2.0], [2.0, 2.0], budget=math.inf)
    assert enough([2.0, 2.0, 2.0], [2.0, 2.0, 2.0], budget=math.inf)
    assert enough([2.0], [9.0], rounds=1, budget=math.inf)  # the heavy rows' one pair
    assert enough([2.0], [9.0], rounds=1)


def test_quick_puts_every_scheduler_on_2_and_on_8_nodes_once():
    schedulers = range(len(bench.SIM_SCHEDULERS))
    first = [bench.quick_node_counts(0, s) for s in schedulers]
    second = [bench.quick_node_counts(1, s) for s in schedulers]
    assert all(len(n) == 1 for n in first + second)
    assert {a + b for a, b in zip(first, second, strict=True)} == {(2, 8), (8, 2)}
    assert {n for (n,) in first} == {2, 8}  # both counts on each case


class FakeStore:
    class path:
        name = "store"


class RecordedPoint(bench.PointPairs):
    """A point whose pairs are given (real seconds, simulated seconds) rather than run: the
    sweeps' order is what is tested, not the renders."""

    def __init__(self, name, pairs, taken):
        self.name, self.pairs, self.taken = name, list(pairs), taken
        self.store, self.nodes = FakeStore, 2
        self.reals, self.sims, self.others, self.charged = [], [], [], []

    def take(self, costs, charge_others):
        real, sim = self.pairs.pop(0)
        self.reals.append(real)
        self.sims.append(sim)
        self.others.append(0.0)
        self.charged.append(costs)
        self.taken.append(self.name)


def test_out_of_sample_pairs_come_in_sweeps_a_third_only_where_needed():
    taken = []
    agree = [(2.0, 2.0), (2.0, 2.1), (2.0, 2.0)]
    disagree = [(2.0, 2.0), (2.0, 2.8), (2.0, 2.1)]
    points = [("case", "image", RecordedPoint("a", agree, taken)),
              ("case", "domain", RecordedPoint("b", disagree, taken)),
              ("case", "async", RecordedPoint("c", agree, taken))]
    bench._take_in_sweeps(points, bench.CostModel(), 3, None, QUICK)
    # every point's first pair, then every point's second: a slow minute falls on one pair
    # of several points, not on both of one; the median of b's three sets its outlier aside
    assert taken == ["a", "b", "c", "a", "b", "c", "b"]
    errors = bench.pair_errors(points[1][2].reals, points[1][2].sims)
    assert sorted(errors)[1] == pytest.approx(0.05)  # the row's error: +40 % set aside


def test_third_pairs_go_to_the_widest_spread_first_and_stop_when_the_time_is_spent():
    def points(taken):
        narrow = [(2.0, 2.0), (2.0, 2.3), (2.0, 2.1)]   # +0 and +15 %
        wide = [(2.0, 2.0), (2.0, 3.0), (2.0, 2.1)]     # +0 and +50 %
        agree = [(2.0, 2.0), (2.0, 2.1), (2.0, 2.0)]
        return [("case", "image", RecordedPoint("narrow", narrow, taken)),
                ("case", "domain", RecordedPoint("agree", agree, taken)),
                ("case", "async", RecordedPoint("wide", wide, taken))]

    taken = []
    bench._take_in_sweeps(points(taken), bench.CostModel(), 3, None, QUICK)
    assert taken[6:] == ["wide", "narrow"]
    taken = []
    spent = points(taken)
    bench._take_in_sweeps(spent, bench.CostModel(), 3, None, QUICK, seconds=0.0)
    assert taken == ["narrow", "agree", "wide"] * 2  # never fewer than two pairs a point
    assert all(len(p.reals) == bench.QUICK_MIN_PAIRS for _, _, p in spent)
