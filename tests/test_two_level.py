"""One query per ray in core: a top-level Embree scene of domain instances (issue 9).

With every domain resident the tracer queries one top-level scene holding an instance per
domain instead of visiting domains one by one; the hits, and so the image, must be the same
bit for bit, ties between domains included (the lower domain id wins).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from vastray.render.driver import render
from vastray.render.tracer import DomainTracer
from vastray.scene.cache import DomainCache
from vastray.scene.embree.library import binding
from vastray.scene.embree.scenes import TopScene
from vastray.scene.store import DomainArrays, Store, StoreWriter

from embree_hooks import live_scenes
from scenes import bumpy_config, bumpy_scene, mesh_arrays, settings, write_store

pytestmark = pytest.mark.skipif(binding() is None,
                                reason="the compiled Embree binding is unavailable")



@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    root = tmp_path_factory.mktemp("two_level")
    mesh = bumpy_scene()
    rng = np.random.default_rng(0)
    colored = DomainArrays(mesh.vertices, mesh.indices,
                           colors=rng.uniform(0.2, 1.0, (len(mesh.vertices), 3)).astype(np.float32))
    return {
        "grid8": write_store(root / "grid8", mesh, grid=(2, 2, 2)),
        "kd64": write_store(root / "kd64", mesh, kd=64),
        "colors27": write_store(root / "colors27", colored, grid=(3, 3, 3)),
        "one": write_store(root / "one", colored, grid=(1, 1, 1)),
    }


def _count_top_queries(monkeypatch) -> dict:
    calls = {"intersect": 0, "occluded": 0}
    for name in calls:
        original = getattr(TopScene, name)

        def counted(self, *args, _name=name, _original=original, **kw):
            calls[_name] += 1
            return _original(self, *args, **kw)

        monkeypatch.setattr(TopScene, name, counted)
    return calls


@pytest.mark.parametrize("integrator", ["ao", "pt"])
@pytest.mark.parametrize("name", ["grid8", "kd64", "colors27"])
def test_image_bit_identical_to_domain_by_domain(stores, name, integrator, monkeypatch):
    cfg = bumpy_config()
    st = settings(width=64, height=48, spp=2, integrator=integrator, batch_size=1024)
    per_domain = render(stores[name], cfg, st, progress=False, two_level=False)
    calls = _count_top_queries(monkeypatch)
    two_level = render(stores[name], cfg, st, progress=False)
    assert calls["intersect"] > 0 and calls["occluded"] > 0  # the top level was used
    assert per_domain.film.image().max() > 0.05
    np.testing.assert_array_equal(two_level.film.image(), per_domain.film.image())
    np.testing.assert_array_equal(two_level.film.depth_image(), per_domain.film.depth_image())
    np.testing.assert_array_equal(two_level.film.normal_image(),
                                  per_domain.film.normal_image())


@pytest.mark.parametrize("integrator", ["ao", "pt"])
def test_one_domain_is_queried_without_box_tests(stores, integrator):
    # One domain: every ray goes straight to its Embree scene (no ray-box test), as rays go
    # to the top-level scene with several; the image is the per-domain query's, bit for bit.
    cfg = bumpy_config()
    st = settings(width=64, height=48, spp=2, integrator=integrator, batch_size=1024)
    per_domain = render(stores["one"], cfg, st, progress=False, two_level=False)
    direct = render(stores["one"], cfg, st, progress=False)
    rays = direct.counters["rays"]["total"]
    assert rays == per_domain.counters["rays"]["total"]
    # camera rays that miss the scene's box are never queried (nor counted in "rays"),
    # whichever way (trace_paths)
    escaped = direct.counters["camera_rays_escaped"]
    assert escaped == per_domain.counters["camera_rays_escaped"]
    queried = rays
    assert direct.counters["ray_domain_tests"] == queried  # every ray, none box-culled
    assert escaped > 0
    # nor does the per-domain box test cull any ray here: every bounce and shadow ray starts
    # on a surface in the box, and the camera rays it culled before session 79 (those
    # through the quad light's part of the scene's box) are left out before, with the pixels
    # where no occupied cell nor the light can be seen (render.seen_pixels)
    assert per_domain.counters["ray_domain_tests"] == queried
    assert per_domain.film.image().max() > 0.05
    np.testing.assert_array_equal(direct.film.image(), per_domain.film.image())
    np.testing.assert_array_equal(direct.film.depth_image(), per_domain.film.depth_image())
    np.testing.assert_array_equal(direct.film.normal_image(), per_domain.film.normal_image())


def test_bounded_cache_keeps_per_domain_queries(stores, monkeypatch):
    calls = _count_top_queries(monkeypatch)
    render(stores["kd64"], bumpy_config(), settings(integrator="ao"),
           cache_capacity=8, progress=False)
    assert calls == {"intersect": 0, "occluded": 0}


def _duplicate_store(path) -> Store:
    """Two domains holding the same sphere (objects 0 and 1), a third far away: every hit on
    the sphere ties between domains 0 and 1."""
    sphere = mesh_arrays(trimesh.creation.icosphere(subdivisions=3))
    far = mesh_arrays(trimesh.creation.icosphere(subdivisions=1))
    far.vertices = far.vertices + np.float32(50.0)
    with StoreWriter(path, objects=[{"name": "a"}, {"name": "b"}]) as writer:
        n = len(sphere.indices)
        writer.add_domain(DomainArrays(far.vertices, far.indices,
                                       objects=np.zeros(len(far.indices), np.uint16)))
        writer.add_domain(DomainArrays(sphere.vertices, sphere.indices,
                                       objects=np.ones(n, np.uint16)))
        writer.add_domain(DomainArrays(sphere.vertices, sphere.indices,
                                       objects=np.zeros(n, np.uint16)))
    return Store(path)


def test_ties_between_domains_go_to_the_lower_domain_id(tmp_path, monkeypatch):
    store = _duplicate_store(tmp_path / "dup")
    rng = np.random.default_rng(1)
    n = 4000
    origins = (rng.normal(size=(n, 3)) * 3).astype(np.float32)
    directions = (rng.normal(size=(n, 3)) * 0.3 - origins).astype(np.float32)
    results = {}
    for two_level in (False, True):
        cache = DomainCache(store, 3, keep=frozenset({"objects"}))
        tracer = DomainTracer(store, cache, threads=2, two_level=two_level)
        for d in range(3):
            cache.get(d)  # all resident: the top level has every domain
        calls = _count_top_queries(monkeypatch)
        hits = tracer.intersect(origins, directions)
        blocked = tracer.occluded(origins, directions, np.full(n, 2.5, np.float32))
        assert calls["intersect"] == int(two_level)
        results[two_level] = hits, blocked
        tracer.close()
        monkeypatch.undo()
    (hits, blocked), (hits2, blocked2) = results[False], results[True]
    assert hits.hit.sum() > n // 2
    assert (hits.material[hits.hit] == 1).all()  # domain 1 (object 1) won every tie
    np.testing.assert_array_equal(hits2.material, hits.material)
    np.testing.assert_array_equal(hits2.t, hits.t)
    np.testing.assert_array_equal(hits2.normal, hits.normal)
    np.testing.assert_array_equal(blocked2, blocked)
    assert blocked.any() and not blocked.all()


def test_domains_missing_from_the_top_level_are_visited_and_loaded(stores):
    # Only some domains resident: the top level holds those, the others are visited (and so
    # loaded) one by one; the hits equal the per-domain tracer's.
    store = stores["kd64"]
    rng = np.random.default_rng(2)
    n = 3000
    origins = rng.uniform(-3, 3, (n, 3)).astype(np.float32)
    origins[:, 1] = 2.5
    directions = (rng.normal(size=(n, 3)) * 0.5 + [0.0, -1.0, 0.0]).astype(np.float32)
    reference = DomainTracer(store, DomainCache(store, 64), threads=1, two_level=False)
    want = reference.intersect(origins, directions)
    want_blocked = reference.occluded(origins, directions, np.full(n, 3.0, np.float32))
    cache = DomainCache(store, 64)
    for d in range(0, 64, 3):
        cache.get(d)
    tracer = DomainTracer(store, cache, threads=1)
    got = tracer.intersect(origins, directions)
    assert len(cache.resident()) > 22  # visiting loaded more
    got_blocked = tracer.occluded(origins, directions, np.full(n, 3.0, np.float32))
    np.testing.assert_array_equal(got.t, want.t)
    np.testing.assert_array_equal(got.normal, want.normal)
    np.testing.assert_array_equal(got_blocked, want_blocked)
    tracer.close()
    reference.close()


def test_top_scene_close_releases(stores):
    before = live_scenes()
    store = stores["grid8"]
    cache = DomainCache(store, 8)
    tracer = DomainTracer(store, cache, threads=1)
    for d in range(8):
        cache.get(d)
    tracer.intersect(np.zeros((4, 3), np.float32) + 5, -np.ones((4, 3), np.float32))
    assert live_scenes() == before + len(cache.resident()) + 1
    tracer.close()
    assert live_scenes() == before + len(cache.resident())

