"""Closest-hit and occlusion queries over a store split into domains.

A ray's closest hit is final only when every domain it has not visited starts beyond that hit
(domain boxes may overlap). Each query visits every domain whose box the ray enters before its
current closest hit, once, in an order that prefers resident domains and then the domains with
the most waiting rays (the image-plane schedule, Navrátil's LoadAnyOnce). The result does not
depend on that order: the minimum over domains is the same whichever domain comes first.
"""

from __future__ import annotations

import os
import threading
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
    """Per-axis ray data for slab tests in float32, computed once per query.

    Direction components that are exactly zero are replaced by a tiny signed value for the box
    test only: the slab then spans (-huge, +huge) when the origin lies inside it and is missed
    otherwise, which is the exact answer, without NaNs from ``0 * inf``.

    Float32 rounding moves a computed slab distance by at most a few ulps of the largest
    coordinate involved, ``M = max|origin| + max|box|``; growing every box by ``2^-19 M`` (16
    times that bound) keeps the test conservative: a ray may visit a box it barely misses,
    never skip one it enters.

    Parameters
    ----------
    origins, directions : (n, 3) float32
    box_magnitude : largest absolute box coordinate of the scene.
    """

    def __init__(self, origins: np.ndarray, directions: np.ndarray, box_magnitude: float):
        d = directions.T.astype(np.float32)  # (3, n)
        d[d == 0] = np.float32(1e-30)
        self.origin = origins.T.astype(np.float32)  # (3, n)
        with np.errstate(over="ignore"):
            self.inv = np.float32(1.0) / d  # (3, n)
        origin_magnitude = float(np.abs(self.origin).max(initial=0.0))
        self.pad = 2.0 ** -19 * (origin_magnitude + box_magnitude)
        n = origins.shape[0]
        self._a = np.empty(n, np.float32)
        self._b = np.empty(n, np.float32)

    def intervals(self, lo: np.ndarray, hi: np.ndarray, near: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Entry and exit distances of every ray through the box ``[lo, hi]`` ((3,) each).

        Parameters
        ----------
        near : optional (n,) float32 output array for the entry distances.

        Returns
        -------
        t_enter, t_exit : (n,) float32; the ray overlaps the box where ``t_enter <= t_exit``.
        """
        n = self.origin.shape[1]
        near = np.empty(n, np.float32) if near is None else near
        far = np.empty(n, np.float32)
        a, b = self._a, self._b
        lo = (lo - self.pad).astype(np.float32)
        hi = (hi + self.pad).astype(np.float32)
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(3):
                np.subtract(lo[k], self.origin[k], out=a)
                a *= self.inv[k]
                np.subtract(hi[k], self.origin[k], out=b)
                b *= self.inv[k]
                if k == 0:
                    np.minimum(a, b, out=near)
                    np.maximum(a, b, out=far)
                else:
                    lower = np.minimum(a, b)
                    np.maximum(a, b, out=b)
                    np.maximum(near, lower, out=near)
                    np.minimum(far, b, out=far)
        return near, far


def _groups(sorted_rays: np.ndarray, counts: np.ndarray) -> list[np.ndarray]:
    """Split rays sorted by domain into one array per domain with a nonzero count."""
    ends = np.cumsum(counts)
    return [sorted_rays[e - c:e] for c, e in zip(counts, ends, strict=True) if c]


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
        self._stats_lock = threading.Lock()  # render workers share one tracer
        #: When a list, every query appends its (origins, directions): benchmarks replay them.
        self.record: list | None = None
        self.lo, self.hi = store.domain_boxes()  # (D, 3) float64 each
        self.box_magnitude = float(max(np.abs(self.lo).max(initial=0), np.abs(self.hi).max(initial=0)))
        self.nonempty = np.array([d.n_triangles > 0 for d in store.domains], dtype=bool)
        # Rays per traversal chunk: bounds the (domains x rays) entry-distance matrix to 64 MB.
        self._chunk = max(4096, (8 << 20) // max(1, int(self.nonempty.sum())))
        threads = threads or os.cpu_count() or 1
        self.pool = ThreadPoolExecutor(threads) if threads > 1 else None

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()

    def _count_visit(self, domain: int, n_rays: int) -> None:
        with self._stats_lock:
            self.stats.domains_entered.add(domain)
            self.stats.ray_domain_tests += n_rays

    def _all_fit(self) -> bool:
        return self.cache.capacity >= int(self.nonempty.sum())

    def _chunk_size(self, n: int) -> int:
        """Rays traversed together. Front-to-back waves keep a (domains x rays) matrix, so they
        go in chunks; a cache-bound traversal takes all rays at once to load each domain once."""
        return self._chunk if self._all_fit() else max(n, 1)

    def _visits(self, slabs: RaySlabs, limit: np.ndarray, live: np.ndarray | None = None):
        """Yield ``(domain, rows)``: the rays to test against each domain, in visiting order.

        ``limit`` (the closest hit so far, or a shadow ray's length) and ``live`` may change
        between yields; each visit reads them afresh, so rays stop visiting domains that start
        beyond what they already found.

        When every domain fits in the cache, rays walk their own domains front to back in
        waves (wave k = each ray's k-th nearest box). Otherwise each domain is visited once,
        resident domains first, then by waiting rays (LoadAnyOnce), to bound reloads.
        """
        ids = np.nonzero(self.nonempty)[0]
        if self._all_fit():
            yield from self._front_to_back(slabs, ids, limit, live)
            return
        waiting = {d: np.count_nonzero(self._entering(slabs, d, limit)) for d in ids}
        resident = set(self.cache.resident())
        for d in sorted((d for d in ids if waiting[d]),
                        key=lambda d: (d not in resident, -waiting[d], d)):
            entering = self._entering(slabs, d, limit)
            rows = np.nonzero(entering if live is None else entering & live)[0]
            if len(rows):
                yield d, rows

    def _front_to_back(self, slabs: RaySlabs, ids: np.ndarray, limit: np.ndarray,
                       live: np.ndarray | None):
        n = len(limit)
        entry = np.empty((len(ids), n), np.float32)  # (D, n) distance to each box, inf where missed
        for row, d in enumerate(ids):
            t0, t1 = slabs.intervals(self.lo[d], self.hi[d], near=entry[row])
            np.maximum(t0, 0.0, out=t0)
            t0[(t0 > t1) | (t1 < 0)] = np.inf
        rays = np.arange(n)
        for _ in range(len(ids)):
            # Wave: each remaining ray's nearest unvisited box. A ray whose nearest box starts
            # beyond its limit (or that is no longer live) is done: the rest are farther still.
            nearest = entry.argmin(axis=0)
            columns = np.arange(len(rays))
            distance = entry[nearest, columns]
            active = distance < limit[rays]
            if live is not None:
                active &= live[rays]
            if not active.any():
                return
            keep = np.nonzero(active)[0]
            rays, nearest, entry = rays[keep], nearest[keep], entry[:, keep]
            entry[nearest, np.arange(len(rays))] = np.inf
            # Group the wave's rays by domain (a stable radix sort on small integers).
            order = np.argsort(nearest.astype(np.uint16), kind="stable")
            counts = np.bincount(nearest, minlength=len(ids))
            for row, group in zip(np.nonzero(counts)[0], _groups(rays[order], counts),
                                  strict=True):
                yield int(ids[row]), group

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
        with self._stats_lock:
            self.stats.rays[kind] += n
        if self.record is not None:
            self.record.append((origins, directions))
        best = np.full(n, np.inf, dtype=np.float32)
        normal = np.zeros((n, 3), dtype=np.float32)
        material = np.zeros(n, dtype=np.int64)
        color = np.zeros((n, 3)) if self.color_source else None
        chunk = self._chunk_size(n)
        for start in range(0, n, chunk):
            part = slice(start, min(n, start + chunk))
            self._intersect_part(origins[part], directions[part], best[part], normal[part],
                                 material[part], None if color is None else color[part])
        t = best.astype(np.float64)
        n64 = normal.astype(np.float64)
        length = np.linalg.norm(n64, axis=1, keepdims=True)
        n64 /= np.where(length > 0, length, 1.0)
        return Hits(t=t, normal=n64, material=material, color=color)

    def _intersect_part(self, origins, directions, best, normal, material, color) -> None:
        """Closest hits of a chunk of rays, written into the given views."""
        slabs = RaySlabs(origins, directions, self.box_magnitude)
        for d, idx in self._visits(slabs, best):
            self._count_visit(d, len(idx))
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
        with self._stats_lock:
            self.stats.rays["shadow"] += n
        if self.record is not None:
            self.record.append((origins, directions))
        blocked = np.zeros(n, dtype=bool)
        chunk = self._chunk_size(n)
        for start in range(0, n, chunk):
            part = slice(start, min(n, start + chunk))
            o, d_, limit, out = origins[part], directions[part], t_max[part], blocked[part]
            live = np.ones(len(o), dtype=bool)
            for d, idx in self._visits(RaySlabs(o, d_, self.box_magnitude), limit, live):
                self._count_visit(d, len(idx))
                bvh = self.cache.get(d)
                out[idx] = bvh.occluded(o[idx], d_[idx], limit[idx], self.pool)
                live[idx] = ~out[idx]
        return blocked
