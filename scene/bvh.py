"""One Embree scene (BVH) per loaded domain, queried with structure-of-arrays ray batches."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from embreex import mesh_construction, rtcore, rtcore_scene

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
    arrays : its triangles (memory-mapped arrays are copied into Embree's buffers).
    keep : names of the attributes (``"objects"``, ``"colors"``, ``"scalars"``) to keep for
        shading; the others are dropped at once (the scene does not use them).
    """

    def __init__(self, domain_id: int, arrays: DomainArrays, keep: frozenset[str] = frozenset()):
        self.domain_id = domain_id
        self.n_triangles = arrays.n_triangles
        self._scene = rtcore_scene.EmbreeScene(embree_device())
        mesh_construction.TriangleMesh(
            self._scene,
            np.ascontiguousarray(arrays.vertices, dtype=np.float32),
            np.ascontiguousarray(arrays.indices, dtype=np.uint32),
        )
        # embreex builds the BVH on the first query: do it now, so load time includes the build.
        self._scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), query="DISTANCE")
        needs_indices = bool(keep & {"colors", "scalars"})
        self.indices = np.array(arrays.indices) if needs_indices else None
        self.objects = (np.array(arrays.objects) if "objects" in keep and arrays.objects is not None
                        else None)
        self.colors = np.array(arrays.colors) if "colors" in keep and arrays.colors is not None else None
        self.scalars = (np.array(arrays.scalars) if "scalars" in keep and arrays.scalars is not None
                        else None)

    def nbytes(self) -> int:
        """Approximate resident bytes: Embree's copy of the mesh plus kept attributes."""
        kept = [self.indices, self.objects, self.colors, self.scalars]
        return self.n_triangles * (36 + 12 + 64) + sum(a.nbytes for a in kept if a is not None)

    def intersect(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray,
                  pool: ThreadPoolExecutor | None = None) -> dict[str, np.ndarray]:
        """Closest hits closer than ``t_far``.

        Parameters
        ----------
        origins, directions : (n, 3) float32
        t_far : (n,) float32 (not modified)
        pool : optional thread pool; Embree releases the GIL, so chunks run in parallel.

        Returns
        -------
        dict with ``primID`` (n,) int32 (-1 = no hit), ``tfar`` (n,) float32, ``u``, ``v`` (n,)
        float32 barycentrics and ``Ng`` (n, 3) float32 unnormalised geometric normals.
        """
        def run(sl):
            return self._scene.run(origins[sl], directions[sl], dists=t_far[sl].copy(), output=1)

        parts = _map_chunks(run, len(origins), pool)
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
        def run(sl):
            return self._scene.run(origins[sl], directions[sl], dists=t_far[sl].copy(),
                                   query="OCCLUDED") >= 0

        return np.concatenate(_map_chunks(run, len(origins), pool))


def _map_chunks(fn, n: int, pool: ThreadPoolExecutor | None) -> list:
    if pool is None or n < _SPLIT_MIN:
        return [fn(slice(0, n))]
    k = pool._max_workers
    bounds = np.linspace(0, n, k + 1).astype(int)
    return list(pool.map(fn, [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=False)]))
