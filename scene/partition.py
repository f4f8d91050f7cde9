"""Split one triangle mesh into spatial domains: a uniform grid or a balanced k-d tree.

Triangles are assigned whole, by centroid, so every triangle lands in exactly one domain. A
domain's stored box is the box of its own triangles; it may stick out of the partition cell that
selected them (triangles crossing a cut), so domain boxes may overlap. The cells themselves are
kept in :attr:`Partition.cells`. Empty cells are dropped and the remaining domains numbered
0..D-1 in cell order.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from vastray.scene import meshops
from vastray.scene.store import DomainArrays

log = logging.getLogger(__name__)


@dataclass
class Partition:
    """Domains made from one mesh.

    Attributes
    ----------
    domains : D non-empty domains, each re-indexed to its own vertices.
    cells : (D, 2, 3) float64 partition cell (lo, hi) that selected each domain's triangles.
    method : ``"grid"`` or ``"kd"``.
    params : the method's settings, e.g. ``{"grid": [2, 2, 2]}`` or ``{"domains": 7}``.
    """

    domains: list[DomainArrays]
    cells: np.ndarray
    method: str
    params: dict

    def manifest_entry(self) -> dict:
        """JSON-ready description for the store manifest's ``"partition"`` key."""
        return {"method": self.method, **self.params, "cells": self.cells.tolist()}


def scene_box(mesh: DomainArrays) -> np.ndarray:
    """(2, 3) float64 box of the vertices referenced by triangles."""
    return mesh.bounds()


def grid_cells_of(points: np.ndarray, grid: Sequence[int], box: np.ndarray) -> np.ndarray:
    """Flat cell id of each point in a uniform grid over ``box``.

    Parameters
    ----------
    points : (n, 3) float
    grid : (3,) cells per axis (a, b, c).
    box : (2, 3) lo, hi of the grid.

    Returns
    -------
    (n,) int64 cell id ``(ix * b + iy) * c + iz`` (x slowest); points outside are clamped.
    """
    dims = np.asarray(grid, dtype=np.int64)
    lo, hi = np.asarray(box[0], np.float64), np.asarray(box[1], np.float64)
    extent = np.where(hi > lo, hi - lo, 1.0)
    ijk = np.floor((np.asarray(points, np.float64) - lo) / extent * dims).astype(np.int64)
    ijk = np.clip(ijk, 0, dims - 1)
    return (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]


def grid_cell_boxes(grid: Sequence[int], box: np.ndarray) -> np.ndarray:
    """(a*b*c, 2, 3) float64 boxes of a uniform grid over ``box``, in cell-id order."""
    a, b, c = (int(n) for n in grid)
    lo, hi = np.asarray(box[0], np.float64), np.asarray(box[1], np.float64)
    edges = [np.linspace(lo[k], hi[k], n + 1) for k, n in enumerate((a, b, c))]
    ix, iy, iz = np.meshgrid(np.arange(a), np.arange(b), np.arange(c), indexing="ij")
    ix, iy, iz = ix.ravel(), iy.ravel(), iz.ravel()
    cell_lo = np.stack([edges[0][ix], edges[1][iy], edges[2][iz]], axis=1)
    cell_hi = np.stack([edges[0][ix + 1], edges[1][iy + 1], edges[2][iz + 1]], axis=1)
    return np.stack([cell_lo, cell_hi], axis=1)


def split_by_cell(mesh: DomainArrays, cell: np.ndarray, n_cells: int,
                  cells: np.ndarray) -> tuple[list[DomainArrays], np.ndarray]:
    """Group triangles by cell id into re-indexed domains, dropping empty cells.

    Parameters
    ----------
    mesh : the whole mesh.
    cell : (T,) int cell id of each triangle, in [0, n_cells).
    n_cells : number of cells.
    cells : (n_cells, 2, 3) cell boxes.

    Returns
    -------
    domains : list of D non-empty DomainArrays, in cell-id order.
    cells : (D, 2, 3) boxes of the kept cells.
    """
    order = np.argsort(cell, kind="stable")
    counts = np.bincount(cell, minlength=n_cells)
    ends = np.cumsum(counts)
    domains, kept = [], []
    for cid in np.flatnonzero(counts):  # one iteration per domain
        tris = order[ends[cid] - counts[cid]:ends[cid]]
        domains.append(meshops.subset(mesh, tris))
        kept.append(cid)
    dropped = n_cells - len(kept)
    if dropped:
        log.info("dropped %d empty cells of %d", dropped, n_cells)
    return domains, np.asarray(cells, np.float64)[kept].reshape(-1, 2, 3)


