"""Thousands of domains: the tree over domain boxes answers exactly what the per-box slab test
answered, and renders over 1,000+ domains give the one-domain image."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.actors.job_options import JobOptions
from vastray.actors.local import render_out_of_core
from vastray.render.boxtree import FLAT_BOXES, BoxTree
from vastray.render.driver import render
from vastray.render.lights import AmbientLight, PointLight, QuadLight
from vastray.render.tracer import DomainTracer, RaySlabs, box_pad
from vastray.scene.cache import DomainCache
from vastray.schedule.geometry import DomainGeometry

from domain_loops import crossings_by_loop, next_domain_by_loop
from scenes import camera_config, settings, terrain_scene, write_store


# -- boxes and rays that make the slab test work hard -----------------------------------------
def hard_boxes(rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(D, 3) lo, hi and (D,) non-empty flags: grid cells sharing faces, edges and corners;
    overlapping random boxes; flat (zero-thickness) boxes; a few empty domains."""
    edges = [np.linspace(-1, 1, 7), np.linspace(-1, 1, 6), np.linspace(-1, 1, 5)]
    ix, iy, iz = (a.ravel() for a in np.meshgrid(np.arange(6), np.arange(5), np.arange(4),
                                                 indexing="ij"))
    lo = [np.stack([edges[0][ix], edges[1][iy], edges[2][iz]], axis=1)]
    hi = [np.stack([edges[0][ix + 1], edges[1][iy + 1], edges[2][iz + 1]], axis=1)]
    center = rng.uniform(-1, 1, (40, 3))
    half = rng.uniform(0.02, 0.4, (40, 3))
    lo.append(center - half)
    hi.append(center + half)
    flat = rng.uniform(-1, 1, (6, 3))
    thick = flat + rng.uniform(0.1, 0.5, (6, 3))
    thick[np.arange(6), np.arange(6) % 3] = flat[np.arange(6), np.arange(6) % 3]
    lo.append(flat)
    hi.append(thick)
    lo, hi = np.concatenate(lo), np.concatenate(hi)
    nonempty = rng.random(len(lo)) > 0.05
    return lo, hi, nonempty


