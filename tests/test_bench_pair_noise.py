"""``bench/pair_noise.py``: how much of the validation's worst row the machine's noise makes
(a pair's spread about its point's mean, and the chance an unbiased simulator stays within
the goal)."""

from __future__ import annotations

import numpy as np
import pytest
from bench_modules import load_bench

noise = load_bench("pair_noise")


def test_a_points_bias_is_not_noise():
    """Two points, each pair 0.1 from its point's mean, the means far apart: the spread is
    0.1 (sqrt of 4 * 0.01 / (4 - 2)), not the spread of all four errors."""
    sd = noise.pooled_sd([[-0.4, -0.2], [0.3, 0.5]])
    assert sd == pytest.approx(np.sqrt(4 * 0.01 / 2))
    assert sd < np.std([-0.4, -0.2, 0.3, 0.5])


def test_points_of_one_pair_give_no_spread():
    assert noise.pooled_sd([[0.1], [0.3]]) is None
    assert noise.pooled_sd([[0.1], [0.2, 0.4]]) == pytest.approx(np.sqrt(0.02))


def test_no_noise_always_within_the_goal():
    assert noise.chance_within(0.2, 0.0, [2] * 14) == 1.0


def test_more_pairs_or_fewer_points_raise_the_chance():
    two = noise.chance_within(0.2, 0.12, [2] * 14)
    four = noise.chance_within(0.2, 0.12, [4] * 14)
    fewer = noise.chance_within(0.2, 0.12, [2] * 4)
    assert 0.5 < two < four < 1.0
    assert fewer > two


def test_one_point_of_one_pair_matches_the_normal_law():
    """A single normal draw within +-0.2 at sd 0.1: about 95.45 %."""
    chance = noise.chance_within(0.2, 0.1, [1], draws=200_000)
    assert chance == pytest.approx(0.9545, abs=0.005)


def test_the_same_inputs_give_the_same_figure():
    assert noise.chance_within(0.2, 0.12, [2, 3]) == noise.chance_within(0.2, 0.12, [2, 3])
