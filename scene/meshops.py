"""Array-level triangle-mesh operations shared by readers, partitioning and generation.

Every function works on whole arrays (no Python loop per triangle or vertex) and on the
``DomainArrays`` layout of :mod:`vastray.scene.store`.
"""

from __future__ import annotations

import numpy as np

from vastray.scene.store import DomainArrays


def centroids(vertices: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Triangle centroids.

    Parameters
    ----------
    vertices : (V, 3) float
    indices : (T, 3) integer

    Returns
    -------
    (T, 3) float32
    """
    v = np.asarray(vertices, dtype=np.float32)
    c = v[indices[:, 0]] + v[indices[:, 1]]
    c += v[indices[:, 2]]
    c /= np.float32(3.0)
    return c


def triangle_areas(vertices: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Triangle areas computed in float64 from the (float32) vertices.

    Parameters
    ----------
    vertices : (V, 3) float
    indices : (T, 3) integer

    Returns
    -------
    (T,) float64
    """
    v = np.asarray(vertices, dtype=np.float64)
    a = v[indices[:, 0]]
    e1 = v[indices[:, 1]] - a
    e2 = v[indices[:, 2]] - a
    return 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)


def degenerate_mask(vertices: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Mask of zero-area triangles (repeated index, coincident or collinear vertices).

    Parameters
    ----------
    vertices : (V, 3) float32
    indices : (T, 3) integer

    Returns
    -------
    (T,) bool, True where the triangle has zero area in float32 vertex precision.
    """
    if len(indices) == 0:
        return np.zeros(0, dtype=bool)
    return triangle_areas(np.asarray(vertices, dtype=np.float32), indices) == 0.0


def subset(mesh: DomainArrays, triangles: np.ndarray) -> DomainArrays:
    """The given triangles of ``mesh`` with only the vertices they use, re-indexed.

    Parameters
    ----------
    mesh : source arrays.
    triangles : (k,) integer indices or (T,) bool mask of the triangles to keep.

    Returns
    -------
    DomainArrays with k triangles and the (sorted, unique) vertices they reference; objects,
    scalars and colors are carried along.
    """
    idx = np.asarray(mesh.indices)[triangles]
    used, inverse = np.unique(idx, return_inverse=True)
    return DomainArrays(
        vertices=np.asarray(mesh.vertices)[used],
        indices=inverse.reshape(-1, 3).astype(np.uint32),
        objects=None if mesh.objects is None else np.asarray(mesh.objects)[triangles],
        scalars=None if mesh.scalars is None else np.asarray(mesh.scalars)[used],
        colors=None if mesh.colors is None else np.asarray(mesh.colors)[used],
        origin=mesh.origin,
    )


def weld(mesh: DomainArrays) -> DomainArrays:
    """Merge vertices with bit-identical positions (exact, no tolerance).

    Used to join the pieces of a brick-by-brick isosurface, whose shared vertices are computed
    identically on both sides of a brick face. Vertices keep their first-occurrence order;
    attributes of the first occurrence are kept. Unreferenced vertices are kept too.

    Parameters
    ----------
    mesh : arrays with vertices (V, 3) float32 and indices (T, 3).

    Returns
    -------
    DomainArrays with V' <= V vertices and the same triangles.
    """
    v = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    if len(v) == 0:
        return mesh
    bits = v.view(np.uint32)
    order = np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0]))  # stable: first occurrence leads
    sorted_bits = bits[order]
    new_group = np.ones(len(v), dtype=bool)
    new_group[1:] = np.any(sorted_bits[1:] != sorted_bits[:-1], axis=1)
    first = order[new_group]  # original index of each group's first occurrence
    group_of_sorted = np.cumsum(new_group) - 1
    # renumber groups by first occurrence so the vertex order stays close to the input's
    rank = np.empty(len(first), dtype=np.int64)
    by_first = np.argsort(first, kind="stable")
    rank[by_first] = np.arange(len(first))
    remap = np.empty(len(v), dtype=np.int64)
    remap[order] = rank[group_of_sorted]
    keep = first[by_first]
    return DomainArrays(
        vertices=v[keep],
        indices=remap[mesh.indices].astype(np.uint32),
        objects=mesh.objects,
        scalars=None if mesh.scalars is None else np.asarray(mesh.scalars)[keep],
        colors=None if mesh.colors is None else np.asarray(mesh.colors)[keep],
        origin=mesh.origin,
    )


def concat(parts: list[DomainArrays], objects: list[int] | None = None) -> DomainArrays:
    """Concatenate meshes into one, offsetting indices.

    Parameters
    ----------
    parts : the meshes; an attribute (scalars, colors) is kept only when every part has it.
    objects : optional object (material slot) id of each part; written as the per-triangle
        ``objects`` (T,) uint16 array. Without it, the parts' own ``objects`` are kept when
        all parts have them.

    Returns
    -------
    DomainArrays with sum(V_i) vertices and sum(T_i) triangles, in the first part's frame
    (``origin``; the other parts' vertices are moved into it in float64).
    """
    if not parts:
        return DomainArrays(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32))
    n_vert = np.array([len(p.vertices) for p in parts], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(n_vert)[:-1]])
    indices = np.concatenate([
        np.asarray(p.indices, dtype=np.int64) + off for p, off in zip(parts, offsets, strict=True)
    ]).reshape(-1, 3)
    if len(indices) and int(n_vert.sum()) > np.iinfo(np.uint32).max:
        raise ValueError("more than 2**32 vertices in one mesh")

    def _all(name):
        arrays = [getattr(p, name) for p in parts]
        if any(a is None for a in arrays):
            return None
        return np.concatenate([np.asarray(a) for a in arrays])

    if objects is not None:
        obj = np.repeat(np.asarray(objects, dtype=np.uint16),
                        [p.n_triangles for p in parts])
    else:
        obj = _all("objects")
    origin = parts[0].origin
    base = np.zeros(3) if origin is None else np.asarray(origin, np.float64)

    def _in_frame(p: DomainArrays) -> np.ndarray:
        shift = (np.zeros(3) if p.origin is None else np.asarray(p.origin, np.float64)) - base
        if not shift.any():
            return np.asarray(p.vertices, np.float32)
        return (np.asarray(p.vertices, np.float64) + shift).astype(np.float32)

    return DomainArrays(
        vertices=np.concatenate([_in_frame(p) for p in parts]).reshape(-1, 3),
        indices=indices.astype(np.uint32),
        objects=obj,
        scalars=_all("scalars"),
        colors=_all("colors"),
        origin=origin,
    )
