"""The fused shading kernels (``render.kernels``) against the numpy chain they replace: the
RNG, shading and the radiance sum must agree bit for bit."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from vastray.render import kernels
from vastray.render.film import Film
from vastray.render.integrators import (
    PathContext,
    PathResult,
    RadianceRays,
    RenderSettings,
    Shading,
    add_unoccluded,
    shade,
)
from vastray.render.lights import AmbientLight, DirectionalLight, PointLight, QuadLight
from vastray.render.materials import Material, MaterialTable
from vastray.render.rng import Purpose, uniform2
from vastray.render.tracer import Hits

from oracles import add_unoccluded_numpy, shade_numpy


def test_numba_rng_equals_numpy_rng_on_many_keys():
    rng = np.random.default_rng(0)
    n = 200_000
    pixel = rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)
    sample = rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)
    bounce = rng.integers(0, 256, n, dtype=np.uint64).astype(np.uint8)
    index = rng.integers(0, 2**40, n, dtype=np.uint64)
    for seed in (0, 7, 2**63 + 12345, 2**64 - 1):
        for purpose in (Purpose.CAMERA_JITTER, Purpose.AO_DIRECTION,
                        Purpose.LIGHT_SAMPLE + 16 * 3, Purpose.BOUNCE_DIRECTION):
            want = uniform2(seed, pixel, sample, bounce, purpose, index)
            got = kernels.uniform2(np.uint64(seed), np.uint64(purpose), pixel, sample, bounce,
                                   index)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
    # the uniforms are not all the same value (the comparison above could not fail otherwise)
    assert len(np.unique(got[0])) > n // 2


def test_hemisphere_uniforms_are_the_numpy_keys_repeated():
    rng = np.random.default_rng(1)
    pixel = rng.integers(0, 10_000, 50).astype(np.uint32)
    sample = rng.integers(0, 8, 50).astype(np.uint32)
    path = rng.integers(0, 50, 300)
    depth = rng.integers(0, 4, 300).astype(np.uint8)
    m = 5
    u, v = kernels.hemisphere_uniforms(np.uint64(9), np.uint64(Purpose.AO_DIRECTION), pixel,
                                       sample, path, depth, m)
    j = np.tile(np.arange(m, dtype=np.uint64), len(path))
    p = np.repeat(path, m)
    want = uniform2(9, pixel[p], sample[p], np.repeat(depth, m), Purpose.AO_DIRECTION, j)
    np.testing.assert_array_equal(u, want[0])
    np.testing.assert_array_equal(v, want[1])


def _batch(k: int, seed: int, n_materials: int, with_color: bool):
    """k radiance rays that hit, with random hits (mixed depths, some black throughput)."""
    rng = np.random.default_rng(seed)
    P = 2 * k
    path = np.sort(rng.choice(P, k, replace=False)).astype(np.int64)
    depth = rng.integers(0, 4, k).astype(np.uint8)
    origin = rng.uniform(-3, 3, (k, 3)).astype(np.float32)
    direction = rng.standard_normal((k, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    beta = rng.uniform(0, 1, (k, 3))
    beta[rng.random(k) < 0.05] = 0.0  # paths that carry nothing: no continuation
    rays = RadianceRays(path, depth, origin, direction.astype(np.float32), beta)
    normal = rng.standard_normal((k, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    hits = Hits(rng.uniform(0.01, 5, k), normal, rng.integers(0, n_materials, k),
                rng.uniform(0, 1, (k, 3)) if with_color else None)
    pixel = rng.integers(0, 100_000, P).astype(np.uint32)
    sample = rng.integers(0, 16, P).astype(np.uint32)
    return rays, hits, pixel, sample


LIGHTS = [
    DirectionalLight(np.array([-0.4, -1.0, -0.6]), np.full(3, 2.4)),
    AmbientLight(np.array([0.25, 0.3, 0.2])),
    PointLight(np.array([1.0, 4.0, -2.0]), np.array([30.0, 20.0, 10.0])),
    QuadLight(np.array([-1.0, 5.0, -1.0]), np.array([2.0, 0.0, 0.0]), np.array([0.0, 0.0, 2.0]),
              np.array([5.0, 5.0, 4.0])),
]


def _assert_same(a, b):
    assert type(a) is type(b)
    for f in fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert x.dtype == y.dtype and x.shape == y.shape, f.name
        np.testing.assert_array_equal(x, y, err_msg=f.name)


@pytest.mark.parametrize("with_color", [False, True])
@pytest.mark.parametrize("specular", [False, True])
@pytest.mark.parametrize("lights", [LIGHTS[:2], LIGHTS, [LIGHTS[2]], [LIGHTS[3]]],
                         ids=["default", "all", "point", "quad"])
def test_fused_pt_shading_equals_numpy_chain(with_color, specular, lights):
    mats = [Material(np.array([0.7, 0.6, 0.5]), np.zeros(3), 32.0),
            Material(np.array([0.2, 0.8, 0.3]),
                     np.array([0.3, 0.3, 0.3]) if specular else np.zeros(3), 48.0)]
    rays, hits, pixel, sample = _batch(3000, 11, len(mats), with_color)
    settings = RenderSettings(integrator="pt", bounces=3, shadow_samples=6, seed=123)
    ctx = PathContext(Shading(lights, MaterialTable(mats), with_color), settings, pixel, sample,
                      1.0)
    shadow, cont = shade(ctx, rays, hits)
    shadow_np, cont_np = shade_numpy(ctx, rays, hits)
    assert len(shadow) > 1000 and len(cont) > 1000  # the comparison compares something
    _assert_same(shadow, shadow_np)
    _assert_same(cont, cont_np)


@pytest.mark.parametrize("with_color", [False, True])
def test_fused_ao_shading_equals_numpy_chain(with_color):
    rays, hits, pixel, sample = _batch(2000, 5, 1, with_color)
    settings = RenderSettings(integrator="ao", shadow_samples=7, seed=3)
    ctx = PathContext(Shading([], MaterialTable([Material.default()]), with_color), settings,
                      pixel, sample, 0.75)
    shadow, cont = shade(ctx, rays, hits)
    shadow_np, cont_np = shade_numpy(ctx, rays, hits)
    assert len(shadow) == 7 * 2000 and len(cont) == 0
    _assert_same(shadow, shadow_np)
    _assert_same(cont, cont_np)


@pytest.mark.parametrize("integrator", ["pt", "ao"])
def test_shading_rows_in_place_equals_shading_their_takes(integrator):
    # shade(rays, hits, rows) reads the rows in place (no takes, issue 39): the same rays as
    # shading the taken rows, in the order of rows (not sorted), specular lobes included
    mats = [Material(np.array([0.7, 0.6, 0.5]), np.zeros(3), 32.0),
            Material(np.array([0.2, 0.8, 0.3]), np.array([0.3, 0.3, 0.3]), 48.0)]
    rays, hits, pixel, sample = _batch(3000, 11, len(mats), True)
    settings = RenderSettings(integrator=integrator, bounces=3, shadow_samples=4, seed=5)
    ctx = PathContext(Shading(LIGHTS, MaterialTable(mats), True), settings, pixel, sample, 1.0)
    rows = np.random.default_rng(3).permutation(3000)[:1700]
    shadow, cont = shade(ctx, rays, hits, rows)
    shadow_take, cont_take = shade(ctx, rays.take(rows), hits.take(rows))
    assert len(shadow) > 1000 and (len(cont) > 1000 or integrator == "ao")
    _assert_same(shadow, shadow_take)
    _assert_same(cont, cont_take)


def test_shade_refuses_a_light_of_another_kind():
    class Dim(PointLight):  # not one of the kinds the kernels know
        pass

    lights = [LIGHTS[1], Dim(np.array([1.0, 4.0, -2.0]), np.array([30.0, 20.0, 10.0]))]
    rays, hits, pixel, sample = _batch(50, 2, 1, False)
    ctx = PathContext(Shading(lights, MaterialTable([Material.default()]), False),
                      RenderSettings(shadow_samples=3), pixel, sample, 1.0)
    with pytest.raises(TypeError, match=r"light #2 is a Dim: .*PointLight, DirectionalLight, "
                                        r"QuadLight, AmbientLight"):
        shade(ctx, rays, hits)


def test_the_oracles_are_not_in_the_package():
    import importlib.util

    from vastray.render import integrators, lights, materials

    for name in ("shade_numpy", "add_unoccluded_numpy", "spawn", "_next_event_rays",
                 "_ambient_occlusion_rays"):
        assert not hasattr(integrators, name), name
    for kind in (PointLight, DirectionalLight, QuadLight, AmbientLight):
        assert not hasattr(kind, "sample"), kind.__name__
    assert not hasattr(lights, "SampleKeys")
    assert not hasattr(materials, "blinn_phong_lobe")
    assert importlib.util.find_spec("vastray.render.sampling") is None


def test_add_unoccluded_refuses_what_the_kernel_cannot_add_into():
    rays, hits, pixel, sample = _batch(200, 4, 1, False)
    ctx = PathContext(Shading(LIGHTS, MaterialTable([Material.default()]), False),
                      RenderSettings(shadow_samples=2), pixel, sample, 1.0)
    shadow, _ = shade(ctx, rays, hits)
    lit = np.ones(len(shadow), bool)
    with pytest.raises(TypeError, match="C-contiguous float64"):
        add_unoccluded(np.zeros((len(pixel), 3), np.float32), shadow, lit)
    with pytest.raises(TypeError, match="non-contiguous float64"):
        add_unoccluded(np.zeros((3, len(pixel))).T, shadow, lit)


def test_fused_radiance_sum_equals_bincount():
    rays, hits, pixel, sample = _batch(3000, 4, 1, True)
    ctx = PathContext(Shading(LIGHTS, MaterialTable([Material.default()]), True),
                      RenderSettings(shadow_samples=4), pixel, sample, 1.0)
    shadow, _ = shade(ctx, rays, hits)
    lit = np.random.default_rng(0).random(len(shadow)) < 0.7
    start = np.random.default_rng(1).uniform(0, 1, (len(pixel), 3))
    fused, numpy_sum = start.copy(), start.copy()
    add_unoccluded(fused, shadow, lit)
    add_unoccluded_numpy(numpy_sum, shadow, lit)
    assert not np.array_equal(fused, start)
    np.testing.assert_array_equal(fused, numpy_sum)


@pytest.mark.parametrize("fov, width, height", [(40.0, 96, 72), (90.0, 33, 101)])
def test_fused_camera_rays_equal_generate(fov, width, height):
    from vastray.render.camera import Camera

    camera = Camera(np.array([0.3, 1.2, 4.0]), np.array([0.0, -0.2, 0.1]),
                    np.array([0.0, 1.0, 0.0]), fov, width, height)
    n = width * height * 3
    pixel = (np.arange(n) // 3).astype(np.uint32)
    sample = (np.arange(n) % 3).astype(np.uint32)
    origin, direction = camera.generate(pixel, sample, 17)
    o32, d32 = camera.generate32(pixel, sample, 17)
    np.testing.assert_array_equal(o32, origin.astype(np.float32))
    np.testing.assert_array_equal(d32, direction.astype(np.float32))
    assert len(np.unique(d32, axis=0)) == n  # jittered: every ray differs
    o_far, d_far = camera.generate32(pixel, sample, 17, advance=2.5)
    np.testing.assert_array_equal(d_far, d32)
    np.testing.assert_array_equal(o_far, (origin + direction * 2.5).astype(np.float32))


def _enters_box_numpy(origin, direction, lo, hi):
    """The slab test in float64 with numpy (zero components handled apart): the oracle."""
    o, d = origin.astype(np.float64), direction.astype(np.float64)
    near, far = np.full(len(o), -np.inf), np.full(len(o), np.inf)
    inside = np.ones(len(o), bool)
    for a in range(3):
        flat = d[:, a] == 0
        inside &= ~flat | ((o[:, a] >= lo[a]) & (o[:, a] <= hi[a]))
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (lo[a] - o[:, a]) / d[:, a], (hi[a] - o[:, a]) / d[:, a]
        near = np.where(flat, near, np.maximum(near, np.minimum(t0, t1)))
        far = np.where(flat, far, np.minimum(far, np.maximum(t0, t1)))
    return inside & (near <= far) & (far >= 0)


@pytest.mark.parametrize("advance", [0.0, 1.5])
def test_camera_rays_in_box_are_generate32s_rays_that_enter_the_box(advance):
    from vastray.render.camera import Camera

    # looking along -z at the box's corner: some rays miss, some graze, none all aligned
    camera = Camera(np.array([0.0, 0.0, 6.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), 60.0,
                    64, 48)
    n = 64 * 48 * 2
    pixel, sample = (np.arange(n) // 2).astype(np.uint32), (np.arange(n) % 2).astype(np.uint32)
    lo, hi = np.array([-2.0, -1.0, -1.0]), np.array([0.5, 1.5, 1.0])
    o32, d32 = camera.generate32(pixel, sample, 9, advance)
    rows, o_in, d_in = camera.generate32_in_box(pixel, sample, 9, advance, lo, hi)
    expect = np.nonzero(_enters_box_numpy(o32, d32, lo, hi))[0]
    assert 0 < len(expect) < n  # the test sees both kinds
    np.testing.assert_array_equal(rows, expect)
    np.testing.assert_array_equal(o_in, o32[expect])
    np.testing.assert_array_equal(d_in, d32[expect])


def test_box_test_of_axis_aligned_rays_keeps_those_inside_a_slab():
    # zero direction components: a ray inside the slab (or on its face) keeps it, one outside
    # never enters; and a box behind the ray is missed
    lo, hi = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0])
    position = np.array([[0.5, 0.5, 5.0], [1.5, 0.5, 5.0], [0.5, 0.5, 5.0], [1.0, 1.0, 5.0],
                         [0.0, 0.0, 0.0], [-3.0, -1.0, 0.2]])
    direction = np.array([[0, 0, -1], [0, 0, -1], [0, 0, 1], [0, 0, -1], [1, 0, 0],
                          [0.6, -0.8, 0]])

    def enters(o, d):  # the kernel's slab test, as Python
        slabs = [kernels._slab.py_func(o[a], d[a], lo[a], hi[a]) for a in range(3)]
        return kernels._overlap.py_func(*(t for slab in slabs for t in slab))

    got = np.array([enters(p, d) for p, d in zip(position, direction, strict=True)])
    np.testing.assert_array_equal(got, [True, False, False, True, True, False])
    np.testing.assert_array_equal(got, _enters_box_numpy(position, direction, lo, hi))


def test_fused_camera_rays_find_row_and_column_of_any_uint32_pixel():
    # the kernel takes pixel // width and pixel % width through float64 ((pixel + 0.5) /
    # width, floored): exact up to 2^32 pixels, the keys' range, on a film that wide
    from vastray.render.camera import Camera

    camera = Camera(np.array([0.0, 0.0, 5.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), 50.0,
                    65535, 65537)
    rng = np.random.default_rng(3)
    pixel = np.concatenate([rng.integers(0, 65535 * 65537, 4000), [0, 65534, 65535, 65536,
                                                                   65535 * 65537 - 1]])
    pixel = pixel.astype(np.uint32)
    sample = rng.integers(0, 1 << 20, len(pixel)).astype(np.uint32)
    origin, direction = camera.generate(pixel, sample, 5)
    o32, d32 = camera.generate32(pixel, sample, 5)
    np.testing.assert_array_equal(d32, direction.astype(np.float32))
    np.testing.assert_array_equal(o32, origin.astype(np.float32))


def test_fused_unit_normals_equal_numpy():
    from vastray.render.tracer import ClosestHits

    rng = np.random.default_rng(8)
    best = ClosestHits.empty(5000, False)
    best.ng[:] = (rng.standard_normal((5000, 3)) * rng.uniform(1e-6, 1e6, (5000, 1)))
    best.ng[:10] = 0.0  # misses: zero normals stay zero
    rows = rng.permutation(5000)[:3000]
    got = best.hits(rows).normal
    n64 = best.ng[rows].astype(np.float64)
    length = np.linalg.norm(n64, axis=1, keepdims=True)
    np.testing.assert_array_equal(got, n64 / np.where(length > 0, length, 1.0))
    np.testing.assert_array_equal(best.hits().normal[:10], 0.0)


def test_fused_offer_equals_numpy_comparison_with_ties():
    from types import SimpleNamespace

    from vastray.render.tracer import ClosestHits

    rng = np.random.default_rng(12)
    n = 4000
    fused = ClosestHits.empty(n, False)
    ref = ClosestHits.empty(n, False)
    bvh = SimpleNamespace(objects=None,  # 100 triangles to rebuild hit points on
                          vertices=rng.uniform(-1, 1, (300, 3)).astype(np.float32),
                          indices=np.arange(300, dtype=np.uint32).reshape(100, 3))
    for domain in (5, 2, 7, 2 + 1):
        rows = np.sort(rng.choice(n, 2500, replace=False))
        k = len(rows)
        r = {"primID": np.where(rng.random(k) < 0.2, -1, rng.integers(0, 100, k)).astype(np.int32),
             "tfar": rng.choice(np.float32([1.0, 1.5, 2.0, 3.0]), k),  # many ties
             "Ng": rng.standard_normal((k, 3)).astype(np.float32),
             "u": np.zeros(k, np.float32), "v": np.zeros(k, np.float32)}
        got = fused.offer(rows, domain, bvh, r, None, (0.0, 1.0))
        # the numpy comparison the kernel replaced
        t_old = ref.t[rows]
        want = (r["primID"] >= 0) & ((r["tfar"] < t_old)
                                     | ((r["tfar"] == t_old) & (domain < ref.domain[rows])))
        won = rows[want]
        ref.t[won], ref.domain[won], ref.ng[won] = r["tfar"][want], domain, r["Ng"][want]
        np.testing.assert_array_equal(got, want)
        assert want.any() and not want.all()
    np.testing.assert_array_equal(fused.t, ref.t)
    np.testing.assert_array_equal(fused.domain, ref.domain)
    np.testing.assert_array_equal(fused.ng, ref.ng)
    assert len(np.unique(fused.domain)) >= 3  # ties went to lower domains


def film_add_by_bincount(film: Film, pixel, radiance, counted, sample) -> None:
    """``Film.add`` with ``np.bincount`` over the batch's pixel run (its former numpy path)."""
    lo, hi = int(pixel.min()), int(pixel.max()) + 1
    local = pixel - lo
    for c in range(3):
        film.sum[lo:hi, c] += np.bincount(local, weights=radiance[:, c], minlength=hi - lo)
    for b in range(film.batch.shape[1]):
        mine = sample % film.batch.shape[1] == b
        for c in range(3):
            film.batch[lo:hi, b, c] += np.bincount(local[mine], weights=radiance[mine, c],
                                                   minlength=hi - lo)
    film.count[lo:hi] += np.bincount(local if counted is None else local[counted],
                                     minlength=hi - lo)


