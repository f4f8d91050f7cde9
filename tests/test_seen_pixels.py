"""The pixels whose camera rays can meet something (``render.seen_pixels``): no pixel a hit or a
quad light is seen through is left out, whatever the camera, and renders that leave the others
out are bit for bit those that trace every camera ray."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.render import driver, integrators
from vastray.render.camera import Camera
from vastray.render.driver import render
from vastray.render.integrators import camera_rays
from vastray.render.kernels import camera_rays_in_box
from vastray.render.lights import AmbientLight, PointLight, QuadLight
from vastray.render.seen_pixels import occupied_boxes, pixel_cover
from vastray.render.tracer import DomainTracer
from vastray.scene.cache import DomainCache

from scenes import bumpy_scene, camera_config, settings, write_store


@pytest.fixture(scope="module")
def bumpy(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("seen") / "bumpy", bumpy_scene())


@pytest.fixture(scope="module")
def bumpy_domains(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("seen") / "bumpy8", bumpy_scene(), grid=(2, 2, 2))


def _cover_and_hits(store, config, run):
    """(the cover of ``store`` for ``config``'s camera or None, (paths,) the pixel of each
    path, (paths,) whether its camera ray hits anything: every camera ray traced)."""
    camera = driver.store_camera(config, store, run.width, run.height)
    shading = driver.shading_inputs(store, config, run.integrator)[0]
    shading = driver.with_seen_pixels(driver.with_camera_clip(shading, store, camera), store,
                                      camera)
    ctx = driver.path_context(shading, run, 0, run.paths, 1.0)
    every = camera_rays(camera, ctx)
    tracer = DomainTracer(store, DomainCache(store, len(store.domains)), threads=1)
    try:
        hit = tracer.intersect(every.origin, every.direction, kind="camera").hit
    finally:
        tracer.close()
    return shading.seen_pixels, ctx.pixel, hit


# the scene in the middle; far with a narrow view (a pixel is a sliver of a cell); near and
# looking past the ground's edge; grazing the ground's plane; from below, the ground filling
# the view (whether the cover leaves pixels out: the last)
CAMERAS = [([3.0, 2.2, 4.5], [0.0, -0.5, 0.0], 45.0, True),
           ([40.0, 30.0, 55.0], [0.3, -0.2, 0.1], 2.0, True),
           ([4.0, 0.5, 3.0], [-1.0, -0.6, -2.0], 70.0, True),
           ([7.0, -1.25, 0.3], [0.0, -1.25, 0.0], 60.0, True),
           ([0.5, -4.0, 0.7], [0.0, 0.0, 0.0], 50.0, False)]


@pytest.mark.parametrize("position, look_at, fov, leaves_out", CAMERAS)
@pytest.mark.parametrize("domains", [1, 8])
def test_no_pixel_a_camera_ray_hits_through_is_left_out(bumpy, bumpy_domains, position,
                                                        look_at, fov, leaves_out, domains):
    store = bumpy if domains == 1 else bumpy_domains
    assert all(d.occupancy is not None and not d.occupancy.all() for d in store.domains
               if d.n_triangles)  # masks with empty cells: the cover is more than boxes
    run = settings(width=80, height=60, spp=4, integrator="ao")
    seen, pixel, hit = _cover_and_hits(store, camera_config(position, look_at, fov), run)
    assert seen is not None and hit.any()
    assert seen[pixel[hit]].all()  # every hit's pixel is kept
    assert (not seen.all()) == leaves_out


def test_cover_leaves_out_pixels_inside_the_box(bumpy):
    # the box of the scene covers most of the image; its occupied cells, a good part less
    config = camera_config([3.0, 2.2, 4.5], [0.0, -0.5, 0.0], 45.0)
    run = settings(width=80, height=60, spp=1, integrator="ao")
    camera = driver.store_camera(config, bumpy, run.width, run.height)
    shading = driver.with_camera_clip(driver.shading_inputs(bumpy, config, "ao")[0], bumpy,
                                      camera)
    ctx = driver.path_context(shading, run, 0, run.paths, 1.0)
    in_box = len(integrators.seen_camera_rays(camera, ctx))
    covered = driver.with_seen_pixels(shading, bumpy, camera)
    ctx = driver.path_context(covered, run, 0, run.paths, 1.0)
    in_cover = len(integrators.seen_camera_rays(camera, ctx))
    assert 0 < in_cover < 0.9 * in_box


def test_a_box_at_the_cameras_plane_leaves_no_pixel_out():
    camera = Camera(np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]), 60.0,
                    32, 24)
    ahead = (np.array([[-1.0, -1.0, -5.0]]), np.array([[1.0, 1.0, -4.0]]))
    assert pixel_cover(camera, *ahead, 1e-6) is not None
    around = (np.array([[-1.0, -1.0, -5.0]]), np.array([[1.0, 1.0, 0.5]]))  # holds the eye
    assert pixel_cover(camera, *around, 1e-6) is None
    behind = (np.array([[-1.0, -1.0, 2.0]]), np.array([[1.0, 1.0, 3.0]]))
    assert pixel_cover(camera, *behind, 1e-6) is None  # (the box test leaves those out)
    off_image = (np.array([[50.0, -1.0, -5.0]]), np.array([[51.0, 1.0, -4.0]]))
    cover = pixel_cover(camera, *off_image, 1e-6)
    assert cover is not None and not cover.any()


def test_a_cell_one_pixel_wide_keeps_its_pixel_and_its_neighbours():
    camera = Camera(np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]), 90.0,
                    100, 100)
    # the image plane at depth 1 spans [-1, 1]: pixel (row 50, column 75) is x 0.50..0.52,
    # y -0.02..0; a tiny box inside it
    lo, hi = np.array([[0.505, -0.015, -1.0]]), np.array([[0.506, -0.014, -1.0]])
    cover = pixel_cover(camera, lo, hi, 0.0).reshape(100, 100)
    assert cover[49:52, 74:77].all() and cover.sum() == 9


def test_empty_domains_have_no_cells(tmp_path):
    from vastray.scene.store import DomainArrays, Store, StoreWriter

    mesh = bumpy_scene()
    with StoreWriter(tmp_path / "s") as writer:
        writer.add_domain(mesh)
        writer.add_domain(DomainArrays(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)))
    lo, hi = occupied_boxes(Store(tmp_path / "s"))
    assert len(lo) == int(Store(tmp_path / "s").domains[0].occupancy.sum())


def test_a_quad_light_in_view_keeps_its_pixels(bumpy, monkeypatch):
    # a quad light off to the side of the scene, facing the camera, where no cell is: the
    # camera sees it directly through pixels the geometry's cover alone would leave out
    quad = QuadLight(np.array([3.5, 2.5, 0.0]), np.array([0.0, 0.0, 1.2]),
                     np.array([0.0, 1.0, 0.0]), np.full(3, 5.0))
    assert quad.area_normal @ (np.array([3.0, 2.2, 4.5]) - quad.corner) > 0  # it faces us
    config = camera_config([3.0, 2.2, 4.5], [1.0, 0.0, 0.0], 60.0,
                           lights=[PointLight(np.array([2.0, 3.0, 1.0]), np.full(3, 12.0)),
                                   quad, AmbientLight(np.full(3, 0.2))])
    run = settings(width=64, height=48, spp=2, integrator="pt")
    camera = driver.store_camera(config, bumpy, run.width, run.height)
    shading = driver.with_camera_clip(driver.shading_inputs(bumpy, config, "pt")[0], bumpy,
                                      camera)
    seen = driver.with_seen_pixels(shading, bumpy, camera).seen_pixels
    ctx = driver.path_context(shading, run, 0, run.paths, 1.0)
    every = camera_rays(camera, ctx)
    sees_quad = np.isfinite(quad.intersect(every.origin.astype(np.float64),
                                           every.direction.astype(np.float64)))
    assert sees_quad.any() and seen[ctx.pixel[sees_quad]].all()
    covered = render(bumpy, config, run, threads=2, progress=False)
    monkeypatch.setattr(integrators, "seen_camera_rays", camera_rays)
    whole = render(bumpy, config, run, threads=2, progress=False)
    for layer in ("image", "depth_image", "normal_image"):
        assert getattr(covered.film, layer)().tobytes() == getattr(whole.film, layer)().tobytes()
    assert covered.counters["camera_rays_escaped"] > 0


def test_the_kernel_refuses_a_cover_of_another_size_or_a_pixel_off_it():
    camera = Camera(np.array([0.0, 0.0, 5.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), 50.0,
                    8, 6)
    inputs = camera._kernel_inputs(np.array([3, 47], np.uint32), np.zeros(2, np.uint32), 1, 0.0)
    lo, hi = np.full(3, -1.0), np.full(3, 1.0)
    rows, origin, direction = np.empty(2, np.int64), np.empty((2, 3), np.float32), np.empty(
        (2, 3), np.float32)
    with pytest.raises(IndexError):
        camera_rays_in_box(*inputs, lo, hi, np.ones(47, np.bool_), rows, origin, direction)
    off = camera._kernel_inputs(np.array([48], np.uint32), np.zeros(1, np.uint32), 1, 0.0)
    with pytest.raises(IndexError):
        camera_rays_in_box(*off, lo, hi, np.ones(48, np.bool_), rows, origin, direction)
    assert camera_rays_in_box(*inputs, lo, hi, np.ones(48, np.bool_), rows, origin,
                              direction) == camera_rays_in_box(*inputs, lo, hi,
                                                               np.zeros(0, np.bool_), rows,
                                                               origin, direction)


@pytest.mark.parametrize("share", [None, (1, 2)])
def test_a_schedule_queues_only_the_seen_camera_rays_of_its_share(bumpy_domains, share):
    """``launched_camera_rays``, as every node's schedule queues a tile's camera rays: of its
    share of the paths (every other one on rank 1 of 2), the rays through covered pixels,
    bit for bit ``camera_rays``' rays, every one that enters an occupied cell among them; the
    share's other paths see the sky at once, and paths outside the share are not touched."""
    from vastray.actors.render_setup import RenderSetup
    from vastray.render.integrators import PathResult, launched_camera_rays

    config = camera_config([3.0, 2.2, 4.5], [0.0, -0.5, 0.0], 45.0,
                           lights=[PointLight(np.array([2.0, 3.0, 1.0]), np.full(3, 12.0)),
                                   AmbientLight(np.full(3, 0.25))])
    run = settings(width=64, height=48, spp=2, integrator="pt")
    setup = RenderSetup.of(bumpy_domains, config, run)
    assert setup.shading.seen_pixels is not None and not setup.shading.seen_pixels.all()
    ctx = driver.path_context(setup.shading, run, 0, run.paths, setup.ao_distance)
    n = len(ctx.pixel)
    rows = None if share is None else np.nonzero(np.arange(n) % share[1] == share[0])[0]
    mine = np.ones(n, bool) if rows is None else np.isin(np.arange(n), rows)
    result = PathResult.empty(n)
    rays = launched_camera_rays(setup.camera, ctx, result, rows)

    every = camera_rays(setup.camera, ctx)
    assert mine[rays.path].all() and np.all(np.diff(rays.path) > 0)
    assert 0 < len(rays) < 0.8 * mine.sum()
    assert rays.origin.tobytes() == every.origin[rays.path].tobytes()
    assert rays.direction.tobytes() == every.direction[rays.path].tobytes()
    ray, _, _, _ = setup.geometry.crossings(every.origin, every.direction,
                                            np.full(n, np.inf, np.float32))
    enters = np.zeros(n, bool)
    enters[ray] = True
    assert enters[mine].any() and np.isin(np.nonzero(enters & mine)[0], rays.path).all()
    launched = np.zeros(n, bool)
    launched[rays.path] = True
    sky = integrators.escaped_emission(ctx)
    assert (result.radiance[mine & ~launched] == sky).all()
    assert not result.radiance[launched].any() and not result.radiance[~mine].any()
    assert np.isinf(result.first_t).all()  # a miss's layers, for every path so far
