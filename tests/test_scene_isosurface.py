"""Brick-by-brick marching cubes equals whole-volume marching cubes and has no cracks."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from skimage.measure import marching_cubes

from vastray.scene import meshops
from vastray.scene.isosurface import (
    axis_bricks,
    brick_grid,
    iter_brick_triangles,
    iter_field_triangles,
    march_brick,
)
from vastray.scene.store import DomainArrays


def sphere_volume(shape=(37, 41, 29), noise=0.0, seed=0) -> np.ndarray:
    axes = [np.linspace(-1, 1, n, dtype=np.float32) for n in shape]
    r = np.sqrt(axes[0][:, None, None] ** 2 + axes[1][None, :, None] ** 2
                + axes[2][None, None, :] ** 2)
    if noise:
        r += noise * np.random.default_rng(seed).standard_normal(shape).astype(np.float32)
    return r


def welded(pieces) -> DomainArrays:
    return meshops.weld(meshops.concat([DomainArrays(v, f) for _, v, f in pieces]))


@pytest.mark.parametrize("n, brick", [(2, 64), (10, 3), (65, 64), (66, 64), (100, 7)])
def test_axis_bricks_cover_every_cell_once(n, brick):
    ranges = axis_bricks(n, brick)
    assert ranges[0][0] == 0 and ranges[-1][1] == n
    for (_s0, e0), (s1, _) in zip(ranges, ranges[1:], strict=False):
        assert s1 == e0 - 1  # one shared voxel
    cells = np.concatenate([np.arange(s, e - 1) for s, e in ranges])
    np.testing.assert_array_equal(cells, np.arange(n - 1))
    assert max(e - s - 1 for s, e in ranges) <= brick


def test_axis_bricks_respect_cuts():
    ranges = axis_bricks(64, 10, cuts=[0, 21, 42, 63])
    starts = {s for s, _ in ranges}
    assert {0, 21, 42} <= starts
    with pytest.raises(ValueError):
        axis_bricks(64, 10, cuts=[0, 30, 30, 63])


@pytest.mark.parametrize("brick", [4, 9, 16, 64])
def test_same_triangles_as_whole_volume(brick):
    vol = sphere_volume(noise=0.03)
    verts, faces, _, _ = marching_cubes(vol, 0.7)
    mesh = welded(iter_brick_triangles(vol, 0.7, brick=brick))
    assert abs(mesh.n_triangles - len(faces)) <= 2
    assert len(mesh.vertices) == len(verts)
    np.testing.assert_allclose(np.sort(mesh.vertices, axis=0), np.sort(verts, axis=0), atol=1e-4)


def test_sphere_isosurface_is_watertight_across_bricks():
    mesh = welded(iter_brick_triangles(sphere_volume((48, 48, 48)), 0.8, brick=10,
                                       spacing=(0.5, 0.25, 2.0), origin=(10, -3, 1)))
    tm = trimesh.Trimesh(mesh.vertices, mesh.indices, process=False)
    assert tm.is_watertight
    assert tm.euler_number == 2
    lo, hi = mesh.bounds()
    np.testing.assert_allclose((lo + hi) / 2, [10 + 47 * 0.25, -3 + 47 * 0.125, 1 + 47],
                               atol=0.3)


def test_stitching_keeps_a_non_repeatable_field_watertight():
    """A field whose value on a shared face depends on which brick evaluates it."""
    n = 40
    calls = []

    def field(xr, yr, zr):
        calls.append((len(xr), len(yr), len(zr)))
        g = [np.linspace(-1, 1, n)[np.asarray(r)] for r in (xr, yr, zr)]
        r = np.sqrt(g[0][:, None, None] ** 2 + g[1][None, :, None] ** 2 + g[2][None, None, :] ** 2)
        wobble = 1e-4 * (xr.start + 2 * yr.start + 3 * zr.start)  # brick-dependent
        return (r + wobble).astype(np.float32)

    mesh = welded(iter_field_triangles(field, (n, n, n), 0.75, brick=8))
    tm = trimesh.Trimesh(mesh.vertices, mesh.indices, process=False)
    assert tm.is_watertight
    assert max(max(c) for c in calls) <= 9


def test_only_bricks_are_read():
    class Spy:
        def __init__(self, data):
            self.data, self.shape, self.largest = data, data.shape, 0

        def __getitem__(self, key):
            block = self.data[key]
            self.largest = max(self.largest, block.size)
            return block

    spy = Spy(sphere_volume((70, 70, 70)))
    assert sum(len(f) for _, _, f in iter_brick_triangles(spy, 0.5, brick=16)) > 0
    assert spy.largest <= 17 ** 3


def test_memmapped_volume(tmp_path):
    vol = sphere_volume()
    np.save(tmp_path / "v.npy", vol)
    mm = np.load(tmp_path / "v.npy", mmap_mode="r")
    a = welded(iter_brick_triangles(mm, 0.6, brick=8))
    b = welded(iter_brick_triangles(vol, 0.6, brick=8))
    np.testing.assert_array_equal(a.indices, b.indices)


def test_no_crossing_and_skipped_bricks():
    vol = sphere_volume()
    assert list(iter_brick_triangles(vol, 5.0)) == []
    v, f = march_brick(np.ones((3, 3, 3)), 1.0, (0, 0, 0))
    assert v.shape == (0, 3) and f.shape == (0, 3)
    assert list(iter_field_triangles(lambda *r: None, (20, 20, 20), 0.5, brick=4)) == []
    with pytest.raises(ValueError, match="NaN"):
        march_brick(np.full((3, 3, 3), np.nan), 0.5, (0, 0, 0))


def test_brick_grid_order_is_x_slowest():
    bricks = brick_grid((10, 10, 10), brick=4)
    assert [b[0] for b in bricks[:4]] == [(0, 0, 0), (0, 0, 1), (0, 0, 2), (0, 1, 0)]