@pytest.mark.parametrize("order", ["scattered", "ascending"])
@pytest.mark.parametrize("counting", ["all", "some"])
def test_fused_film_add_equals_bincount(counting, order):
    # Several batches over overlapping pixel runs, repeated pixels, values of every scale,
    # zeros of both signs and NaN: the sums, batch sums (per channel) and counts are numpy's
    # bit for bit, in any row order and in a render's (each pixel's rows one run, gaps
    # between: the kernel's run-by-run path)
    rng = np.random.default_rng(5)
    films = [Film(37, 11), Film(37, 11)]
    for _ in range(6):
        first = rng.integers(0, 300)
        pixel = rng.integers(first, min(first + 120, 37 * 11), 500)
        if order == "ascending":
            pixel.sort()
        radiance = rng.lognormal(0.0, 4.0, (500, 3)) * rng.choice([0.0, 1.0, -0.0], (500, 1))
        radiance[rng.random(500) < 0.01, 1] = np.nan
        counted = None if counting == "all" else rng.random(500) < 0.6
        sample = rng.integers(0, 20, 500)
        films[0].add(pixel, radiance, counted, sample)
        film_add_by_bincount(films[1], pixel, radiance, counted, sample)
    films[0].add(np.array([5, 5, 6], np.uint32), np.zeros((3, 3)))  # no sample: batch 0
    film_add_by_bincount(films[1], np.array([5, 5, 6]), np.zeros((3, 3)), None,
                         np.zeros(3, np.int64))
    for name in ("sum", "batch", "count"):
        got, want = getattr(films[0], name), getattr(films[1], name)
        assert got.any()
        assert got.tobytes() == want.tobytes(), name  # NaN where NaN, the sign of every zero


