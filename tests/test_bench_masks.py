"""``bench/masks.py``'s finer masks and its oracle (the ceiling of any culling), on a small
store: both keep the image bit for bit, the oracle keeps a pair only where its ray hits a
triangle of the domain and queues the fewest rays (the bench itself renders for 20 s)."""

from __future__ import annotations

import numpy as np
import pytest
from bench_modules import load_bench

from vastray.render.integrators import RenderSettings
from vastray.scene.embree.scenes import Scene
from vastray.scene.generate import generate
from vastray.scene.store import Store

masks = load_bench("masks")
SETTINGS = RenderSettings(width=24, height=18, spp=2, integrator="pt", bounces=2,
                          shadow_samples=1, seed=3)


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Store:
    path = tmp_path_factory.mktemp("masks") / "rm"
    generate("rm", path, 40, grid=(3, 3, 2), seed=0)
    return Store(path)


def test_the_oracle_keeps_exactly_the_pairs_whose_ray_hits_the_domain(store):
    rng = np.random.default_rng(5)
    lo, hi = store.bounds
    n = 4000
    origins = (lo + (hi - lo) * rng.random((n, 3))).astype(np.float32)
    directions = rng.normal(size=(n, 3)).astype(np.float32)
    limit = np.full(n, np.float32(np.linalg.norm(hi - lo) / 3))
    oracle = masks.ExactCulling(store)
    try:
        ray = np.repeat(np.arange(n), len(store.domains))
        domain = np.tile(np.arange(len(store.domains)), n)
        kept = oracle.crosses(origins, directions, ray, domain, limit, 1e-6)
        hits = np.zeros(len(ray), bool)
        for d in range(len(store.domains)):
            arrays = store.load_domain(d)
            if not len(arrays.indices):
                continue
            scene = Scene(np.asarray(arrays.vertices), np.asarray(arrays.indices))
            rows = np.nonzero(domain == d)[0]
            hit = scene.intersect(origins[ray[rows]], directions[ray[rows]], limit[ray[rows]])
            hits[rows] = hit["primID"] >= 0
            scene.close()
    finally:
        oracle.close()
    assert hits.any() and not hits.all()  # the check can fail either way
    assert np.array_equal(kept, hits)


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_finer_masks_and_the_oracle_keep_the_image_and_queue_fewer_pairs(store, scheduler):
    cache = max(1, len(store.domains) // 4)
    plain = masks.run(store, SETTINGS, scheduler, cache, True)
    finer = masks.run(store, SETTINGS, scheduler, cache, True, masks.finer(store, 32))
    oracle_culling = masks.ExactCulling(store)
    try:
        exact = masks.run(store, SETTINGS, scheduler, cache, True, oracle_culling)
    finally:
        oracle_culling.close()
        store._occupancy = None
    for got in (finer, exact):
        assert np.array_equal(got["image"], plain["image"])
    assert exact["pairs"] < finer["pairs"] <= plain["pairs"]
