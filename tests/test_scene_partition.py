"""Grid and k-d partitioning keep every triangle exactly once, with its attributes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from vastray.scene import meshops
from vastray.scene.partition import kd_cells_of, partition_grid, partition_kd
from vastray.scene.store import DomainArrays


def soup(seed: int, n_tri: int = 3000, n_vert: int = 1500) -> DomainArrays:
    """Random shared-vertex triangles with per-vertex scalars/colours and per-triangle objects."""
    rng = np.random.default_rng(seed)
    vertices = (rng.random((n_vert, 3)) * [4.0, 2.0, 1.0]).astype(np.float32)
    base = rng.integers(0, n_vert, n_tri)
    indices = np.stack([base, (base + 1 + rng.integers(0, 5, n_tri)) % n_vert,
                        (base + 7 + rng.integers(0, 5, n_tri)) % n_vert], axis=1)
    return DomainArrays(vertices, indices.astype(np.uint32),
                        objects=rng.integers(0, 3, n_tri).astype(np.uint16),
                        scalars=vertices[:, 0] * 10,
                        colors=vertices / vertices.max(axis=0))


def triangle_rows(mesh: DomainArrays) -> np.ndarray:
    """(T, 10) rows: each triangle's vertex coordinates (vertex order normalised) + object id."""
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.indices)]  # (T, 3, 3)
    order = np.lexsort((tri[:, :, 2], tri[:, :, 1], tri[:, :, 0]), axis=1)
    tri = np.take_along_axis(tri, order[:, :, None], axis=1).reshape(-1, 9)
    rows = np.concatenate([tri, np.asarray(mesh.objects, np.float32)[:, None]], axis=1)
    return rows[np.lexsort(rows.T[::-1])]


def assert_same_triangles(mesh: DomainArrays, domains: list[DomainArrays]) -> None:
    assert sum(d.n_triangles for d in domains) == mesh.n_triangles
    np.testing.assert_array_equal(triangle_rows(meshops.concat(domains)), triangle_rows(mesh))


def assert_attributes_follow(domains: list[DomainArrays]) -> None:
    for d in domains:
        np.testing.assert_array_equal(d.scalars, d.vertices[:, 0] * 10)
        assert d.indices.dtype == np.uint32 and int(d.indices.max()) < len(d.vertices)
        assert len(np.unique(d.indices)) == len(d.vertices)  # only the vertices it uses


@pytest.mark.parametrize("grid", [(1, 1, 1), (2, 2, 2), (4, 3, 1), (5, 1, 7)])
def test_grid_keeps_every_triangle_once(grid):
    mesh = soup(0)
    part = partition_grid(mesh, grid)
    assert 1 <= len(part.domains) <= np.prod(grid)
    assert part.cells.shape == (len(part.domains), 2, 3)
    assert_same_triangles(mesh, part.domains)
    assert_attributes_follow(part.domains)
    for dom, cell in zip(part.domains, part.cells, strict=True):
        c = meshops.centroids(dom.vertices, dom.indices)
        assert np.all(c >= cell[0] - 1e-5) and np.all(c <= cell[1] + 1e-5)


@pytest.mark.parametrize("n", [1, 2, 3, 5, 7, 8, 13])
def test_kd_keeps_every_triangle_once_and_balances(n):
    mesh = soup(1, n_tri=4000)
    part = partition_kd(mesh, n)
    assert len(part.domains) == n
    assert_same_triangles(mesh, part.domains)
    assert_attributes_follow(part.domains)
    counts = np.array([d.n_triangles for d in part.domains])
    assert counts.max() - counts.min() <= int(np.ceil(np.log2(n))) + 1
    assert counts.max() / counts.min() < 1.02


def test_kd_cells_tile_the_box_and_contain_their_points():
    rng = np.random.default_rng(3)
    pts = rng.random((1000, 3)) * [10, 1, 1]
    box = np.array([[0, 0, 0], [10, 1, 1.0]])
    leaf, cells = kd_cells_of(pts, 6, box)
    assert np.bincount(leaf).tolist() == [166, 167, 167, 166, 167, 167]
    assert np.isclose(np.prod(cells[:, 1] - cells[:, 0], axis=1).sum(), 10.0)
    inside = (pts >= cells[leaf, 0]) & (pts <= cells[leaf, 1])
    assert inside.all()
    # the first cut is along the longest (x) axis
    assert cells[0, 1, 0] < 10 and cells[0, 1, 1] == 1


def test_more_domains_than_triangles():
    mesh = soup(2, n_tri=5)
    part = partition_kd(mesh, 9)
    assert len(part.domains) == 5
    assert_same_triangles(mesh, part.domains)


def test_empty_grid_cells_are_dropped_and_ids_renumbered():
    a = trimesh.creation.icosphere(subdivisions=2)
    b = a.copy()
    b.apply_translation([10, 0, 0])
    mesh = meshops.concat([DomainArrays(np.asarray(m.vertices, np.float32),
                                        np.asarray(m.faces, np.uint32)) for m in (a, b)],
                          objects=[0, 1])
    part = partition_grid(mesh, (5, 1, 1))
    assert len(part.domains) == 2
    assert [int(np.unique(d.objects)[0]) for d in part.domains] == [0, 1]
    assert part.manifest_entry()["method"] == "grid"


def test_triangles_crossing_a_cut_grow_the_domain_box():
    # one long triangle whose centroid is in the left cell but reaches into the right one
    v = np.array([[0, 0, 0], [0, 1, 0], [3, 0, 0], [3.5, 0, 0], [4, 0, 0], [4, 1, 0]],
                 np.float32)
    mesh = DomainArrays(v, np.array([[0, 1, 2], [3, 4, 5]], np.uint32))
    part = partition_grid(mesh, (2, 1, 1))
    assert len(part.domains) == 2
    assert part.domains[0].bounds()[1, 0] == 3.0 > part.cells[0, 1, 0] == 2.0


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n_tri=st.integers(1, 300),
       grid=st.tuples(st.integers(1, 4), st.integers(1, 4), st.integers(1, 4)),
       n_kd=st.integers(1, 12))
def test_partitions_are_exact_for_any_input(seed, n_tri, grid, n_kd):
    mesh = soup(seed, n_tri=n_tri, n_vert=max(12, n_tri))
    assert_same_triangles(mesh, partition_grid(mesh, grid).domains)
    assert_same_triangles(mesh, partition_kd(mesh, n_kd).domains)


def test_flat_mesh_partitions():
    # zero extent along z must not divide by zero
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    mesh = DomainArrays(v, np.array([[0, 1, 2], [1, 3, 2]], np.uint32))
    assert sum(d.n_triangles for d in partition_grid(mesh, (2, 2, 2)).domains) == 2
    assert len(partition_kd(mesh, 2).domains) == 2