@pytest.mark.parametrize("s0, s1, first, stop", [
    (0, 16, 0, 65536), (3, 7, 12345, 99999), (0, 1, 5, 9), (4, 8, 7, 7),
    (16, 32, 131071, 196608)])
def test_path_keys_are_the_division_of_path_numbers(s0, s1, first, stop):
    # path_context numbers the paths of a pass by counting (kernels.path_keys): the keys must
    # be the pixel-major division of the path numbers, whatever the window and the first path
    from vastray.render.driver import path_context

    settings = RenderSettings(width=64, height=64, spp=s1).window(s0, s1)
    ctx = path_context(None, settings, first, stop, 1.0)
    ids = np.arange(first, stop, dtype=np.uint64)
    per_pixel = np.uint64(s1 - s0)
    assert ctx.pixel.dtype == ctx.sample.dtype == np.uint32
    np.testing.assert_array_equal(ctx.pixel, (ids // per_pixel).astype(np.uint32))
    np.testing.assert_array_equal(ctx.sample, (ids % per_pixel + np.uint64(s0)).astype(np.uint32))


def test_film_first_hits_take_sample_zero_rows_last_one_winning():
    # the depth and normal layers: rows of sample 0 only, a later row of a pixel over an
    # earlier one (numpy's fancy assignment), whatever the keys' integer type
    film, want = Film(4, 2), Film(4, 2)
    pixel = np.array([0, 3, 3, 5, 5, 7], np.uint32)
    sample = np.array([0, 0, 0, 1, 0, 2], np.uint32)
    t = np.arange(6, dtype=np.float32) + 1
    normal = np.arange(18, dtype=np.float32).reshape(6, 3)
    kernels.film_first_hits(film.depth, film.normal, pixel, sample, t, normal)
    zero = sample == 0
    want.depth[pixel[zero]] = t[zero]
    want.normal[pixel[zero]] = normal[zero]
    np.testing.assert_array_equal(film.depth, want.depth)
    np.testing.assert_array_equal(film.normal, want.normal)
    assert film.depth[3] == 3 and film.depth[5] == 5 and np.isinf(film.depth[7])


def test_film_refuses_pixels_outside_it_before_writing():
    # the kernels do not check bounds row by row: a key past the film (or a negative one,
    # wrapped to uint32) is refused whole, and nothing is written
    film = Film(4, 2)
    with pytest.raises(IndexError, match="outside the film"):
        film.add(np.array([1, 8]), np.ones((2, 3)))
    with pytest.raises(IndexError, match="outside the film"):
        film.add(np.array([1, -1]), np.ones((2, 3)))
    paths = PathResult.empty(2)
    with pytest.raises(IndexError, match="outside the film"):
        film.add_paths(np.array([9, 1], np.uint32), np.array([0, 0], np.uint32), paths)
    assert not film.sum.any() and not film.count.any()


def test_one_domain_hits_equal_offer_then_hits_bit_for_bit():
    # one pass from Embree's output to the final hits (issue 39) against the record it
    # replaced: misses, zero normals, slivers, degenerate and far-away triangles included
    from types import SimpleNamespace

    from vastray.render.tracer import ClosestHits, one_domain_hits

    rng = np.random.default_rng(39)
    n, tris = 20_000, 400
    vertices = (rng.standard_normal((3 * tris, 3))
                * rng.choice([1e-3, 1.0, 1e4], (3 * tris, 1))).astype(np.float32)
    vertices[3:6] = vertices[0]  # a degenerate triangle
    vertices[7] = vertices[6] + np.float32([1e-4, 0, 0])  # a sliver
    vertices[8] = vertices[6] + np.float32([1.0, 1e-6, 0])
    for objects, color_source in ((None, None), (rng.integers(0, 3, tris), "scalars")):
        bvh = SimpleNamespace(objects=objects, vertices=vertices,
                              indices=np.arange(3 * tris, dtype=np.uint32).reshape(tris, 3),
                              scalars=rng.random(3 * tris).astype(np.float32))
        u = rng.random(n).astype(np.float32)
        r = {"primID": np.where(rng.random(n) < 0.3, -1,
                                rng.integers(0, tris, n)).astype(np.int32),
             "tfar": rng.uniform(0, 1e3, n).astype(np.float32),
             "Ng": (rng.standard_normal((n, 3)) * rng.uniform(1e-6, 1e6, (n, 1))
                    ).astype(np.float32),
             "u": u, "v": (rng.random(n) * (1 - u)).astype(np.float32)}
        r["Ng"][:50] = 0.0
        r["tfar"][r["primID"] < 0] = np.inf
        got = one_domain_hits(bvh, r, color_source, (0.0, 1.0))
        best = ClosestHits.empty(n, color_source is not None)
        best.offer(np.arange(n), 0, bvh, r, color_source, (0.0, 1.0))
        want = best.hits()
        for name in ("t", "normal", "material", "color", "point", "error"):
            if getattr(want, name) is None:
                assert getattr(got, name) is None
            else:
                np.testing.assert_array_equal(getattr(got, name), getattr(want, name),
                                              err_msg=name)
        assert (~got.hit).sum() > 1000 and np.isfinite(got.error).all()


def test_first_hits_equal_the_numpy_layers():
    # record_camera_hits' kernel against t + start and tracer.facing, rays grazing the
    # surface (dot product about 0) included
    from vastray.render.tracer import facing

    rng = np.random.default_rng(40)
    k, paths = 30_000, 50_000
    normal = rng.standard_normal((k, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal[:20] = 0.0
    dirs = rng.standard_normal((k, 3)).astype(np.float32)
    # grazing: directions made perpendicular to the normal in float64, then rounded
    grazing = slice(100, 10_000)
    d = dirs[grazing].astype(np.float64)
    d -= np.einsum("ij,ij->i", d, normal[grazing])[:, None] * normal[grazing]
    dirs[grazing] = d.astype(np.float32)
    t = np.where(rng.random(k) < 0.2, np.inf, rng.uniform(0, 1e4, k))
    path = rng.permutation(paths)[:k].astype(np.int64)
    start = 12.375
    first_t, first_normal = np.full(paths, np.inf, np.float32), np.zeros((paths, 3), np.float32)
    kernels.first_hits(path, t, normal, dirs, start, first_t, first_normal)
    want_t, want_n = first_t.copy(), first_normal.copy()
    want_t[:], want_n[:] = np.inf, 0.0
    want_t[path] = t + start
    want_n[path] = facing(normal, dirs.astype(np.float64))
    np.testing.assert_array_equal(first_t, want_t)
    np.testing.assert_array_equal(first_normal, want_n)
    flipped = np.einsum("ij,ij->i", normal, dirs.astype(np.float64)) > 0
    assert flipped[grazing].any() and (~flipped[grazing]).any()


@pytest.mark.parametrize("lut", [None, "table"])
def test_scalar_colors_equal_the_numpy_colormap_and_nan_is_grey(lut):
    # the compiled scalar colouring (issue 39) against the numpy interpolation and colormap
    # it replaced, scalars beyond the range, infinite and NaN ones included
    from types import SimpleNamespace

    from vastray.render.materials import NAN_COLOR, colormap
    from vastray.render.tracer import vertex_color

    rng = np.random.default_rng(41)
    k, tris = 50_000, 500
    scalars = rng.uniform(-2.0, 3.0, 3 * tris).astype(np.float32)
    scalars[:6] = [np.nan, 1.0, 2.0, np.inf, -np.inf, 0.5]  # triangles 0 and 1
    bvh = SimpleNamespace(indices=rng.integers(0, 3 * tris, (tris, 3)).astype(np.uint32),
                          scalars=scalars)
    bvh.indices[0], bvh.indices[1] = [0, 1, 2], [3, 4, 5]
    prim = rng.integers(0, tris, k).astype(np.int32)
    u = rng.random(k).astype(np.float32)
    v = (rng.random(k) * (1 - u)).astype(np.float32)
    table = None if lut is None else rng.random((7, 3))
    got = vertex_color(bvh, prim, u, v, "scalars", (0.0, 1.5, table))
    tri = bvh.indices[prim]
    w = np.stack([1.0 - u - v, u, v], axis=1).astype(np.float64)
    want = colormap(np.einsum("kj,kj->k", w, bvh.scalars[tri].astype(np.float64)), 0.0, 1.5,
                    table)
    np.testing.assert_array_equal(got, want)
    nan = prim == 0
    assert nan.any() and (got[nan] == NAN_COLOR).all()
    assert np.isfinite(got).all() and ((got >= 0) & (got <= 1)).all()


def test_add_to_rows_is_numpys_masked_add_bit_for_bit():
    rng = np.random.default_rng(3)
    radiance = rng.normal(size=(5000, 3)) * 10.0 ** rng.integers(-30, 30, size=(5000, 1))
    radiance[:7] = [[np.nan, -0.0, np.inf], [-np.inf, 0.0, 1e308], [-0.0, -0.0, -0.0],
                    [1.0, 2.0, 3.0], [np.nan, np.nan, np.nan], [5e-324, -5e-324, 0.0],
                    [1e308, 1e308, 1e308]]
    rows = rng.random(5000) < 0.6
    rows[:7] = True
    value = np.array([0.25, 1e308, -0.0])
    expected = radiance.copy()
    with np.errstate(over="ignore", invalid="ignore"):  # inf + -inf, 1e308 + 1e308
        expected[rows] += value
    kernels.add_to_rows(radiance, rows, value)
    assert radiance.tobytes() == expected.tobytes()  # the rows left out untouched too
