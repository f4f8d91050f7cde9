"""Sparse loads (scene/sparse.py): a domain built from the triangles a few rays can hit answers
those rays as the whole domain does, bit for bit, and says which other rays it cannot answer;
out of core, image and spec-ooc renders that load domains sparse give the in-core image."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.render.scene_config import SceneConfig
from vastray.render.tracer import box_pad
from vastray.scene import sparse
from vastray.scene.bvh import DomainBVH
from vastray.scene.cache import DomainCache
from vastray.scene.sparse import RaySegments, SparseDomainBVH, select
from vastray.scene.store import DomainArrays

from scenes import bumpy_scene, rm_store, settings
from test_occupancy import boundary_triangles

UNIT = (np.zeros(3), np.ones(3))


def soup(seed: int = 0, n: int = 4000) -> DomainArrays:
    """Small random triangles in [0, 1]^3, some lying in cell boundary planes, and a few
    large ones spanning many cells."""
    rng = np.random.default_rng(seed)
    small = rng.uniform(0.05, 0.95, (n, 1, 3)) + rng.uniform(-0.02, 0.02, (n, 3, 3))
    large = rng.uniform(0.0, 1.0, (4, 3, 3))
    tris = np.concatenate([small, boundary_triangles(rng, n // 4, cells=16), large])
    tris = np.clip(tris, 0.0, 1.0).astype(np.float32)
    return DomainArrays(tris.reshape(-1, 3),
                        np.arange(len(tris) * 3, dtype=np.uint32).reshape(-1, 3))


def rays(rng, n: int, axis_aligned: bool = False) -> tuple[np.ndarray, ...]:
    """(origins, directions, limits): from inside and outside the box, some axis-aligned or
    along a cell plane, some of finite length."""
    origins = rng.uniform(-0.3, 1.3, (n, 3)).astype(np.float32)
    directions = rng.normal(size=(n, 3)).astype(np.float32)
    if axis_aligned:
        directions[: n // 2, 1:] = 0  # along x
        origins[: n // 4, 1] = 0.5  # in a cell boundary plane of a 16-cell grid
    limits = np.where(rng.random(n) < 0.5, np.inf, rng.uniform(0.05, 1.0, n)).astype(np.float32)
    return origins, directions, limits


def pad_of(origins: np.ndarray) -> float:
    return box_pad(1.0, 2.0, origins)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("count", [1, 8, 64])
def test_a_sparse_build_answers_its_rays_as_the_whole_domain(seed, count):
    """Closest hits (distance, triangle, barycentrics, normal) and occlusion of the rays a
    selection was made for are the whole domain's, bit for bit, and the selection leaves
    most triangles out for few rays."""
    dom = soup(seed)
    rng = np.random.default_rng(seed + 10)
    o, d, t = rays(rng, count, axis_aligned=seed == 1)
    segments = RaySegments(o, d, t, pad_of(o))
    chosen = select(dom.vertices, dom.indices, *UNIT, segments)
    whole = DomainBVH(0, dom)
    part = SparseDomainBVH(0, dom, chosen)
    if count <= 8:
        assert part.n_triangles < 0.5 * dom.n_triangles, part.n_triangles
    got, want = part.intersect(o, d, t), whole.intersect(o, d, t)
    for key in ("primID", "tfar", "u", "v", "Ng"):
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)
    np.testing.assert_array_equal(part.occluded(o, d, t), whole.occluded(o, d, t))
    assert part.covers(o, d, t, segments.pad).all()
    assert np.array_equal(chosen.triangles, np.unique(chosen.triangles))  # ascending: ties


def test_every_triangle_a_ray_hits_is_selected():
    """The triangle each of many rays hits in the whole domain is among those selected for it
    alone (rays aimed at triangle centres, boundary-lying triangles included)."""
    dom = soup(3, n=800)
    rng = np.random.default_rng(4)
    tris = dom.vertices[dom.indices]
    targets = tris.mean(axis=1)[rng.integers(0, dom.n_triangles, 300)]
    o = rng.uniform(-0.3, 1.3, (300, 3)).astype(np.float32)
    d = (targets - o).astype(np.float32)
    t = np.full(300, np.inf, np.float32)
    hit = DomainBVH(0, dom).intersect(o, d, t)["primID"]
    for i in np.nonzero(hit >= 0)[0]:
        chosen = select(dom.vertices, dom.indices, *UNIT,
                        RaySegments(o[i:i + 1], d[i:i + 1], t[i:i + 1], pad_of(o)))
        assert hit[i] in chosen.triangles


def test_covers_names_the_rays_a_sparse_build_cannot_answer():
    """Rays of another part of the box are not covered (a schedule queues them for a later
    load); a ray whose numbers are not finite selects every triangle."""
    dom = soup(5)
    o = np.array([[0.1, 0.1, -0.5]], np.float32)
    d = np.array([[0.0, 0.0, 1.0]], np.float32)
    t = np.array([np.inf], np.float32)
    chosen = select(dom.vertices, dom.indices, *UNIT, RaySegments(o, d, t, pad_of(o)))
    part = SparseDomainBVH(0, dom, chosen)
    far = np.array([[0.9, 0.9, -0.5], [0.1, 0.1, -0.5]], np.float32)
    assert part.covers(far, np.repeat(d, 2, 0), np.full(2, np.inf, np.float32),
                       pad_of(far)).tolist() == [False, True]
    nan = np.array([[np.nan, 0.1, 0.1]], np.float32)
    everything = select(dom.vertices, dom.indices, *UNIT, RaySegments(nan, d, t, 0.0))
    assert len(everything.triangles) == dom.n_triangles and everything.marks is None


@pytest.fixture(scope="module")
def big_domains(tmp_path_factory):
    """rm 96^3 in 3x3x2 domains: thousands of triangles a domain, so the last bounces' few
    rays a domain take a small share of it."""
    return rm_store(tmp_path_factory.mktemp("sparse-rm") / "rm.store", 96, (3, 3, 2))


@pytest.mark.parametrize("scheduler", ["image", "spec-ooc"])
def test_out_of_core_renders_with_sparse_loads_give_the_in_core_image(big_domains, scheduler,
                                                                      monkeypatch):
    """PT with a point light (spec-ooc casts shadow rays at every hit and tests them in the
    domain at once) out of core at a quarter of the domains: some domains are loaded sparse,
    spec-ooc defers shadow rays that leave a sparse load's cells, and the image is the in-core
    one bit for bit; with sparse loads off the loads are more."""
    st = settings(width=40, height=30, spp=4, integrator="pt", bounces=3)
    store = big_domains
    inside = render_out_of_core(store, SceneConfig(), st,
                                JobOptions(scheduler=scheduler, cache=len(store.domains),
                                           threads=1), progress=False)
    options = JobOptions(scheduler=scheduler, cache=-(-len(store.domains) // 4), threads=1)
    sparse_on = render_out_of_core(store, SceneConfig(), st, options, progress=False)
    monkeypatch.setenv(sparse.ENV, "0")
    sparse_off = render_out_of_core(store, SceneConfig(), st, options, progress=False)
    np.testing.assert_array_equal(sparse_on.film.image(), inside.film.image())
    np.testing.assert_array_equal(sparse_off.film.image(), inside.film.image())
    on, off = sparse_on.counters, sparse_off.counters
    assert on["sparse_loads"] > 0 and off["sparse_loads"] == 0
    assert 0 < on["sparse_triangle_share"] <= sparse.MAX_SHARE
    assert on["loads"] < off["loads"], (on["loads"], off["loads"])
    if scheduler == "spec-ooc":
        assert on["shadow_deferred"] > 0


def test_a_cache_holding_every_domain_never_loads_sparse(tmp_path):
    """In core (the cache holds the store) a domain is loaded whole and cached whatever rays
    ask for it."""
    from scenes import write_store

    store = write_store(tmp_path / "b.store", bumpy_scene(), grid=(2, 1, 1))
    cache = DomainCache(store, len(store.domains))
    o = np.zeros((1, 3), np.float32)
    segments = RaySegments(o, np.ones((1, 3), np.float32), np.ones(1, np.float32), 1e-6)
    assert isinstance(cache.get_for(0, segments), DomainBVH)
    assert cache.stats.loads == 1 and cache.stats.sparse_loads == 0 and 0 in cache
