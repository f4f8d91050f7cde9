"""Closest-hit and occlusion queries over a store split into domains.

A ray's closest hit is final only when every domain it has not visited starts beyond that hit
(domain boxes may overlap). Each query visits every domain whose box the ray enters before its
current closest hit, once, in an order that prefers resident domains and then the domains with
the most waiting rays (the image-plane schedule, Navrátil's LoadAnyOnce). The result does not
depend on that order: the minimum over domains is the same whichever domain comes first.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from vastray.render.materials import colormap
from vastray.scene.cache import DomainCache
from vastray.scene.store import Store


@dataclass
class Hits:
    """Closest hits of a ray batch.

    Attributes
    ----------
    t : (n,) float64 hit distance, ``inf`` for a miss.
    normal : (n, 3) float64 unit geometric normal (not yet facing the ray).
    material : (n,) int64 material slot (0 where the store has one object).
    color : (n, 3) float64 per-vertex or colour-mapped colour, or None when the scene has none.
    """

    t: np.ndarray
    normal: np.ndarray
    material: np.ndarray
    color: np.ndarray | None

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.t)


@dataclass
class TraceStats:
    """Work counters of a tracer."""

    rays: dict = field(default_factory=lambda: {"camera": 0, "bounce": 0, "shadow": 0})
    ray_domain_tests: int = 0
    domains_entered: set = field(default_factory=set)


class RaySlabs:
    """Per-axis ray data for slab tests, computed once per query.

    Direction components that are exactly zero are replaced by a tiny signed value for the box
    test only: the slab then spans (-huge, +huge) when the origin lies inside it and is missed
    otherwise, which is the exact answer, without NaNs from ``0 * inf``.

    Parameters
    ----------
    origins, directions : (n, 3)
    """

    def __init__(self, origins: np.ndarray, directions: np.ndarray):
        d = directions.astype(np.float64)
        d[d == 0] = 1e-300
        self.origin = [np.ascontiguousarray(origins[:, k], dtype=np.float64) for k in range(3)]
        self.inv = [1.0 / d[:, k] for k in range(3)]

    def intervals(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Entry and exit distances of every ray through the box ``[lo, hi]`` ((3,) each).

        Returns
        -------
        t_enter, t_exit : (n,) float64; the ray overlaps the box where ``t_enter <= t_exit``.
        """
        near = far = None
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(3):
                t0 = (lo[k] - self.origin[k]) * self.inv[k]
                t1 = (hi[k] - self.origin[k]) * self.inv[k]
                lo_k, hi_k = np.minimum(t0, t1), np.maximum(t0, t1)
                near = lo_k if near is None else np.maximum(near, lo_k, out=near)
                far = hi_k if far is None else np.minimum(far, hi_k, out=far)
        return near, far