def partition_grid(mesh: DomainArrays, grid: Sequence[int] = (2, 2, 2),
                   box: np.ndarray | None = None) -> Partition:
    """Uniform a x b x c grid over the scene box; triangles go to the cell of their centroid.

    Parameters
    ----------
    mesh : vertices (V, 3), indices (T, 3) and optional attributes.
    grid : (3,) cells per axis, each >= 1.
    box : (2, 3) grid box; defaults to the box of the triangles.

    Returns
    -------
    Partition with at most a*b*c domains (empty cells dropped), ids in x-slowest cell order.
    """
    grid = tuple(int(n) for n in grid)
    if len(grid) != 3 or min(grid) < 1:
        raise ValueError(f"grid needs 3 positive cell counts, got {grid}")
    box = scene_box(mesh) if box is None else np.asarray(box, np.float64)
    cell = grid_cells_of(meshops.centroids(mesh.vertices, mesh.indices), grid, box)
    domains, cells = split_by_cell(mesh, cell, int(np.prod(grid)), grid_cell_boxes(grid, box))
    return Partition(domains, cells, "grid", {"grid": list(grid)})


def kd_cells_of(points: np.ndarray, n: int, box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Balanced k-d split of points into ``n`` leaves.

    Each node with ``m`` leaves to make splits its points along the longest axis of their box,
    at the point of rank ``len * (m // 2) / m`` (the median when ``m`` is even), giving
    ``m // 2`` leaves to the low side and the rest to the high side. Leaf sizes differ by at
    most one point per level, so any ``n`` (not only powers of two) is balanced.

    Parameters
    ----------
    points : (k, 3) float
    n : number of leaves, >= 1.
    box : (2, 3) box of the root cell.

    Returns
    -------
    leaf : (k,) int64 leaf id of each point, leaves numbered left to right.
    cells : (n, 2, 3) float64 leaf cell boxes (they tile ``box``).
    """
    points = np.asarray(points)
    leaf = np.zeros(len(points), dtype=np.int64)
    cells = np.zeros((n, 2, 3))
    # stack of (point ids, first leaf id, leaf count, cell box)
    stack = [(np.arange(len(points)), 0, n, np.asarray(box, np.float64).copy())]
    while stack:  # one iteration per tree node (2n - 1 in all)
        ids, first, m, cell = stack.pop()
        if m == 1:
            leaf[ids] = first
            cells[first] = cell
            continue
        m_low = m // 2
        k = (len(ids) * m_low) // m
        pts = points[ids]
        if len(ids):
            axis = int(np.argmax(pts.max(axis=0) - pts.min(axis=0)))
        else:
            axis = int(np.argmax(cell[1] - cell[0]))
        if 0 < k < len(ids):
            part = np.argpartition(pts[:, axis], k)
            low, high = ids[part[:k]], ids[part[k:]]
            cut = float(pts[part[k], axis])
        else:
            low, high = ids[:k], ids[k:]
            cut = float(cell[:, axis].mean())
        cut = min(max(cut, cell[0, axis]), cell[1, axis])
        low_cell, high_cell = cell.copy(), cell.copy()
        low_cell[1, axis] = cut
        high_cell[0, axis] = cut
        stack.append((high, first + m_low, m - m_low, high_cell))
        stack.append((low, first, m_low, low_cell))
    return leaf, cells


def partition_kd(mesh: DomainArrays, n: int) -> Partition:
    """Balanced k-d split of the triangle centroids into ``n`` domains.

    Parameters
    ----------
    mesh : vertices (V, 3), indices (T, 3) and optional attributes.
    n : number of domains, >= 1; fewer come out only when there are fewer than ``n`` triangles.

    Returns
    -------
    Partition whose domain triangle counts differ by at most about log2(n).
    """
    if n < 1:
        raise ValueError(f"need at least one domain, got {n}")
    box = scene_box(mesh)
    leaf, cells = kd_cells_of(meshops.centroids(mesh.vertices, mesh.indices), n, box)
    domains, kept = split_by_cell(mesh, leaf, n, cells)
    return Partition(domains, kept, "kd", {"domains": int(n)})


def partition_pieces(mesh: DomainArrays, piece: np.ndarray, n: int) -> Partition:
    """One domain per piece, as the data came (e.g. the pieces of a ``.pvtu``), not re-split.

    Parameters
    ----------
    mesh : vertices (V, 3), indices (T, 3) and optional attributes.
    piece : (T,) int piece id of each triangle, in [0, n).
    n : number of pieces; pieces without triangles are dropped.

    Returns
    -------
    Partition whose cells are the boxes of the pieces' own triangles.
    """
    domains, _ = split_by_cell(mesh, np.asarray(piece, np.int64), n, np.zeros((n, 2, 3)))
    cells = np.asarray([d.bounds() for d in domains], np.float64).reshape(-1, 2, 3)
    return Partition(domains, cells, "pieces", {"domains": len(domains)})
