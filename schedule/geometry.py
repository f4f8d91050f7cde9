"""Where rays meet domain boxes: the next domain along a ray, or every domain it crosses."""

from __future__ import annotations

import numpy as np

from vastray.render.tracer import RaySlabs, box_pad


class DomainGeometry:
    """Domain boxes and the ray-box questions schedulers ask.

    Box distances are clamped at 0 (a ray starting inside a box enters it at 0). Domains along
    a ray are ordered by (entry distance, domain id), so ties have one answer.

    Parameters
    ----------
    lo, hi : (D, 3) domain boxes.
    nonempty : (D,) bool, domains with triangles (the others are never visited).
    origin_bound : largest |coordinate| of ray origins (scene and camera), for the box padding.
    """

    def __init__(self, lo: np.ndarray, hi: np.ndarray, nonempty: np.ndarray,
                 origin_bound: float):
        self.lo, self.hi = lo, hi
        self.ids = np.nonzero(nonempty)[0]
        self.n_domains = len(lo)
        self.box_magnitude = float(max(np.abs(lo).max(initial=0), np.abs(hi).max(initial=0)))
        self.origin_bound = max(origin_bound, 2.0 * self.box_magnitude)

    def _entries(self, origins, directions):
        """Yield (domain, entry (n,) float32 with inf where the ray misses the box)."""
        slabs = RaySlabs(origins, directions,
                         box_pad(self.box_magnitude, self.origin_bound, origins))
        for d in self.ids:
            t0, t1 = slabs.intervals(self.lo[d], self.hi[d])
            entry = np.maximum(t0, np.float32(0))
            entry[(t0 > t1) | (t1 < 0)] = np.inf
            yield int(d), entry

    def next_domain(self, origins: np.ndarray, directions: np.ndarray, after_t: np.ndarray,
                    after_d: np.ndarray, limit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The first domain after (after_t, after_d) along each ray that starts before ``limit``.

        Parameters
        ----------
        origins, directions : (n, 3) float32
        after_t, after_d : (n,) the last domain visited (-inf, -1 for none yet)
        limit : (n,) float32, the closest hit so far or the shadow ray's length

        Returns
        -------
        domain : (n,) int32, -1 where there is none
        entry : (n,) float32 its entry distance
        """
        n = len(origins)
        best_d = np.full(n, -1, np.int32)
        best_e = np.full(n, np.inf, np.float32)
        for d, entry in self._entries(origins, directions):
            later = (entry > after_t) | ((entry == after_t) & (d > after_d))
            take = later & (entry < limit) & (entry < best_e)  # ids ascend: ties keep the lower
            best_d[take] = d
            best_e[take] = entry[take]
        return best_d, best_e

    def crossings(self, origins: np.ndarray, directions: np.ndarray, limit: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every (ray, domain) pair whose box the ray enters before ``limit``.

        Returns
        -------
        ray, domain : (m,) int64 / int32
        entry : (m,) float32
        rank : (m,) int32, the domain's position along the ray (0 = nearest), SpRay's
            "domain hit depth"
        """
        rays, domains, entries = [], [], []
        for d, entry in self._entries(origins, directions):
            rows = np.nonzero(entry < limit)[0]
            rays.append(rows)
            domains.append(np.full(len(rows), d, np.int32))
            entries.append(entry[rows])
        if not rays:
            empty = np.zeros(0, np.int64)
            return empty, empty.astype(np.int32), empty.astype(np.float32), empty.astype(np.int32)
        ray, domain, entry = np.concatenate(rays), np.concatenate(domains), np.concatenate(entries)
        order = np.lexsort((domain, entry, ray))
        ray, domain, entry = ray[order], domain[order], entry[order]
        first = np.searchsorted(ray, ray, side="left")
        rank = (np.arange(len(ray)) - first).astype(np.int32)
        return ray, domain, entry, rank