class DomainTracer:
    """Traces ray batches through the domains of a store, loading them through a cache.

    Parameters
    ----------
    store : the domain store.
    cache : the domain cache (its capacity bounds memory).
    color_source : ``"colors"``, ``"scalars"`` or None: the per-vertex data shading uses.
    threads : Embree query threads (Embree releases the GIL).
    """

    def __init__(self, store: Store, cache: DomainCache, color_source: str | None = None,
                 threads: int | None = None):
        self.store = store
        self.cache = cache
        self.color_source = color_source
        self.scalar_range = store.scalar_range or (0.0, 1.0)
        self.stats = TraceStats()
        lo, hi = store.domain_boxes()
        # Grow boxes by a few float32 ulps of their coordinates so a triangle lying exactly on
        # a box face is never culled by rounding in the slab test.
        pad = 1e-6 * (np.abs(lo).max(axis=1, initial=0) + np.abs(hi).max(axis=1, initial=0)
                      + (hi - lo).max(axis=1, initial=0))[:, None] + 1e-30
        self.lo, self.hi = lo - pad, hi + pad
        self.nonempty = np.array([d.n_triangles > 0 for d in store.domains], dtype=bool)
        threads = threads or os.cpu_count() or 1
        self.pool = ThreadPoolExecutor(threads) if threads > 1 else None

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()

    def _visit_order(self, slabs: RaySlabs, t_limit: np.ndarray) -> list[int]:
        """Domains to visit: all of them in id order when they all fit in the cache; else the
        resident ones first, then by waiting rays (descending), skipping those no ray enters."""
        ids = np.nonzero(self.nonempty)[0]
        if self.cache.capacity >= len(ids):
            return ids.tolist()
        waiting = {d: np.count_nonzero(self._entering(slabs, d, t_limit)) for d in ids}
        resident = set(self.cache.resident())
        return sorted((d for d in ids if waiting[d]),
                      key=lambda d: (d not in resident, -waiting[d], d))

    def _entering(self, slabs: RaySlabs, d: int, t_limit: np.ndarray) -> np.ndarray:
        """(n,) bool: the ray enters domain ``d``'s box before ``t_limit``, ahead of its origin."""
        t0, t1 = slabs.intervals(self.lo[d], self.hi[d])
        return (t0 <= t1) & (t1 >= 0) & (t0 < t_limit)

    def intersect(self, origins: np.ndarray, directions: np.ndarray, kind: str = "bounce"
                  ) -> Hits:
        """Closest hit of each ray among all domains.

        Parameters
        ----------
        origins, directions : (n, 3) float32; directions need not be unit length.
        kind : ``"camera"`` or ``"bounce"``, for the ray counters.
        """
        n = len(origins)
        self.stats.rays[kind] += n
        best = np.full(n, np.inf, dtype=np.float32)
        normal = np.zeros((n, 3), dtype=np.float32)
        material = np.zeros(n, dtype=np.int64)
        color = np.zeros((n, 3)) if self.color_source else None
        slabs = RaySlabs(origins, directions)
        for d in self._visit_order(slabs, best):
            idx = np.nonzero(self._entering(slabs, d, best))[0]
            if len(idx) == 0:
                continue
            self.stats.domains_entered.add(d)
            self.stats.ray_domain_tests += len(idx)
            bvh = self.cache.get(d)
            r = bvh.intersect(origins[idx], directions[idx], best[idx], self.pool)
            got = (r["primID"] >= 0) & (r["tfar"] < best[idx])
            if not got.any():
                continue
            rows = idx[got]
            prim = r["primID"][got]
            best[rows] = r["tfar"][got]
            normal[rows] = r["Ng"][got]
            if bvh.objects is not None:
                material[rows] = bvh.objects[prim]
            if color is not None:
                color[rows] = self._vertex_color(bvh, prim, r["u"][got], r["v"][got])
        t = best.astype(np.float64)
        n64 = normal.astype(np.float64)
        length = np.linalg.norm(n64, axis=1, keepdims=True)
        n64 /= np.where(length > 0, length, 1.0)
        return Hits(t=t, normal=n64, material=material, color=color)

    def _vertex_color(self, bvh, prim, u, v) -> np.ndarray:
        tri = bvh.indices[prim]
        w = np.stack([1.0 - u - v, u, v], axis=1).astype(np.float64)
        if self.color_source == "colors":
            return np.einsum("kj,kjc->kc", w, bvh.colors[tri].astype(np.float64))
        scalar = np.einsum("kj,kj->k", w, bvh.scalars[tri].astype(np.float64))
        return colormap(scalar, *self.scalar_range)

    def occluded(self, origins: np.ndarray, directions: np.ndarray, t_max: np.ndarray
                 ) -> np.ndarray:
        """Whether each shadow ray is blocked before ``t_max``.

        Parameters
        ----------
        origins, directions : (n, 3) float32
        t_max : (n,) float32 (``inf`` for lights at infinity)

        Returns
        -------
        (n,) bool
        """
        n = len(origins)
        self.stats.rays["shadow"] += n
        blocked = np.zeros(n, dtype=bool)
        slabs = RaySlabs(origins, directions)
        for d in self._visit_order(slabs, t_max):
            idx = np.nonzero(~blocked & self._entering(slabs, d, t_max))[0]
            if len(idx) == 0:
                continue
            self.stats.domains_entered.add(d)
            self.stats.ray_domain_tests += len(idx)
            bvh = self.cache.get(d)
            blocked[idx] = bvh.occluded(origins[idx], directions[idx], t_max[idx], self.pool)
        return blocked
