"""Scenes too small or too large for float32 ray tracing are refused, by ``vastray render``
(and the Python API) and by ``vastray partition``, on one line naming the store or mesh file;
scenes at the bounds still render as at unit scale (issue 23, part 5; ``scene/extent.py``)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh

import vastray
from vastray.render import driver
from vastray.scene.errors import InputError
from vastray.scene.extent import MAX_EXTENT, MIN_EXTENT

from scenes import compare, far_config, far_settings, far_store

#: The far scene's extent at scale 1 (its largest side).
FAR_EXTENT = 2.6


def _vastray(*args, cwd):
    return subprocess.run([sys.executable, "-m", "vastray.cli", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def _image(store, scale: float) -> np.ndarray:
    return driver.render(store, far_config(scale=scale), far_settings(), threads=1,
                         progress=False).film.image()


@pytest.fixture(scope="module")
def unit(tmp_path_factory):
    """The far scene at unit scale: its image and the seed-to-seed noise."""
    root = tmp_path_factory.mktemp("extent")
    base = far_store(root / "unit.store", 0.0)
    reference = _image(base, 1.0)
    noise = driver.render(base, far_config(), far_settings(seed=2), threads=1, progress=False)
    return {"root": root, "reference": reference,
            "noise": compare(noise.film.image(), reference)}


@pytest.mark.parametrize("extent", [MIN_EXTENT, MAX_EXTENT])
def test_a_scene_at_either_bound_renders_as_at_unit_scale(unit, extent):
    scale = extent / FAR_EXTENT
    store = far_store(unit["root"] / f"{extent:g}.store", 0.0, scale=scale)
    assert np.max(store.bounds[1] - store.bounds[0]) == pytest.approx(extent, rel=0.01)
    c = compare(_image(store, scale), unit["reference"])
    assert c["nonfinite"] == 0
    # far inside the seed-to-seed noise (tests/test_numerics.py allows twice it): exact at
    # 1e12, off by 1e-5 in relative MSE at 1e-7, where 1e-8 is 0.3 % off in the mean
    assert c["rel_mse_global"] < 0.01 * unit["noise"]["rel_mse_global"], c
    assert abs(c["mean"]) < 0.25 * abs(unit["noise"]["mean"]), c


@pytest.mark.parametrize("scale, says", [(1e-18, "is below the 1e-07 that"),
                                         (1e18, "is above the 1e+12 that")])
def test_render_refuses_a_store_out_of_float32s_reach(unit, tmp_path, scale, says):
    store = far_store(tmp_path / "s.store", 0.0, scale=scale)
    out = _vastray("render", store.path, "-o", "a.exr", "--png", "a.png", "--width", "16",
                   "--height", "12", "--spp", "1", cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and str(store.path) in lines[0], out.stderr
    assert says in lines[0] and f"multiply its coordinates by {1 / scale:g}" in lines[0]
    assert "partition it again" in lines[0]
    assert not (tmp_path / "a.exr").exists() and not (tmp_path / "a.png").exists()
    with pytest.raises(InputError, match="scene extent"):  # the Python API refuses it too
        vastray.render(store, width=16, height=12, spp=1)


@pytest.mark.parametrize("scale", [1e-6, 1e6])
def test_render_takes_stores_scaled_by_1e6_either_way(tmp_path, scale):
    store = far_store(tmp_path / "s.store", 0.0, scale=scale)
    out = _vastray("render", store.path, "-o", "a.exr", "--width", "16", "--height", "12",
                   "--spp", "1", "--quiet", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "a.exr").stat().st_size > 0


@pytest.mark.parametrize("scale", [1e-18, 1e18])
def test_partition_refuses_a_mesh_out_of_float32s_reach(tmp_path, scale):
    ball = trimesh.creation.icosphere(subdivisions=2)
    ball.apply_scale(scale)
    ball.export(tmp_path / "ball.ply")
    out = _vastray("partition", "ball.ply", "-o", "b.store", cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vastray partition: error: ball.ply: "
                                                   "scene extent 2e")
    assert "partition it" in lines[0]
    assert not (tmp_path / "b.store").exists()


def test_partition_refuses_meshes_that_fit_alone_but_lie_too_far_apart(tmp_path):
    for name, where in (("near.ply", 0.0), ("far.ply", 1e13)):
        ball = trimesh.creation.icosphere(subdivisions=2)
        ball.apply_translation([where, 0.0, 0.0])
        ball.export(tmp_path / name)
    out = _vastray("partition", "near.ply", "far.ply", "-o", "b.store", cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    assert "b.store: scene extent 1e+13 is above" in out.stderr
    assert "partition them" in out.stderr and not (tmp_path / "b.store").exists()
