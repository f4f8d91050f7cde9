"""Sparse loads: a domain built from only the triangles the rays waiting for it can hit.

Out of core, the last bounces of a frame reach domains the cache has evicted, a few rays
each: issue 25 counted rounds 3-4 of spec-ooc at 36 % of the loads for 0.6 % of the rays
(a median of 2 rays a load), and each such load reads the domain and builds its whole BVH
(the build is 80-90 % of a load here: ``bench/README.md``, "Sparse loads"). A sparse load
reads the domain as usual (the checksums are checked over whole files), then builds Embree's
BVH over only the triangles whose boxes meet the cells those rays' segments cross, on a grid
of the domain's box finer than its occupancy mask (:func:`grid_dims`). It is traced once and
dropped: it does not enter the cache, so it evicts nothing.

Why the hits are the same bit for bit. A hit on the segment ``[0, limit]`` of a ray lies in a
cell that ``occupancy_kernels.mark_segments`` marks (the occupancy query's conservative walk,
grown by the same radius: ``scene.occupancy``'s docstring), and in the box of the triangle
it lies on, whose cells ``select_triangles`` tests: every triangle a ray of the batch can hit
is built. Embree's robust triangle test gives a triangle's distance and barycentrics from its
vertices alone (the BVH only decides which triangles are tested: a BVH built at another
quality gives the same hits, ``tests/test_build_quality.py``), and the tie filter keeps the
lowest primitive id: the selection keeps the triangles in their order, and its ids map back
to the domain's (``SparseDomainBVH.intersect``), so ties go the same way.

A ray the load was not built for (a shadow ray cast at a hit in the domain) may cross cells
it left out: ``SparseDomainBVH.covers`` says which rays it answers for, and a schedule
queues the others for the domain's next activation (``schedule.spec_ooc``).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from vastray.scene.bvh import DomainBVH
from vastray.scene.footprint import resident_bytes
from vastray.scene.occupancy import RADIUS_PADS, cell_size
from vastray.scene.store import DomainArrays

#: Set to "0", "off" or "no" to load every domain whole (measurements: with and without).
ENV = "VASTRAY_SPARSE_LOADS"
#: Most rays an activation may bring for its domain to be loaded sparse (more: whole). The
#: walk that marks their cells costs about a microsecond a ray; many rays select most
#: triangles anyway.
MAX_RAYS = 4096
#: Largest share of a domain's triangles a sparse build may take; above it the domain is
#: built whole and cached, as any load (a second activation then costs nothing).
MAX_SHARE = 0.25
#: Cells along the finest selection grid's longest axis.
MAX_RESOLUTION = 96


def enabled() -> bool:
    """Whether out-of-core renders may load domains sparse (``VASTRAY_SPARSE_LOADS``,
    default on)."""
    return os.environ.get(ENV, "1").strip().lower() not in ("0", "off", "no", "false")


@dataclass(frozen=True)
class RaySegments:
    """The rays an activation will trace against a domain, as segments ``[0, limit]``.

    Attributes
    ----------
    origins, directions : (n, 3) float32
    limits : (n,) float32 (``inf``: to the box's far side)
    pad : the slab test's pad of these rays (``DomainGeometry.slabs``): the marks are grown by
        ``RADIUS_PADS`` of it, as the occupancy query's.
    """

    origins: np.ndarray
    directions: np.ndarray
    limits: np.ndarray
    pad: float

    def __len__(self) -> int:
        return len(self.limits)

    @staticmethod
    def empty(pad: float = 0.0) -> RaySegments:
        """No ray."""
        return RaySegments(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                           np.zeros(0, np.float32), pad)

    @staticmethod
    def joined(parts: list[RaySegments]) -> RaySegments:
        """One batch of several; the largest pad covers them all."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return RaySegments.empty()
        return RaySegments(np.concatenate([p.origins for p in parts]),
                           np.concatenate([p.directions for p in parts]),
                           np.concatenate([p.limits for p in parts]),
                           max(p.pad for p in parts))


def grid_dims(lo: np.ndarray, hi: np.ndarray, n_triangles: int) -> tuple[int, int, int]:
    """Cells per axis of a selection grid: about 2 cells a triangle's width along the longest
    axis (``2 * cbrt(T)``, an isosurface's triangles spread over a surface, not a volume),
    between 4 and ``MAX_RESOLUTION``, the other axes in proportion."""
    extent = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0.0)
    longest = float(extent.max(initial=0.0))
    if not np.isfinite(longest) or longest <= 0:
        return (1, 1, 1)
    r = int(np.clip(round(2.0 * max(n_triangles, 1) ** (1.0 / 3.0)), 4, MAX_RESOLUTION))
    dims = np.clip(np.ceil(r * extent / longest - 1e-9), 1, r).astype(np.int64)
    return tuple(int(d) for d in dims)


@dataclass(frozen=True)
class Selection:
    """The cells a batch of segments may hit on, and the triangles that meet them.

    Attributes
    ----------
    lo, hi, cell : (3,) float64 the grid's box and cell edge; dims : (3,) int64 cells per
        axis
    marks : (a * b * c,) uint8, 1 at the marked cells (None: every cell)
    triangles : (m,) int32 the selected triangles' ids in the domain, ascending
    """

    lo: np.ndarray
    hi: np.ndarray
    cell: np.ndarray
    dims: np.ndarray
    marks: np.ndarray | None
    triangles: np.ndarray


