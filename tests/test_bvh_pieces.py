"""The fast BVH builds a large mesh as pieces of ``PIECE_TRIANGLES`` triangles (one Embree
geometry each, built in parallel by Embree's two-level builder), and every query still
reports, and breaks ties by, the mesh's own triangle ids."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.scene.bvh import DomainBVH
from vastray.scene.embree.kernels import PIECE_TRIANGLES
from vastray.scene.embree.library import RTC_BUILD_QUALITY_LOW, binding
from vastray.scene.embree.scenes import QUERIES_ENV, Scene, TopScene
from vastray.scene.store import DomainArrays

pytestmark = pytest.mark.skipif(binding() is None, reason="the compiled Embree binding is "
                                                          "unavailable (embreex fallback)")


def grid_mesh(cells: int) -> DomainArrays:
    """A flat ``cells`` x ``cells`` grid in z = 0, two triangles a cell: 2 cells² triangles,
    in row order (so each piece is a band of rows)."""
    n = cells + 1
    x, y = np.meshgrid(np.arange(n, dtype=np.float32), np.arange(n, dtype=np.float32))
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(n * n, np.float32)], axis=1)
    corner = (np.arange(cells)[None, :] + n * np.arange(cells)[:, None]).ravel()
    lower = np.stack([corner, corner + 1, corner + n + 1], axis=1)
    upper = np.stack([corner, corner + n + 1, corner + n], axis=1)
    indices = np.stack([lower, upper], axis=1).reshape(-1, 3).astype(np.uint32)
    return DomainArrays(vertices, indices)


def down_at(vertices: np.ndarray, indices: np.ndarray, triangles: np.ndarray):
    """Rays straight down (-z) onto the centroids of ``triangles``: origins, directions,
    t_far, each (n, 3) / (n,) float32."""
    centroids = vertices[indices[triangles]].mean(axis=1)
    origins = (centroids + np.array([0, 0, 1], np.float32)).astype(np.float32)
    directions = np.tile(np.array([0, 0, -1], np.float32), (len(triangles), 1))
    return origins, directions, np.full(len(triangles), np.inf, np.float32)


@pytest.fixture(params=["packets", "single"])
def queries(request, monkeypatch):
    """Each test runs with the packet kernels and with the 1-ray ones."""
    monkeypatch.setenv(QUERIES_ENV, request.param)
    if request.param == "packets" and not binding().packets:
        pytest.skip("this Embree traces 8-ray packets ray by ray (no AVX)")
    return request.param


def test_a_large_mesh_is_built_in_pieces_and_hits_name_its_own_triangles(queries):
    mesh = grid_mesh(300)  # 180,000 triangles: two pieces
    fast = DomainBVH(0, mesh, mesh_quality=RTC_BUILD_QUALITY_LOW)
    quality = DomainBVH(0, mesh)
    assert fast._scene.pieces == -(-len(mesh.indices) // PIECE_TRIANGLES) == 2
    assert quality._scene.pieces == 1
    rng = np.random.default_rng(0)
    aimed = np.concatenate([rng.integers(0, len(mesh.indices), 4000),
                            [0, PIECE_TRIANGLES - 1, PIECE_TRIANGLES, len(mesh.indices) - 1]])
    origins, directions, far = down_at(mesh.vertices, mesh.indices, aimed)
    hits = fast.intersect(origins, directions, far)
    np.testing.assert_array_equal(hits["primID"], aimed)  # beyond the first piece too
    np.testing.assert_array_equal(hits["primID"], quality.intersect(origins, directions,
                                                                     far)["primID"])
    np.testing.assert_allclose(hits["tfar"], 1.0)
    assert fast.occluded(origins, directions, np.full(len(aimed), 2, np.float32)).all()
    assert not fast.occluded(origins, directions, np.full(len(aimed), 0.5, np.float32)).any()


def test_of_two_equally_near_triangles_in_different_pieces_the_lower_id_wins(queries):
    """Triangle 100 (piece 0) is repeated as triangle PIECE_TRIANGLES + 5 (piece 1): every ray
    onto it hits both at the same distance. Compared by (geomID, primID) the copy's local id 5
    would beat 100, and by arrival order either could win."""
    mesh = grid_mesh(300)
    indices = mesh.indices.copy()
    copy = PIECE_TRIANGLES + 5
    indices[copy] = indices[100]
    fast = DomainBVH(0, DomainArrays(mesh.vertices, indices),
                     mesh_quality=RTC_BUILD_QUALITY_LOW)
    v = mesh.vertices[indices[100]].astype(np.float64)
    rng = np.random.default_rng(1)
    w = rng.dirichlet([2, 2, 2], 64)  # points inside the triangle
    targets = (w @ v).astype(np.float32)
    origins = targets + np.array([0.1, -0.2, 1.0], np.float32)
    directions = (targets - origins) / np.linalg.norm(targets - origins, axis=1)[:, None]
    far = np.full(len(targets), np.inf, np.float32)
    hits = fast.intersect(origins, directions.astype(np.float32), far)
    np.testing.assert_array_equal(hits["primID"], 100)
    # the same through a top-level scene (an instance of the domain)
    top = TopScene([fast._scene], [7])
    through = top.intersect(origins, directions.astype(np.float32), far)
    np.testing.assert_array_equal(through["primID"], 100)
    np.testing.assert_array_equal(through["id"], 7)
    top.close()


def test_pieces_need_a_two_level_bvh_and_a_positive_size():
    mesh = grid_mesh(4)
    with pytest.raises(ValueError, match="mesh_quality"):
        Scene(mesh.vertices, mesh.indices, piece_triangles=8)
    with pytest.raises(ValueError, match="positive"):
        Scene(mesh.vertices, mesh.indices, mesh_quality=RTC_BUILD_QUALITY_LOW, piece_triangles=0)
    small = Scene(mesh.vertices, mesh.indices, mesh_quality=RTC_BUILD_QUALITY_LOW,
                  piece_triangles=PIECE_TRIANGLES)
    assert small.pieces == 1  # fewer triangles than a piece: one geometry, as before
    small.close()
