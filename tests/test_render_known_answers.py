"""Known answers: the furnace sphere, ambient occlusion limits, point-light irradiance falloff."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from vastray.render.camera import Camera
from vastray.render.driver import render
from vastray.render.lights import PointLight
from vastray.render.materials import Material

from scenes import camera_config, mesh_arrays, settings, write_store


@pytest.mark.parametrize("shadow_samples", [1, 4])
def test_furnace_sphere_radiance_is_one(tmp_path, shadow_samples):
    # Inward-facing unit sphere, albedo 0.5, point light of intensity pi at the centre:
    # every bounce adds half the previous one, so L = sum 0.5^k -> 1 (pbrt-v4's furnace test).
    sphere = trimesh.creation.icosphere(subdivisions=5)
    store = write_store(tmp_path / "s", mesh_arrays(sphere, flip=True), grid=(2, 2, 2))
    cfg = camera_config([0, 0, 0.2], [0, 0, -1], fov=70,
                        lights=[PointLight(np.zeros(3), np.full(3, np.pi))],
                        default_material=Material(np.full(3, 0.5), np.zeros(3), 1.0))
    result = render(store, cfg, settings(width=24, height=24, spp=2, bounces=12,
                                         shadow_samples=shadow_samples), progress=False)
    image = result.film.image()
    assert abs(image.mean() - 1.0) < 0.025
    assert np.all(np.abs(image - 1.0) < 0.05)


def _plane(size=10.0, y=0.0):
    plane = trimesh.creation.box(extents=[size, 0.01 * size, size])
    plane.apply_translation([0, y - 0.005 * size, 0])
    return plane


def test_ao_of_open_plane_is_one(tmp_path):
    store = write_store(tmp_path / "p", mesh_arrays(_plane()), grid=(2, 1, 2))
    cfg = camera_config([0.3, 2.0, 0.2], [0, 0, 0], fov=40, up=(0, 0, 1))
    result = render(store, cfg, settings(integrator="ao", ao_distance=1.0, shadow_samples=16),
                    progress=False)
    assert np.all(result.film.image() == 1.0)


def test_ao_inside_closed_box_is_zero(tmp_path):
    box = trimesh.creation.box(extents=[1.0, 1.0, 1.0])
    store = write_store(tmp_path / "b", mesh_arrays(box, flip=True))
    cfg = camera_config([0.1, 0.05, 0.0], [0, 0, -1], fov=60)
    result = render(store, cfg, settings(integrator="ao", ao_distance=5.0, shadow_samples=16),
                    progress=False)
    assert np.all(result.film.image() == 0.0)


def test_diffuse_plane_matches_point_light_falloff(tmp_path):
    # Radiance of a Lambertian plane lit by a point light: (rho / pi) * I * cos(theta) / r^2.
    store = write_store(tmp_path / "p", mesh_arrays(_plane()), grid=(2, 1, 2))
    light = np.array([0.7, 1.5, -0.4])
    rho, intensity = 0.6, 5.0
    cfg = camera_config([0.0, 4.0, 3.0], [0, 0, 0], fov=50,
                        lights=[PointLight(light, np.full(3, intensity))],
                        default_material=Material(np.full(3, rho), np.zeros(3), 1.0))
    st = settings(width=40, height=30, spp=1, bounces=0)
    result = render(store, cfg, st, progress=False)
    camera: Camera = result.camera
    pixel = np.arange(st.width * st.height, dtype=np.uint32)
    origins, dirs = camera.generate(pixel, np.zeros_like(pixel), st.seed)
    depth = result.film.depth.astype(np.float64)
    assert np.isfinite(depth).all()
    points = origins + dirs * depth[:, None]
    to_light = light - points
    r2 = np.einsum("ij,ij->i", to_light, to_light)
    cos = to_light[:, 1] / np.sqrt(r2)
    expected = rho / np.pi * intensity * cos / r2
    got = result.film.image().reshape(-1, 3)[:, 0]
    np.testing.assert_allclose(got, expected, rtol=2e-4)
