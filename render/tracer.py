"""Closest-hit and occlusion queries over a store split into domains.

A ray's closest hit is final only when every domain it has not visited starts beyond that hit
(domain boxes may overlap). Each query visits every domain whose box the ray enters before its
current closest hit, once: nearest first when all domains are resident, else resident domains
first and then those with the most waiting rays (the image-plane schedule, Navrátil's
LoadAnyOnce). The result does not depend on that order: the minimum over domains is the same
whichever domain comes first.

Two levels: when every domain fits in the cache, a query first goes, one Embree query per ray,
through a top-level scene holding an instance of every resident domain (``embree.scenes.TopScene``);
only domains not resident yet are then visited one by one (which loads them), and once all the
domains rays enter are resident no ray-box work is left at all. Ties between domains still go
to the lower domain id, so the hits, and the image, are the same bit for bit. A store of one
domain needs no top level: its own scene takes every ray, with no ray-box work either. A
bounded cache (out of core) keeps the per-domain queries.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from vastray.render import kernels
from vastray.render.boxtree import BoxTree
from vastray.render.materials import NAN_COLOR, ScalarMap, color_table, colormap
from vastray.scene.cache import DomainCache
from vastray.scene.cpus import available_cpus
from vastray.scene.embree.scenes import TopScene
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
    point : (n, 3) float64 hit point rebuilt from the triangle and barycentrics, and
    error : (n,) float64 its error bound (``kernels.hit_points``); None: shading takes
        ``o + t d`` (hits made up in tests).
    """

    t: np.ndarray
    normal: np.ndarray
    material: np.ndarray
    color: np.ndarray | None
    point: np.ndarray | None = None
    error: np.ndarray | None = None

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.t)

    def take(self, rows: np.ndarray) -> Hits:
        return Hits(self.t[rows], self.normal[rows], self.material[rows],
                    *(None if a is None else a[rows]
                      for a in (self.color, self.point, self.error)))


