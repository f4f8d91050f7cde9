"""Camera rays that miss the scene's box are never generated nor queried
(``integrators.seen_camera_rays``): the image stays bit for bit the same, and no ray left out
could have hit anything."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.render import driver, integrators
from vastray.render.driver import render
from vastray.render.integrators import camera_rays, seen_camera_rays
from vastray.render.tracer import DomainTracer
from vastray.scene.cache import DomainCache
from vastray.scene.store import DomainArrays

from scenes import bumpy_config, bumpy_scene, camera_config, settings, write_store


@pytest.fixture(scope="module")
def bumpy(tmp_path_factory):
    return write_store(tmp_path_factory.mktemp("escape") / "bumpy", bumpy_scene())


@pytest.fixture(scope="module")
def square(tmp_path_factory):
    """A flat unit square at z = 0: its box has no depth, and its edges are the box's."""
    vertices = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    indices = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
    return write_store(tmp_path_factory.mktemp("escape") / "square",
                       DomainArrays(vertices, indices))


def _every_camera_ray(monkeypatch):
    """Make ``trace_paths`` trace every camera ray, as before rays were left out."""
    monkeypatch.setattr(integrators, "seen_camera_rays", camera_rays)


@pytest.mark.parametrize("integrator", ["pt", "ao"])
def test_leaving_out_escaping_camera_rays_changes_no_bit(bumpy, monkeypatch, integrator):
    # point, quad and ambient lights: escaped rays see the sky, none sees the quad
    config = bumpy_config()
    config.camera["position"] = np.array([6.0, 4.4, 9.0])  # the scene in the middle
    run = settings(width=64, height=48, spp=3, integrator=integrator)
    culled = render(bumpy, config, run, threads=2, progress=False)
    escaped = culled.counters["camera_rays_escaped"]
    assert 0 < escaped < 64 * 48 * 3 == escaped + culled.counters["rays"]["camera"]
    _every_camera_ray(monkeypatch)
    whole = render(bumpy, config, run, threads=2, progress=False)
    assert whole.counters["camera_rays_escaped"] == 0
    for layer in ("image", "depth_image", "normal_image", "variance_of_mean"):
        a, b = getattr(culled.film, layer)(), getattr(whole.film, layer)()
        assert a.tobytes() == b.tobytes(), layer
    assert whole.counters["rays"]["camera"] == 64 * 48 * 3


@pytest.mark.parametrize("position, fov", [([0.0, 0.0, 3.0], 60.0),  # square fills the middle
                                           ([2.5, 0.3, 0.4], 90.0),  # low, grazing its plane
                                           ([2.0, 1.0, 1e-3], 120.0)])  # just above its plane
def test_no_escaped_camera_ray_hits_anything(square, position, fov):
    config = camera_config(position=position, look_at=[0.0, 0.0, 0.0], fov=fov,
                           up=[0.0, 0.0, 1.0] if position[2] < 0.01 else [0.0, 1.0, 0.0])
    run = settings(width=96, height=96, spp=8, integrator="ao")
    camera = driver.store_camera(config, square, run.width, run.height)
    shading = driver.with_camera_clip(driver.shading_inputs(square, config, "ao")[0], square,
                                      camera)
    ctx = driver.path_context(shading, run, 0, run.paths, 1.0)
    kept = seen_camera_rays(camera, ctx)
    escaped = np.setdiff1d(np.arange(run.paths), kept.path)
    every = camera_rays(camera, ctx)
    tracer = DomainTracer(square, DomainCache(square, 1), threads=1)
    try:
        hit = tracer.intersect(every.origin, every.direction, kind="camera").hit
    finally:
        tracer.close()
    assert len(escaped) > 0 and hit.any()
    assert not hit[escaped].any()  # nothing left out could have hit
    assert len(kept) + len(escaped) == len(every)
    np.testing.assert_array_equal(kept.origin, every.origin[kept.path])
    np.testing.assert_array_equal(kept.direction, every.direction[kept.path])