def select(vertices: np.ndarray, indices: np.ndarray, lo: np.ndarray, hi: np.ndarray,
           segments: RaySegments) -> Selection:
    """The triangles of a domain that ``segments`` can hit.

    Parameters
    ----------
    vertices : (V, 3) float32; indices : (T, 3) uint32 (a domain's, in the store's frame)
    lo, hi : (3,) its box (the manifest's bounds, as the occupancy mask's)
    segments : the rays.
    """
    from vastray.scene.occupancy_kernels import mark_segments, select_triangles

    lo = np.ascontiguousarray(lo, np.float64)
    hi = np.ascontiguousarray(hi, np.float64)
    dims = np.asarray(grid_dims(lo, hi, len(indices)), np.int64)
    cell = cell_size(lo, hi, dims)
    marks = np.zeros(int(np.prod(dims)), np.uint8)
    everything = not mark_segments(np.ascontiguousarray(segments.origins, np.float32),
                                   np.ascontiguousarray(segments.directions, np.float32),
                                   np.ascontiguousarray(segments.limits, np.float32),
                                   float(RADIUS_PADS * segments.pad), lo, hi, cell, dims,
                                   marks)
    if everything or marks.all():
        return Selection(lo, hi, cell, dims, None, np.arange(len(indices), dtype=np.int32))
    table = np.zeros(tuple(int(d) + 1 for d in dims), np.int64)
    table[1:, 1:, 1:] = marks.reshape(tuple(dims)).cumsum(0).cumsum(1).cumsum(2)
    keep = np.empty(len(indices), np.uint8)
    select_triangles(np.ascontiguousarray(vertices, np.float32),
                     np.ascontiguousarray(indices, np.uint32), lo, cell, dims, table, keep)
    return Selection(lo, hi, cell, dims, marks, np.nonzero(keep)[0].astype(np.int32))


class SparseDomainBVH:
    """A domain's selected triangles in an Embree scene, answering for the rays whose cells
    were marked (``covers``) as the whole domain would, bit for bit.

    It has what shading reads of a ``DomainBVH`` (``domain_id``, ``vertices`` and
    ``indices`` of the whole domain, the kept attributes), and its hits name the domain's
    triangle ids.

    Parameters
    ----------
    domain_id : the domain's id in the store.
    arrays : the whole domain as read.
    selection : what ``select`` chose for the rays.
    keep, pool, build_quality, mesh_quality : as for ``DomainBVH``.
    """

    sparse = True

    def __init__(self, domain_id: int, arrays: DomainArrays, selection: Selection,
                 keep: frozenset[str] = frozenset(), pool: ThreadPoolExecutor | None = None,
                 build_quality: int | None = None, mesh_quality: int | None = None):
        self.domain_id = domain_id
        self.selection = selection
        self._ids = selection.triangles
        chosen = DomainArrays(vertices=arrays.vertices,
                              indices=np.ascontiguousarray(arrays.indices[self._ids]))
        self._inner = DomainBVH(domain_id, chosen, frozenset(), pool, build_quality,
                                mesh_quality)
        self.compiled, self.pool = self._inner.compiled, pool
        #: triangles built (of ``domain_triangles``)
        self.n_triangles = len(self._ids)
        self.domain_triangles = arrays.n_triangles
        self.vertices = np.ascontiguousarray(arrays.vertices, dtype=np.float32)
        self.indices = np.ascontiguousarray(arrays.indices, dtype=np.uint32)
        self.objects = (np.array(arrays.objects) if "objects" in keep and arrays.objects is not None
                        else None)
        self.colors = np.array(arrays.colors) if "colors" in keep and arrays.colors is not None else None
        self.scalars = (np.array(arrays.scalars) if "scalars" in keep and arrays.scalars is not None
                        else None)
        self._array_bytes = arrays.nbytes()

    def covers(self, origins: np.ndarray, directions: np.ndarray, limits: np.ndarray,
               pad: float) -> np.ndarray:
        """(n,) bool: the rays every cell of whose segment ``[0, limit]`` (grown as the marks
        were, by ``RADIUS_PADS * pad``; ``pad`` at most the marks') is marked, which this
        load answers for as the whole domain would: the occupancy query run over the cells
        left unmarked finds none."""
        sel = self.selection
        n = len(origins)
        if sel.marks is None or n == 0:
            return np.ones(n, bool)
        from vastray.scene.occupancy_kernels import crosses

        unmarked = np.ascontiguousarray(1 - sel.marks)
        crossing = np.ones(n, np.bool_)
        one = np.zeros(1, np.int64)
        crosses(np.ascontiguousarray(origins, np.float32),
                np.ascontiguousarray(directions, np.float32), np.arange(n, dtype=np.int64),
                np.zeros(n, np.int64),
                np.ascontiguousarray(np.broadcast_to(limits, (n,)), np.float32),
                float(RADIUS_PADS * pad), sel.lo[None], sel.hi[None], sel.cell[None],
                sel.dims[None], np.ones(1, np.bool_), one, unmarked, crossing)
        return ~crossing

    def nbytes(self) -> int:
        """Bytes held while it is traced: the domain's arrays and Embree's scene of the
        selection."""
        return resident_bytes(self.n_triangles, self._array_bytes, self.compiled, False)

    def intersect(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray,
                  pool: ThreadPoolExecutor | None = None) -> dict[str, np.ndarray]:
        """``DomainBVH.intersect``, the hits' ``primID`` the domain's triangle ids."""
        r = self._inner.intersect(origins, directions, t_far, pool)
        prim = r["primID"]
        hit = prim >= 0
        prim[hit] = self._ids[prim[hit]]
        return r

    def occluded(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray,
                 pool: ThreadPoolExecutor | None = None) -> np.ndarray:
        """``DomainBVH.occluded``."""
        return self._inner.occluded(origins, directions, t_far, pool)

    def close(self) -> None:
        self._inner.close()