def facing(normal: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Normals flipped to face against the incoming ``direction`` (surfaces are two-sided).

    Parameters
    ----------
    normal, direction : (k, 3)

    Returns
    -------
    (k, 3)
    """
    side = np.where(np.einsum("ij,ij->i", normal, direction) > 0, -1.0, 1.0)
    return normal * side[:, None]


@dataclass
class ClosestHits:
    """The closest hit found so far for each of n rays, as domains report theirs.

    A hit replaces the current one when it is nearer, or equally near in a domain with a lower
    id: ties never depend on the order in which domains were visited.

    Attributes
    ----------
    t : (n,) float32 (inf = none yet); domain : (n,) int32 domain of the hit
    ng : (n, 3) float32 unnormalised geometric normal; material : (n,) int64
    color : (n, 3) float64 or None
    point : (n, 3) float64 hit point and error : (n,) float64 its bound, rebuilt from the
        winning triangle (``kernels.hit_points``); None for records that only keep distances.
    """

    t: np.ndarray
    domain: np.ndarray
    ng: np.ndarray
    material: np.ndarray
    color: np.ndarray | None
    point: np.ndarray | None = None
    error: np.ndarray | None = None

    @staticmethod
    def empty(n: int, with_color: bool) -> ClosestHits:
        return ClosestHits(np.full(n, np.inf, np.float32), np.full(n, NO_DOMAIN, np.int32),
                           np.zeros((n, 3), np.float32), np.zeros(n, np.int64),
                           np.zeros((n, 3)) if with_color else None,
                           np.zeros((n, 3)), np.zeros(n))

    def rebuild_points(self, won: np.ndarray, bvh, prim: np.ndarray, u: np.ndarray,
                       v: np.ndarray) -> None:
        """Store the hit points of rays ``won`` ((k,)) on triangles ``prim`` of ``bvh`` at
        barycentrics ``u, v`` (where this record keeps points)."""
        if self.point is None or len(won) == 0:
            return
        kernels.hit_points(np.ascontiguousarray(won, np.int64),
                           np.ascontiguousarray(prim, np.int32),
                           np.ascontiguousarray(u, np.float32),
                           np.ascontiguousarray(v, np.float32),
                           bvh.vertices, bvh.indices, self.point, self.error)

    def offer(self, rows: np.ndarray, domain: int, bvh, r: dict, color_source: str | None,
              scalar_range: tuple[float, float]) -> np.ndarray:
        """Take the hits of ``domain`` (Embree output ``r`` for the rays ``rows``) that win.

        Returns
        -------
        (k,) bool, which of ``rows`` improved.
        """
        if (self.t.dtype == np.float32 and self.domain.dtype == np.int32
                and self.ng.dtype == np.float32 and r["Ng"].dtype == np.float32):
            rows = np.ascontiguousarray(rows, np.int64)
            got = np.empty(len(rows), np.bool_)
            kernels.offer(rows, np.int64(domain), r["primID"], r["tfar"], r["Ng"], self.t,
                          self.domain, self.ng, got)  # the comparison and stores below, fused
            if not got.any():
                return got
            won = rows[got]
            prim = r["primID"][got]
        else:
            t_old = self.t[rows]
            got = (r["primID"] >= 0) & ((r["tfar"] < t_old)
                                        | ((r["tfar"] == t_old) & (domain < self.domain[rows])))
            if not got.any():
                return got
            won = rows[got]
            prim = r["primID"][got]
            self.t[won] = r["tfar"][got]
            self.domain[won] = domain
            self.ng[won] = r["Ng"][got]
        if bvh.objects is not None:
            self.material[won] = bvh.objects[prim]
        if self.color is not None:
            self.color[won] = vertex_color(bvh, prim, r["u"][got], r["v"][got], color_source,
                                           scalar_range)
        self.rebuild_points(won, bvh, prim, r["u"][got], r["v"][got])
        return got

    def hits(self, rows: np.ndarray | slice = slice(None)) -> Hits:
        """The hits of ``rows`` with float64 distances and unit normals."""
        ng = np.ascontiguousarray(self.ng[rows])
        n64 = np.empty(ng.shape)
        kernels.unit_normals(ng, n64)  # ng / norm(ng) in one pass, bit for bit
        return Hits(self.t[rows].astype(np.float64), n64, self.material[rows],
                    *(None if a is None else a[rows]
                      for a in (self.color, self.point, self.error)))


NO_DOMAIN = np.iinfo(np.int32).max


def _fusable(r: dict, bvh) -> bool:
    """Whether ``one_domain_hits`` takes Embree's output ``r`` of ``bvh`` as it is (the
    compiled binding's dtypes; the embreex fallback may differ)."""
    return (r["primID"].dtype == np.int32 and r["tfar"].dtype == np.float32
            and r["u"].dtype == np.float32 and r["v"].dtype == np.float32
            and r["Ng"].dtype == np.float32 and r["Ng"].flags.c_contiguous
            and bvh.vertices.dtype == np.float32 and bvh.vertices.flags.c_contiguous
            and bvh.indices.flags.c_contiguous and bvh.indices.dtype in (np.uint32, np.int32))


def one_domain_hits(bvh, r: dict, color_source: str | None,
                    scalar_range: tuple[float, float]) -> Hits:
    """The hits of rays whose only domain is ``bvh`` (Embree output ``r`` for all n of them),
    bit for bit what ``ClosestHits.offer`` into an empty record and ``ClosestHits.hits``
    give, in one compiled pass (``kernels.one_domain_hits``: no record, no gathers between
    them; 5 % of a one-domain render, ``bench/peers.py``'s scene, issue 39)."""
    n = len(r["primID"])
    t, normal, point, error = np.empty(n), np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
    kernels.one_domain_hits(r["primID"], r["tfar"], r["u"], r["v"], r["Ng"], bvh.vertices,
                            bvh.indices, t, normal, point, error)
    material = np.zeros(n, np.int64)
    color = np.zeros((n, 3)) if color_source is not None else None
    if bvh.objects is not None or color is not None:
        won = np.nonzero(r["primID"] >= 0)[0]
        prim = r["primID"][won]
        if bvh.objects is not None:
            material[won] = bvh.objects[prim]
        if color is not None:
            color[won] = vertex_color(bvh, prim, r["u"][won], r["v"][won], color_source,
                                      scalar_range)
    return Hits(t, normal, material, color, point, error)


def vertex_color(bvh, prim, u, v, color_source: str, scalar_range) -> np.ndarray:
    """Per-vertex colour, or the colour-mapped scalar, interpolated at barycentrics (u, v).

    Returns
    -------
    (k, 3) float64
    """
    if color_source != "colors" and bvh.scalars.dtype == np.float32:
        # in one compiled pass (``kernels.scalar_colors``), bit for bit the numpy below
        lo, hi, *lut = scalar_range  # a ScalarMap, or (lo, hi)
        out = np.empty((len(prim), 3))
        kernels.scalar_colors(np.ascontiguousarray(prim, np.int32),
                              np.ascontiguousarray(u, np.float32),
                              np.ascontiguousarray(v, np.float32),
                              np.ascontiguousarray(bvh.indices), np.ascontiguousarray(bvh.scalars),
                              float(lo), float(hi),
                              np.ascontiguousarray(color_table(lut[0] if lut else None), np.float64),
                              NAN_COLOR, out)
        return out
    tri = bvh.indices[prim]
    w = np.stack([1.0 - u - v, u, v], axis=1).astype(np.float64)
    if color_source == "colors":
        return np.einsum("kj,kjc->kc", w, bvh.colors[tri].astype(np.float64))
    scalar = np.einsum("kj,kj->k", w, bvh.scalars[tri].astype(np.float64))
    return colormap(scalar, *scalar_range)


@dataclass
class TraceStats:
    """Work counters of a tracer."""

    rays: dict = field(default_factory=lambda: {"camera": 0, "bounce": 0, "shadow": 0})
    #: Camera rays that missed the scene's box: never queried, so not in ``rays``.
    camera_escaped: int = 0
    ray_domain_tests: int = 0
    domains_entered: set = field(default_factory=set)


def box_pad(box_magnitude: float, origin_bound: float, origins: np.ndarray) -> float:
    """Box growth for ``RaySlabs``: constant for rays whose origins stay within
    ``origin_bound`` (the scene and the camera), larger only for rays that start farther out."""
    bound = max(origin_bound, float(np.abs(origins).max(initial=0.0)))
    return 2.0 ** -19 * (box_magnitude + bound)


class RaySlabs:
    """Per-axis ray data for slab tests in float32, computed once per query.

    Direction components that are exactly zero are replaced by a tiny signed value for the box
    test only: the slab then spans (-huge, +huge) when the origin lies inside it and is missed
    otherwise, which is the exact answer, without NaNs from ``0 * inf``.

    Float32 rounding moves a computed slab distance by at most a few ulps of the largest
    coordinate involved, ``M = max|origin| + max|box|``; growing every box by ``2^-19 M`` (16
    times that bound) keeps the test conservative: a ray may visit a box it barely misses,
    never skip one it enters. ``pad`` is that growth; callers keep it the same for a whole
    render (see ``box_pad``), so a ray's box distances never depend on its batch.

    Parameters
    ----------
    origins, directions : (n, 3) float32
    pad : how far to grow every box.
    """

    def __init__(self, origins: np.ndarray, directions: np.ndarray, pad: float):
        n = origins.shape[0]
        #: (6, n) float32, C-contiguous: origins (rows 0-2) and inverse directions (3-5), the
        #: layout ``BoxTree`` reads; ``origin`` and ``inv`` are views of it.
        self.rays = np.empty((6, n), np.float32)
        self.origin, self.inv = self.rays[:3], self.rays[3:]
        d = directions.T.astype(np.float32)  # (3, n)
        d[d == 0] = np.float32(1e-30)
        self.origin[:] = origins.T
        with np.errstate(over="ignore"):
            np.divide(np.float32(1.0), d, out=self.inv)
        self.pad = pad
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


class DomainTracer:
    """Traces ray batches through the domains of a store, loading them through a cache.

    Parameters
    ----------
    store : the domain store.
    cache : the domain cache (its capacity bounds memory).
    color_source : ``"colors"``, ``"scalars"`` or None: the per-vertex data shading uses.
    scalars : how scalars become colours (``render.colormaps.scalar_map``); None: the store's
        range on the built-in table.
    threads : Embree query threads (Embree releases the GIL).
    two_level : when the cache holds every domain and the compiled Embree binding is in use,
        query resident domains through one top-level scene of instances (the default); False:
        domain by domain always (the same hits; for comparisons).
    """

    def __init__(self, store: Store, cache: DomainCache, color_source: str | None = None,
                 threads: int | None = None, two_level: bool = True,
                 scalars: ScalarMap | None = None):
        self.store = store
        self.cache = cache
        self.color_source = color_source
        lo, hi = store.scalar_range or (0.0, 1.0)
        self.scalar_range = ScalarMap(lo, hi) if scalars is None else scalars
        self.stats = TraceStats()
        self._stats_lock = threading.Lock()  # render workers share one tracer
        #: When a list, every query appends its (origins, directions): benchmarks replay them.
        self.record: list | None = None
        self.lo, self.hi = store.domain_boxes()  # (D, 3) float64 each
        self.box_magnitude = float(max(np.abs(self.lo).max(initial=0), np.abs(self.hi).max(initial=0)))
        #: Largest origin coordinate expected (the camera is set by the renderer).
        self.origin_bound = 2.0 * self.box_magnitude
        self.nonempty = np.array([d.n_triangles > 0 for d in store.domains], dtype=bool)
        self.tree_ids = np.nonzero(self.nonempty)[0]
        #: The non-empty domains' boxes in a BVH (``BoxTree``), for the ray-box queries.
        self.tree = BoxTree(self.lo, self.hi, self.tree_ids)
        threads = threads or available_cpus()
        self.pool = ThreadPoolExecutor(threads) if threads > 1 else None
        self.two_level = two_level
        #: (resident domain ids, their TopScene or None, the boxes of the non-empty domains
        #: not resident, in a BoxTree)
        self._top: tuple[frozenset, TopScene | None, BoxTree] | None = None
        self._top_lock = threading.Lock()

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()
        with self._top_lock:
            top, self._top = self._top, None
        if top is not None and top[1] is not None:
            top[1].close()

    def _top_level(self) -> tuple[TopScene | None, BoxTree, dict] | None:
        """The top-level scene of the resident domains, a ``BoxTree`` of the non-empty
        domains not resident (the only ones still visited one by one: rays test their boxes
        only) and the resident ``DomainBVH`` by id; None where queries go domain by domain (the
        cache cannot hold every domain, ``two_level`` is off, or the compiled binding is not
        in use).

        The scene is rebuilt (a BVH over the instances' boxes only) when the resident set has
        changed since the last query, which happens only while domains are first loaded: with
        every domain fitting, nothing is evicted. A query in flight keeps the scene it got.
        """
        if (not self.two_level or self.cache.capacity < len(self.tree_ids)
                or len(self.tree_ids) < 2):  # one domain: its own scene is the one query
            return None
        resident = self.cache.resident_domains()
        key = frozenset(resident)
        with self._top_lock:
            if self._top is None or self._top[0] != key:
                ids = sorted(d for d in key if self.nonempty[d])
                if any(not resident[d].compiled for d in ids):
                    return None
                # instances in ascending domain id: the filter's ties go to the lower id
                top = (TopScene([resident[d]._scene for d in ids], ids) if ids
                       else None)
                missing = np.setdiff1d(self.tree_ids, np.asarray(ids, np.int64))
                self._top = (key, top, BoxTree(self.lo, self.hi, missing))
            _, top, missing = self._top
        return top, missing, resident

    def _only_domain(self) -> int | None:
        """The one non-empty domain, where the store has just one and queries may skip the
        ray-box test (``two_level``, as the top-level scene does for several): its Embree
        query rejects the rays that miss its box itself. None otherwise."""
        if self.two_level and len(self.tree_ids) == 1:
            return int(self.tree_ids[0])
        return None

    def slabs(self, origins: np.ndarray, directions: np.ndarray) -> RaySlabs:
        return RaySlabs(origins, directions,
                        box_pad(self.box_magnitude, self.origin_bound, origins))

    def count_escaped(self, n_rays: int) -> None:
        """Count ``n_rays`` camera rays that miss the scene's box, never queried
        (``integrators.seen_camera_rays``): ``rays`` counts the rays traced."""
        with self._stats_lock:
            self.stats.camera_escaped += n_rays

    def _count_visit(self, domain: int, n_rays: int) -> None:
        with self._stats_lock:
            self.stats.domains_entered.add(domain)
            self.stats.ray_domain_tests += n_rays

    def _visits(self, slabs: RaySlabs, limit: np.ndarray, live: np.ndarray | None = None,
                tree: BoxTree | None = None):
        """Yield ``(domain, rows)``: the rays to test against each domain, in visiting order.

        ``limit`` (the closest hit so far, or a shadow ray's length) and ``live`` may change
        between yields; each visit reads them afresh, so rays skip domains that start beyond
        what they already found. Which rays enter which boxes is found once per query, by
        walking the tree of domain boxes, each ray in compiled code (``BoxTree.entered``; with
        ``tree.compiled`` off, numpy's ``BoxTree.pairs``): the cost grows with the domains the
        rays cross, not with the domain count. With few domains (``tree.flat``) one numpy pass
        tests every ray against every box instead: no grouping by domain is needed after it,
        and it measured faster than the compiled walk (one domain, ``bench/peers.py``'s scene:
        0.05 s against 0.13 s of a 2.7 s render, plus the grouping). A visit's rows are the
        rays for which ``(t0 <= t1) & (t1 >= 0) & (t0 < limit) & live`` holds at that moment,
        ascending, as the per-domain slab test gave them.

        When every domain fits in the cache, domains are visited nearest first as seen from
        the batch's mean origin (cheap, and measured faster than per-ray front-to-back waves,
        whose bookkeeping costs more than the Embree work it saves). Otherwise each domain is
        visited once, resident ones first, then by waiting rays (LoadAnyOnce), so a bounded
        cache reloads as little as possible.

        ``tree`` : the boxes of the domains to visit (default: every non-empty domain's).
        """
        all_fit = self.cache.capacity >= len(self.tree_ids)
        tree = self.tree if tree is None else tree
        if tree.flat:  # few domains: every ray against every box, (m, n) at once
            t0, t1 = tree.flat_intervals(slabs)
            ahead = (t0 <= t1) & (t1 >= 0)
            domains = tree.flat_ids
            waiting = (np.ones(len(domains), np.int64) if all_fit  # (empty visits yield nothing)
                       else np.count_nonzero(ahead & (t0 < limit), axis=1))

            def rows_of(i: int) -> np.ndarray:
                rows = ahead[i] & (t0[i] < limit)
                if live is not None:
                    rows &= live
                return np.nonzero(rows)[0]
        else:
            if tree.compiled and np.asarray(limit).dtype == np.float32:
                # each ray walks the tree in compiled code (``render.boxwalk``)
                ray, dom, t0 = tree.entered(slabs, limit)
            else:
                ray, dom, t0, t1 = tree.pairs(slabs, limit)
                enter = (t0 <= t1) & (t1 >= 0) & (t0 < limit[ray])
                ray, dom, t0 = ray[enter], dom[enter], t0[enter]
            # Group by domain; rays ascend within a domain in ``pairs`` and a stable sort
            # keeps them so (a radix sort, for 16-bit keys).
            key = dom.astype(np.uint16) if len(self.lo) <= 1 << 16 else dom
            by_domain = np.argsort(key, kind="stable")
            ray, t0 = ray[by_domain], t0[by_domain]
            waiting = np.bincount(dom, minlength=len(self.lo))
            first = np.cumsum(waiting) - waiting
            domains = np.nonzero(waiting)[0]
            waiting, first = waiting[domains], first[domains]

            def rows_of(i: int) -> np.ndarray:
                rows = ray[first[i]:first[i] + waiting[i]]
                still = t0[first[i]:first[i] + waiting[i]] < limit[rows]
                if live is not None:
                    still &= live[rows]
                return rows[still]
        if len(domains) == 1:  # nothing to order
            order = np.zeros(1, np.int64)
        elif all_fit:
            center = slabs.origin.mean(axis=1, dtype=np.float64)
            gap = (np.maximum(self.lo[domains] - center, 0)
                   + np.maximum(center - self.hi[domains], 0))
            order = np.argsort(np.einsum("ij,ij->i", gap, gap), kind="stable")
        else:
            resident = np.isin(domains, np.asarray(self.cache.resident(), np.int64))
            order = np.lexsort((domains, -waiting, ~resident))
        for i in order[waiting[order] > 0]:
            rows = rows_of(i)
            if len(rows):
                yield int(domains[i]), rows

    def _threads(self) -> int:
        return self.pool._max_workers if self.pool is not None else 1

    def _take_top_hits(self, best: ClosestHits, r: dict, resident: dict) -> None:
        """Fill ``best`` (empty so far) from a top-level query's output ``r``.

        Counted as one ray-domain test per ray, and the domains hit as entered (a domain a ray
        crossed without hitting it goes uncounted here).
        """
        rows = np.nonzero(r["primID"] >= 0)[0]
        with self._stats_lock:
            self.stats.ray_domain_tests += len(r["primID"])
        if len(rows) == 0:
            return
        domain = r["id"][rows]
        best.t[rows] = r["tfar"][rows]
        best.domain[rows] = domain
        best.ng[rows] = r["Ng"][rows]
        hit_domains = np.unique(domain)
        with self._stats_lock:
            self.stats.domains_entered.update(int(d) for d in hit_domains)
        for d in hit_domains:
            sub = domain == d
            won, prim = rows[sub], r["primID"][rows[sub]]
            bvh = resident[int(d)]
            best.rebuild_points(won, bvh, prim, r["u"][won], r["v"][won])
            if bvh.objects is not None:
                best.material[won] = bvh.objects[prim]
            if best.color is not None:
                best.color[won] = vertex_color(bvh, prim, r["u"][won], r["v"][won],
                                               self.color_source, self.scalar_range)

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
            self.record.append((kind, origins, directions, None))
        only = self._only_domain()
        if only is not None:
            self._count_visit(only, n)
            bvh = self.cache.get(only)
            r = bvh.intersect(origins, directions, np.full(n, np.inf, np.float32), self.pool)
            if _fusable(r, bvh):
                return one_domain_hits(bvh, r, self.color_source, self.scalar_range)
            best = ClosestHits.empty(n, self.color_source is not None)
            best.offer(np.arange(n), only, bvh, r, self.color_source, self.scalar_range)
            return best.hits()
        best = ClosestHits.empty(n, self.color_source is not None)
        top = self._top_level()
        tree = None
        if top is not None:
            scene, tree, resident = top
            if scene is not None:
                self._take_top_hits(best, scene.intersect(origins, directions,
                                                          np.full(n, np.inf, np.float32),
                                                          self._threads()), resident)
            if tree.size == 0:
                return best.hits()
        slabs = self.slabs(origins, directions)
        for d, idx in self._visits(slabs, best.t, tree=tree):
            self._count_visit(d, len(idx))
            bvh = self.cache.get(d)
            r = bvh.intersect(origins[idx], directions[idx], best.t[idx], self.pool)
            best.offer(idx, d, bvh, r, self.color_source, self.scalar_range)
        return best.hits()

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
            self.record.append(("occluded", origins, directions, t_max))
        only = self._only_domain()
        if only is not None:
            self._count_visit(only, n)
            return self.cache.get(only).occluded(origins, directions, t_max, self.pool)
        blocked = np.zeros(n, dtype=bool)
        top = self._top_level()
        tree = None
        if top is not None:
            scene, tree, _ = top
            if scene is not None:
                blocked = scene.occluded(origins, directions, t_max, self._threads())
                with self._stats_lock:
                    self.stats.ray_domain_tests += n
            if tree.size == 0:
                return blocked
        live = ~blocked
        for d, idx in self._visits(self.slabs(origins, directions), t_max, live, tree=tree):
            self._count_visit(d, len(idx))
            bvh = self.cache.get(d)
            blocked[idx] = bvh.occluded(origins[idx], directions[idx], t_max[idx], self.pool)
            live[idx] = ~blocked[idx]
        return blocked
