"""Out-of-core caches build their domains with ``RTC_BUILD_QUALITY_LOW`` (issues 39, 40): a
cheaper build for loads paid again at every reload, adopted because the hits are those of
Embree's default build bit for bit (closest hit, distance, barycentrics, normal, occlusion)."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.scene.bvh import DomainBVH
from vastray.scene.cache import DomainCache
from vastray.scene.embree.library import RTC_BUILD_QUALITY_LOW, binding

from scenes import bumpy_scene, terrain_scene, write_store

pytestmark = pytest.mark.skipif(binding() is None, reason="the compiled Embree binding is "
                                                          "unavailable (embreex fallback)")


def rays(arrays, n: int, seed: int):
    """Rays from around the mesh towards its vertices (many hit, many through shared edges
    and vertices, where a tie between triangles is decided) and random ones."""
    rng = np.random.default_rng(seed)
    v = arrays.vertices.astype(np.float64)
    centre, extent = v.mean(axis=0), v.max(axis=0) - v.min(axis=0)
    origins = centre + extent * (rng.random((n, 3)) - 0.5) * 3.0
    targets = v[rng.integers(0, len(v), n)]
    targets[n // 2:] = centre + extent * (rng.random((n - n // 2, 3)) - 0.5)
    directions = targets - origins
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    return origins.astype(np.float32), directions.astype(np.float32)


@pytest.mark.parametrize("mesh", [bumpy_scene, terrain_scene])
def test_low_quality_builds_give_the_same_hits_bit_for_bit(mesh):
    arrays = mesh()
    medium = DomainBVH(0, arrays)
    low = DomainBVH(0, arrays, build_quality=RTC_BUILD_QUALITY_LOW)
    origins, directions = rays(arrays, 50_000, seed=1)
    far = np.full(len(origins), np.inf, np.float32)
    a, b = medium.intersect(origins, directions, far), low.intersect(origins, directions, far)
    assert (a["primID"] >= 0).mean() > 0.5  # the comparison is about hits
    for key in ("primID", "tfar", "u", "v", "Ng"):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    finite = far.copy()
    finite[:] = np.where(a["primID"] >= 0, a["tfar"], 10.0)  # ends on the hit: a tie decides
    np.testing.assert_array_equal(medium.occluded(origins, directions, finite),
                                  low.occluded(origins, directions, finite))


def test_only_a_cache_smaller_than_the_store_builds_fast(tmp_path):
    store = write_store(tmp_path / "kd8", bumpy_scene(), kd=8)
    assert DomainCache(store, 2).build_quality == RTC_BUILD_QUALITY_LOW
    assert DomainCache(store, len(store.domains)).build_quality is None
