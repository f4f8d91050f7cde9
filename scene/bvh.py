"""One Embree scene (BVH) per loaded domain, queried with structure-of-arrays ray batches.

Scenes are built and traced through our compiled binding (``vastray.scene.embree``): the
domain's (memory-mapped) arrays are Embree's buffers, and queries run in numba kernels over
the caller's thread count without the GIL. Where that binding is unavailable, embreex's
``run`` is used as before (same results: both use Embree's robust scene flag).
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from embreex import mesh_construction, rtcore, rtcore_scene

from vastray.scene.cpus import available_cpus
from vastray.scene.embree.kernels import PIECE_TRIANGLES
from vastray.scene.embree.library import binding
from vastray.scene.embree.scenes import Scene
from vastray.scene.footprint import resident_bytes
from vastray.scene.store import DomainArrays

#: Below this many rays a query runs on the calling thread only.
_SPLIT_MIN = 16384


_device: rtcore.EmbreeDevice | None = None
_device_lock = threading.Lock()


def embree_device() -> rtcore.EmbreeDevice:
    """The process's one Embree device, shared by every domain's scene.

    Unless given one, embreex makes a new device for every scene, and a process holding about
    a thousand of them crashes (a segfault between 1,000 and 1,250 live scenes, measured with
    embreex 4.4): a store of thousands of domains, all resident, needs one shared device.
    Embree devices are thread-safe; scenes built and queried on different threads may share one.
    """
    global _device
    with _device_lock:
        if _device is None:
            _device = rtcore.EmbreeDevice()
        return _device


class DomainBVH:
    """A domain's triangles in an Embree scene, plus the attributes shading will need.

    Parameters
    ----------
    domain_id : the domain's id in the store.
    arrays : its triangles. With the compiled binding, Embree uses the vertex and index
        arrays in place (memory-mapped or not; no copy) and they stay referenced until the scene
        is released; with embreex they are copied into Embree's buffers.
    keep : names of the attributes (``"objects"``, ``"colors"``, ``"scalars"``) to keep for
        shading; the others are dropped at once (the scene does not use them).
    pool : the threads queries of this domain use by default: its size is the number of parts
        a compiled query is split into (``embree.launch.launch``; embreex fallback: the rays are
        split over the pool); None: the calling thread only.
    build_quality : Embree's ``RTCBuildQuality`` for the BVH (``RTC_BUILD_QUALITY_LOW``:
        faster to build, the same hits); None: Embree's default (MEDIUM). The embreex
        fallback ignores it.
    mesh_quality : the mesh's ``RTCBuildQuality`` (``RTC_BUILD_QUALITY_LOW``: Embree's Morton
        builder over Embree's compact triangle layout, ``scene.bvh_choice``'s fast BVH); None:
        Embree's default. The embreex fallback ignores it.

    The Embree scene is released by ``close()``, or when the last reference goes (a cache's
    eviction drops its reference; a query in flight on another thread keeps the domain alive
    until it returns).
    """

    def __init__(self, domain_id: int, arrays: DomainArrays, keep: frozenset[str] = frozenset(),
                 pool: ThreadPoolExecutor | None = None, build_quality: int | None = None,
                 mesh_quality: int | None = None):
        self.domain_id = domain_id
        self.pool = pool
        self.n_triangles = arrays.n_triangles
        self._array_bytes = arrays.nbytes()
        self._fast = mesh_quality is not None  # Embree's Morton builder: more bytes
        self.compiled = binding() is not None
        if self.compiled:
            self._scene = Scene(arrays.vertices, arrays.indices, build_quality=build_quality,
                                mesh_quality=mesh_quality, compact=self._fast,
                                piece_triangles=PIECE_TRIANGLES if self._fast else None)
        else:
            self._scene = rtcore_scene.EmbreeScene(embree_device())
            mesh_construction.TriangleMesh(
                self._scene,
                np.ascontiguousarray(arrays.vertices, dtype=np.float32),
                np.ascontiguousarray(arrays.indices, dtype=np.uint32),
            )
            # embreex builds the BVH on the first query: do it now, so load time includes it.
            self._scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32),
                            query="DISTANCE")
        # Vertices and indices stay reachable for rebuilding hit points
        # (``ClosestHits.rebuild_points``): the compiled scene's own (shared) arrays, or the
        # store's (no copy where they are contiguous).
        if self.compiled and self._scene.indices is not None:
            self.vertices = np.asarray(self._scene.vertices)
            self.indices = np.asarray(self._scene.indices)
        else:
            self.vertices = np.ascontiguousarray(arrays.vertices, dtype=np.float32)
            self.indices = np.ascontiguousarray(arrays.indices, dtype=np.uint32)
        self.objects = (np.array(arrays.objects) if "objects" in keep and arrays.objects is not None
                        else None)
        self.colors = np.array(arrays.colors) if "colors" in keep and arrays.colors is not None else None
        self.scalars = (np.array(arrays.scalars) if "scalars" in keep and arrays.scalars is not None
                        else None)

    def nbytes(self) -> int:
        """Resident bytes (``scene.footprint``): the domain's arrays as read and Embree's scene;
        the attributes kept for shading are among the arrays."""
        return resident_bytes(self.n_triangles, self._array_bytes, self.compiled,
                              self._fast)

    def intersect(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray,
                  pool: ThreadPoolExecutor | None = None) -> dict[str, np.ndarray]:
        """Closest hits closer than ``t_far``.

        Parameters
        ----------
        origins, directions : (n, 3) float32
        t_far : (n,) float32 (not modified)
        pool : the threads to use (default: the domain's ``pool``): the compiled query is
            split into as many parts as it has threads (embreex fallback: the rays are split
            over it; Embree releases the GIL).

        Returns
        -------
        dict with ``primID`` (n,) int32 (-1 = no hit), ``tfar`` (n,) float32, ``u``, ``v`` (n,)
        float32 barycentrics and ``Ng`` (n, 3) float32 unnormalised geometric normals.
        """
        if self.compiled:
            return self._scene.intersect(origins, directions, t_far, _threads(pool or self.pool))

        def run(sl):
            return self._scene.run(origins[sl], directions[sl], dists=t_far[sl].copy(), output=1)

        parts = _map_chunks(run, len(origins), pool or self.pool)
        if len(parts) == 1:
            return parts[0]
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    def occluded(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray,
                 pool: ThreadPoolExecutor | None = None) -> np.ndarray:
        """Whether anything lies between each origin and ``t_far``.

        Returns
        -------
        (n,) bool
        """
        if self.compiled:
            return self._scene.occluded(origins, directions, t_far, _threads(pool or self.pool))

        def run(sl):
            return self._scene.run(origins[sl], directions[sl], dists=t_far[sl].copy(),
                                   query="OCCLUDED") >= 0

        return np.concatenate(_map_chunks(run, len(origins), pool or self.pool))

    def close(self) -> None:
        """Release the Embree scene now (compiled binding; embreex's is freed with the object).
        No query may run on this domain afterwards."""
        if self.compiled:
            self._scene.close()


def _threads(pool: ThreadPoolExecutor | None) -> int:
    """Threads for one query of the compiled kernels: the pool's size (None: one)."""
    return pool._max_workers if pool is not None else 1


def query_pool(threads: int | None) -> ThreadPoolExecutor | None:
    """Threads for Embree queries: ``threads`` (default: every CPU this process may use), or None for one.
    The caller shuts the pool down. (The compiled binding uses only the pool's size, as the
    number of parts a query is split into; the embreex fallback runs on the pool's threads.)"""
    threads = threads or available_cpus()
    return ThreadPoolExecutor(threads, thread_name_prefix="embree") if threads > 1 else None


def _map_chunks(fn, n: int, pool: ThreadPoolExecutor | None) -> list:
    if pool is None or n < _SPLIT_MIN:
        return [fn(slice(0, n))]
    k = pool._max_workers
    bounds = np.linspace(0, n, k + 1).astype(int)
    return list(pool.map(fn, [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=False)]))