def hard_rays(rng, lo, hi, n=4000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, 3) float32 origins and directions, (n,) float32 limits: random rays; rays starting
    on box faces, edges and corners; directions with zero (and denormal) components, axis
    aligned, diagonal; limits infinite, finite, zero."""
    corners = np.concatenate([lo, hi])
    origins = rng.uniform(-1.5, 1.5, (n, 3))
    on = rng.random(n) < 0.6  # start on box planes: 1, 2 or 3 coordinates from box corners
    for axis in range(3):
        pick = on & (rng.random(n) < 0.6)
        origins[pick, axis] = corners[rng.integers(0, len(corners), pick.sum()), axis]
    directions = rng.normal(size=(n, 3))
    zero = rng.random((n, 3)) < 0.35
    zero[zero.all(axis=1), 0] = False
    directions[zero] = 0.0
    diagonal = rng.random(n) < 0.1
    directions[diagonal] = rng.choice([-1.0, 1.0], (diagonal.sum(), 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    tiny = rng.random((n, 3)) < 0.02  # denormal components: 1 / d overflows, 0 * inf = NaN
    directions[tiny] = 1e-40
    limit = np.where(rng.random(n) < 0.5, np.inf, rng.uniform(0, 3, n))
    limit[rng.random(n) < 0.03] = 0.0
    return origins.astype(np.float32), directions.astype(np.float32), limit.astype(np.float32)


def bits(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, np.float32).view(np.uint32)


def assert_crossings_equal(got, want):
    ray, domain, entry, rank = got
    ray0, domain0, entry0, rank0 = want
    assert ray.dtype == ray0.dtype and domain.dtype == domain0.dtype
    assert entry.dtype == entry0.dtype and rank.dtype == rank0.dtype
    np.testing.assert_array_equal(ray, ray0)
    np.testing.assert_array_equal(domain, domain0)
    np.testing.assert_array_equal(bits(entry), bits(entry0))
    np.testing.assert_array_equal(rank, rank0)


#: The three walks that must agree: the compiled per-ray walk (the default), the numpy
#: breadth-first walk of the tree, and the numpy flat pass over every box.
WALKS = ("compiled", "tree", "flat")


def walk_with(tree: BoxTree, mode: str) -> None:
    tree.compiled = mode == "compiled"
    tree.flat = mode == "flat"


@pytest.fixture(params=WALKS)
def geometry_and_rays(request):
    rng = np.random.default_rng(11)
    lo, hi, nonempty = hard_boxes(rng)
    geometry = DomainGeometry(lo, hi, nonempty, origin_bound=1.5)
    assert geometry.tree.size > FLAT_BOXES and not geometry.tree.flat and geometry.tree.compiled
    walk_with(geometry.tree, request.param)  # the same boxes, each way
    return geometry, hard_rays(rng, lo, hi)


def test_crossings_equal_the_per_box_slab_test(geometry_and_rays):
    geometry, (origins, directions, limit) = geometry_and_rays
    got = geometry.crossings(origins, directions, limit)
    assert_crossings_equal(got, crossings_by_loop(geometry, origins, directions, limit))
    assert len(got[0]) > 2 * len(origins)  # the rays do cross many boxes
    edge_case = (directions == 0).any(axis=1) | (np.abs(directions) < 1e-30).any(axis=1)
    assert np.isin(np.nonzero(edge_case)[0], got[0]).mean() > 0.5


def test_walking_next_domain_equals_the_per_box_loop(geometry_and_rays):
    # The image schedule's walk: each ray moves to the next domain after its cursor until none.
    geometry, (origins, directions, limit) = geometry_and_rays
    n = len(origins)
    at_t = np.full(n, -np.inf, np.float32)
    at_d = np.full(n, -1, np.int32)
    steps = 0
    while True:
        got = geometry.next_domain(origins, directions, at_t, at_d, limit)
        want = next_domain_by_loop(geometry, origins, directions, at_t, at_d, limit)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(bits(got[1]), bits(want[1]))
        moving = got[0] >= 0
        if not moving.any():
            break
        at_t = np.where(moving, got[1], at_t)
        at_d = np.where(moving, got[0], at_d)
        steps += 1
    ray, domain, _, _ = geometry.crossings(origins, directions, limit)
    assert steps == np.bincount(ray, minlength=n).max()  # the walk visits every crossing


def test_tree_pairs_are_the_tracers_slab_test(geometry_and_rays):
    # DomainTracer's test: t0 <= t1, t1 >= 0, t0 < limit (t0 not clamped), for every box.
    geometry, (origins, directions, limit) = geometry_and_rays
    slabs = geometry.slabs(origins, directions)
    if geometry.tree.compiled:
        ray, box, t0 = geometry.tree.entered(slabs, limit)
        assert (np.diff(ray) >= 0).all()  # by ray, as the tracer groups them
    else:
        ray, box, t0, t1 = geometry.tree.pairs(slabs, limit)
        enter = (t0 <= t1) & (t1 >= 0) & (t0 < limit[ray])
        ray, box, t0 = ray[enter], box[enter], t0[enter]
    got = sorted(zip(box.tolist(), ray.tolist(), bits(t0).tolist(), strict=True))
    want = []
    for d in geometry.ids:
        w0, w1 = slabs.intervals(geometry.lo[d], geometry.hi[d])
        rows = np.nonzero((w0 <= w1) & (w1 >= 0) & (w0 < limit))[0]
        want += zip([int(d)] * len(rows), rows.tolist(), bits(w0[rows]).tolist(), strict=True)
    assert got == sorted(want)


@pytest.mark.parametrize("count", [1, 2, 3, 5, 31, 33, 100])
def test_trees_of_any_size(count):
    rng = np.random.default_rng(count)
    center = rng.uniform(-1, 1, (count, 3))
    lo, hi = center - 0.3, center + 0.3
    origins, directions, limit = hard_rays(rng, lo, hi, 500)
    for mode in WALKS:
        geometry = DomainGeometry(lo, hi, np.ones(count, bool), 1.5)
        walk_with(geometry.tree, mode)
        assert_crossings_equal(geometry.crossings(origins, directions, limit),
                               crossings_by_loop(geometry, origins, directions, limit))
        at_t = np.full(len(origins), -np.inf, np.float32)
        at_d = np.full(len(origins), -1, np.int32)
        got = geometry.next_domain(origins, directions, at_t, at_d, limit)
        want = next_domain_by_loop(geometry, origins, directions, at_t, at_d, limit)
        np.testing.assert_array_equal(got[0], want[0])
    tree = BoxTree(lo, hi)
    assert sorted(tree.box[tree.box >= 0].tolist()) == list(range(count))
    inner = tree.child[:, 0] >= 0
    for side in (0, 1):  # every node box holds its children's
        assert (tree.node_lo[inner] <= tree.node_lo[tree.child[inner, side]]).all()
        assert (tree.node_hi[inner] >= tree.node_hi[tree.child[inner, side]]).all()


def test_nan_distances_give_the_per_box_answers():
    # A denormal direction component makes 1 / d infinite, and a ray starting exactly on a
    # padded plane of a box or tree node then computes 0 * inf = NaN there: the per-box test
    # rejects such a box, and the tree, whose nodes are never dropped for a NaN, answers the
    # same.
    rng = np.random.default_rng(7)
    lo, hi, nonempty = hard_boxes(rng)
    geometry = DomainGeometry(lo, hi, nonempty, origin_bound=1.5)
    n = 3000
    origins = rng.uniform(-1.2, 1.2, (n, 3))
    directions = rng.normal(size=(n, 3))
    pad = box_pad(geometry.box_magnitude, geometry.origin_bound, origins)
    axis = rng.integers(0, 3, n)
    nodes = rng.integers(0, len(geometry.tree.node_lo), n)  # planes of leaves and inner nodes
    plane = np.where(rng.random(n) < 0.5, geometry.tree.node_lo[nodes, axis] - pad,
                     geometry.tree.node_hi[nodes, axis] + pad)
    origins[np.arange(n), axis] = plane.astype(np.float32)
    directions[np.arange(n), axis] = 1e-40
    origins, directions = origins.astype(np.float32), directions.astype(np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        t0 = geometry.slabs(origins, directions).intervals(lo[0], hi[0])[0]
        nans = sum(np.isnan(geometry.slabs(origins, directions).intervals(lo[d], hi[d])[0]).sum()
                   for d in range(len(lo)))
    assert nans > 50 and t0.dtype == np.float32
    limit = np.full(n, np.inf, np.float32)
    for mode in WALKS:
        walk_with(geometry.tree, mode)
        assert_crossings_equal(geometry.crossings(origins, directions, limit),
                               crossings_by_loop(geometry, origins, directions, limit))
        at_t = np.full(n, -np.inf, np.float32)
        at_d = np.full(n, -1, np.int32)
        for _ in range(3):
            got = geometry.next_domain(origins, directions, at_t, at_d, limit)
            want = next_domain_by_loop(geometry, origins, directions, at_t, at_d, limit)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(bits(got[1]), bits(want[1]))
            moving = got[0] >= 0
            at_t, at_d = np.where(moving, got[1], at_t), np.where(moving, got[0], at_d)


def test_no_domains():
    geometry = DomainGeometry(np.zeros((2, 3)), np.ones((2, 3)), np.zeros(2, bool), 1.0)
    origins = np.zeros((3, 3), np.float32)
    directions = np.ones((3, 3), np.float32)
    ray, domain, entry, rank = geometry.crossings(origins, directions,
                                                  np.full(3, np.inf, np.float32))
    assert len(ray) == len(domain) == len(entry) == len(rank) == 0
    d, e = geometry.next_domain(origins, directions, np.full(3, -np.inf, np.float32),
                                np.full(3, -1, np.int32), np.full(3, np.inf, np.float32))
    assert (d == -1).all() and np.isinf(e).all()


# -- the renders ------------------------------------------------------------------------------
LIGHTS = [PointLight(np.array([2.0, 3.0, 1.0]), np.full(3, 12.0)),
          QuadLight(np.array([-1.0, 3.0, -1.0]), np.array([0.0, 0.0, 0.8]),
                    np.array([0.8, 0.0, 0.0]), np.full(3, 4.0)),
          AmbientLight(np.full(3, 0.2))]


@pytest.fixture(scope="module")
def terrain(tmp_path_factory):
    root = tmp_path_factory.mktemp("many")
    mesh = terrain_scene()
    return {"one": write_store(root / "one", mesh),
            "few": write_store(root / "few", mesh, grid=(4, 1, 4)),
            "grid": write_store(root / "grid", mesh, grid=(32, 2, 32)),
            "kd": write_store(root / "kd", mesh, kd=1100)}


def _old_visits(tracer: DomainTracer, slabs: RaySlabs, limit, live=None):
    """DomainTracer._visits as it was: a slab test of every domain for every ray, per visit."""
    def entering(d):
        t0, t1 = slabs.intervals(tracer.lo[d], tracer.hi[d])
        return (t0 <= t1) & (t1 >= 0) & (t0 < limit)

    ids = np.nonzero(tracer.nonempty)[0]
    if tracer.cache.capacity >= len(ids):
        center = slabs.origin.mean(axis=1, dtype=np.float64)
        gap = np.maximum(tracer.lo[ids] - center, 0) + np.maximum(center - tracer.hi[ids], 0)
        order = ids[np.argsort(np.einsum("ij,ij->i", gap, gap), kind="stable")]
    else:
        waiting = {d: np.count_nonzero(entering(d)) for d in ids}
        resident = set(tracer.cache.resident())
        order = sorted((d for d in ids if waiting[d]),
                       key=lambda d: (d not in resident, -waiting[d], d))
    for d in order:
        rows = np.nonzero(entering(d) if live is None else entering(d) & live)[0]
        if len(rows):
            yield int(d), rows


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("bounded", [False, True])
@pytest.mark.parametrize("store_name", ["few", "grid"])
def test_tracer_visits_what_the_per_domain_loop_visited(terrain, store_name, bounded, compiled):
    # Same domains, same order, same rows, also while limits shrink and rays die between
    # visits (both walks get the same updates): with all domains resident (nearest first) and
    # with a bounded cache (LoadAnyOnce), through the compiled walk, and in numpy through the
    # tree and through the flat pass.
    store = terrain[store_name]
    n_domains = len(store.domains)
    capacity = n_domains // 4 if bounded else n_domains
    tracer = DomainTracer(store, DomainCache(store, capacity), threads=1)
    assert tracer.tree.flat == (store_name == "few")
    tracer.tree.compiled = compiled
    if bounded:
        for d in range(0, n_domains, 7):
            tracer.cache.get(d)
    rng = np.random.default_rng(3)
    n = 3000
    origins = rng.uniform(-2.5, 2.5, (n, 3)).astype(np.float32)
    origins[: n // 3, 1] = 2.0
    directions = rng.normal(size=(n, 3))
    directions[: n // 3] = [0.3, -1.0, 0.2]
    directions[n // 3: n // 2, 1] = 0.0
    directions = (directions / np.linalg.norm(directions, axis=1, keepdims=True)
                  ).astype(np.float32)
    slabs = tracer.slabs(origins, directions)
    limit_new = np.full(n, np.inf, np.float32)
    limit_old = limit_new.copy()
    live_new, live_old = np.ones(n, bool), np.ones(n, bool)
    visits = 0
    for (d_new, rows_new), (d_old, rows_old) in zip(
            tracer._visits(slabs, limit_new, live_new),
            _old_visits(tracer, slabs, limit_old, live_old), strict=True):
        assert d_new == d_old
        np.testing.assert_array_equal(rows_new, rows_old)
        hit = np.float32(rng.uniform(0, 6))
        for limit, live in ((limit_new, live_new), (limit_old, live_old)):
            limit[rows_new[::3]] = np.minimum(limit[rows_new[::3]], hit)
            live[rows_new[1::5]] = False
        visits += 1
    assert visits > min(100, n_domains // 2)


@pytest.mark.parametrize("runner", ["reference", "image", "spec-ooc"])
@pytest.mark.parametrize("partition", ["grid", "kd"])
def test_image_identical_to_one_domain_at_a_thousand_domains(terrain, partition, runner):
    store = terrain[partition]
    assert len(store.domains) >= 1000
    cfg = camera_config([3.0, 2.4, 4.0], [0.0, -0.4, 0.0], fov=50, lights=LIGHTS)
    st = settings(width=16, height=12, spp=2, integrator="pt", bounces=2)
    reference = render(terrain["one"], cfg, st, progress=False).film.image()
    assert reference.max() > 0.05
    if runner == "reference":  # every domain resident (nearest first), and LoadAnyOnce
        runs = [render(store, cfg, st, progress=False),
                render(store, cfg, st, cache_capacity=300, progress=False)]
    else:
        runs = [render_out_of_core(store, cfg, st, options=JobOptions(scheduler=runner, cache=300),
                                   progress=False)]
    assert runs[0].counters["loads"] > 300  # most domains took part
    for result in runs:
        np.testing.assert_array_equal(result.film.image(), reference,
                                      err_msg=f"{len(store.domains)} domains, {runner}")


def test_box_padding_is_the_tracers():
    # The tree pads its boxes as RaySlabs.intervals does, so leaf distances are bit-identical.
    rng = np.random.default_rng(5)
    lo = rng.uniform(-1e4, 1e4, (50, 3))
    hi = lo + rng.uniform(0, 1e-3, (50, 3))
    origins = rng.uniform(-2e4, 2e4, (200, 3))
    aim = (lo[rng.integers(0, 50, 200)] - origins) / 1e4 + rng.normal(0, 1e-8, (200, 3))
    origins, directions = origins.astype(np.float32), aim.astype(np.float32)
    slabs = RaySlabs(origins, directions, box_pad(2e4, 4e4, origins))
    tree = BoxTree(lo, hi)
    ray, box, t0, t1 = tree.pairs(slabs)
    assert len(ray) > 100
    for d in range(50):
        w0, w1 = slabs.intervals(lo[d], hi[d])
        mine = box == d
        np.testing.assert_array_equal(bits(t0[mine]), bits(w0[ray[mine]]))
        np.testing.assert_array_equal(bits(t1[mine]), bits(w1[ray[mine]]))


def test_compiled_crossings_grow_their_output():
    # Rays along a 16^3 grid's diagonals cross far more boxes than the first output holds
    # (4 per ray + 64): the compiled walk stops, the output grows, the walk goes on.
    edges = np.linspace(0.0, 1.0, 17)
    ix, iy, iz = (a.ravel() for a in np.meshgrid(*[np.arange(16)] * 3, indexing="ij"))
    lo = np.stack([edges[ix], edges[iy], edges[iz]], axis=1)
    hi = np.stack([edges[ix + 1], edges[iy + 1], edges[iz + 1]], axis=1)
    geometry = DomainGeometry(lo, hi, np.ones(len(lo), bool), origin_bound=2.0)
    origins = np.array([[-0.5, -0.5, -0.5], [1.5, -0.5, -0.5], [0.3, 0.3, -1.0]], np.float32)
    directions = np.array([[1, 1, 1], [-1, 1, 1], [0, 0, 1]], np.float32)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    limit = np.full(3, np.inf, np.float32)
    got = geometry.crossings(origins, directions, limit)
    assert len(got[0]) > 4 * len(origins) + 64
    assert np.bincount(got[0]).min() >= 16  # each ray crosses at least a row of cells
    assert_crossings_equal(got, crossings_by_loop(geometry, origins, directions, limit))
