"""Numerical stability: spawned rays never re-hit their own surface, at any scale or offset."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vastray.render.driver import render
from vastray.render.tracer import DomainTracer
from vastray.scene.cache import DomainCache

from oracles import cosine_hemisphere, spawn
from scenes import camera_config, mesh_arrays, settings, write_store


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1.0, 1e3, 1e6])
@pytest.mark.parametrize("offset", [0.0, 1e4])
def test_convex_sphere_ao_is_one_at_every_scale(tmp_path, scale, offset):
    # From outside a convex surface nothing can occlude a hemisphere ray except the surface
    # itself, so any self-intersection shows up as AO < 1.
    sphere = trimesh.creation.icosphere(subdivisions=4)
    center = np.full(3, offset * scale)
    sphere.apply_scale(scale)
    sphere.apply_translation(center)
    store = write_store(tmp_path / "s", mesh_arrays(sphere), grid=(2, 2, 2))
    cfg = camera_config(center + np.array([0.0, 0.0, 3.0]) * scale, center, fov=45)
    result = render(store, cfg, settings(integrator="ao", ao_distance=10 * scale,
                                         shadow_samples=32, width=32, height=32, spp=1),
                    progress=False)
    image = result.film.image()
    hit = np.isfinite(result.film.depth_image())
    assert hit.sum() > 300
    assert np.all(image[hit] == 1.0)


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6])
def test_spawned_rays_from_hit_points_never_rehit(tmp_path, scale):
    # Hit a finely tessellated plane at grazing and steep angles, then leave it in every
    # direction of the upper hemisphere: no spawned ray may report a hit.
    plane = trimesh.creation.box(extents=[4.0, 0.5, 4.0])
    plane.apply_translation([0, -0.25, 0])
    plane = plane.subdivide().subdivide().subdivide()
    plane.apply_scale(scale)
    store = write_store(tmp_path / "p", mesh_arrays(plane))
    tracer = DomainTracer(store, DomainCache(store, 1), threads=1)
    rng = np.random.default_rng(1)
    n = 4000
    origins = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(0.01, 3, n),
                               rng.uniform(-1, 1, n)]) * scale
    targets = np.column_stack([rng.uniform(-1.5, 1.5, n), np.zeros(n), rng.uniform(-1.5, 1.5, n)])
    dirs = targets * scale - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hits = tracer.intersect(origins.astype(np.float32), dirs.astype(np.float32))
    assert hits.hit.all()
    p = origins.astype(np.float32).astype(np.float64) + dirs.astype(np.float32) * hits.t[:, None]
    normal = hits.normal * np.sign(-np.einsum("ij,ij->i", hits.normal, dirs))[:, None]
    new_origin = spawn(p, normal, hits.t)
    for k in range(4):
        u, v = rng.random(n).astype(np.float32), rng.random(n).astype(np.float32)
        if k == 0:
            u[:] = 0.999999  # nearly tangent directions: the hardest case
        out = cosine_hemisphere(normal, u, v)
        again = tracer.intersect(new_origin.astype(np.float32), out.astype(np.float32))
        assert not again.hit.any(), f"{again.hit.sum()} rays re-hit their surface"


def test_a_crashed_writers_temporary_file_is_removed_by_the_next_write(tmp_path):
    # A render killed mid-write (SIGKILL, a native crash) cannot clean up; its hidden
    # temporary file names its process, and the next write of that output removes it once the
    # process is gone. Another running writer's file and other files stay.
    import subprocess
    import sys

    from vastray.render.imageio import atomic_path

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    dead_pid = int(gone.stdout)
    orphan = tmp_path / f".a_0000.exr.{dead_pid}.780tnwz9.exr"
    live = tmp_path / f".a_0000.exr.{os.getpid()}.abcdefgh.exr"
    other = tmp_path / ".a_0000.exr.notours.exr"
    for f in (orphan, live, other):
        f.write_bytes(b"partial")
    with atomic_path(tmp_path / "a_0000.exr") as tmp:
        Path(tmp).write_bytes(b"image")
    assert (tmp_path / "a_0000.exr").read_bytes() == b"image"
    assert not orphan.exists()
    assert live.exists() and other.exists()
