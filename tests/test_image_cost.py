"""The sort-first bands' cost estimate (``schedule/image_cost.py``): a sweep's weights
before each path, and pixels over the data weighing more than those over the background."""

from __future__ import annotations

import numpy as np

from vastray.render.camera import Camera
from vastray.schedule.geometry import DomainGeometry
from vastray.schedule.image_cost import PER_DOMAIN, SweepWeights, pixel_weights
from vastray.schedule.ownership import sort_first_tile_paths


def test_sweep_weights_are_the_sum_over_every_path_before():
    rng = np.random.default_rng(3)
    pixel = rng.integers(1, 20, 12)
    per_pixel = np.array([1, 1, 2, 4])
    # the sweep path by path: pass after pass, pixel-major within a pass
    path_weight = np.concatenate([np.repeat(pixel, spp) for spp in per_pixel])
    brute = np.concatenate([[0], np.cumsum(path_weight)])
    weights = SweepWeights(pixel, per_pixel)
    ids = np.arange(len(path_weight) + 1)
    assert np.array_equal(weights(ids), brute)


def test_pixels_whose_ray_meets_the_data_weigh_more():
    # two boxes at the right of a camera looking down -z: the left half sees nothing
    lo = np.array([[0.5, -1.0, -3.0], [0.5, -1.0, -5.0]])
    hi = np.array([[1.5, 1.0, -2.0], [1.5, 1.0, -4.0]])
    geometry = DomainGeometry(lo, hi, np.ones(2, bool), 10.0)
    camera = Camera(np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]), 60.0,
                    80, 40)
    weight = pixel_weights(camera, geometry, 80, 40).reshape(40, 80)
    assert weight.dtype == np.int64 and (weight >= 1).all()
    assert (weight[:, :30] == 1).all()  # rays that miss both boxes: the ray alone
    assert weight[20, 50] == 1 + 2 * PER_DOMAIN  # through both boxes
    # cut by these weights, the node on the background takes more of the image
    sweep = SweepWeights(weight.ravel(), np.array([4]))
    left, right = (sum(len(t) for t in sort_first_tile_paths(80 * 40 * 4, 65536, rank, 2,
                                                                  sweep)) for rank in (0, 1))
    assert left + right == 80 * 40 * 4 and left != right
