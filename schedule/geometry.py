"""Where rays meet domain boxes: the next domain along a ray, or every domain it crosses.

With occupancy masks (:mod:`vastray.scene.occupancy`), a domain whose box a ray enters but
whose occupied cells it does not cross is left out of both answers: no triangle of it can be
hit, so a schedule never queues the ray there (nor loads the domain for it). Entry distances,
orders and ties stay those of the boxes: the masks only remove pairs.
"""

from __future__ import annotations

import copy

import numpy as np

from vastray.render import boxwalk
from vastray.render.boxtree import BoxTree
from vastray.render.tracer import RaySlabs, box_pad
from vastray.scene.occupancy import Occupancy


class DomainGeometry:
    """Domain boxes and the ray-box questions schedulers ask.

    Box distances are clamped at 0 (a ray starting inside a box enters it at 0). Domains along
    a ray are ordered by (entry distance, domain id), so ties have one answer. Queries walk a
    ``BoxTree`` over the non-empty domains' boxes: a ray's cost grows with the domains it
    crosses, not with the domain count, and the answers are those of the per-domain slab test
    (``tests/domain_loops.py``) bit for bit.

    Parameters
    ----------
    lo, hi : (D, 3) domain boxes.
    nonempty : (D,) bool, domains with triangles (the others are never visited).
    origin_bound : largest |coordinate| of ray origins (scene and camera), for the box padding.
    occupancy : the domains' occupancy masks (``Store.occupancy``), or None: every cell of
        every box occupied.
    """

    def __init__(self, lo: np.ndarray, hi: np.ndarray, nonempty: np.ndarray,
                 origin_bound: float, occupancy: Occupancy | None = None):
        self.lo, self.hi = lo, hi
        #: The masks queries apply (None: none, or none with an empty cell).
        self.occupancy = occupancy if occupancy is not None and occupancy.any_useful else None
        self.ids = np.nonzero(nonempty)[0]
        self.n_domains = len(lo)
        self.box_magnitude = float(max(np.abs(lo).max(initial=0), np.abs(hi).max(initial=0)))
        self.origin_bound = max(origin_bound, 2.0 * self.box_magnitude)
        self.tree = BoxTree(lo, hi, self.ids)

    def without_masks(self) -> DomainGeometry:
        """The same boxes, queried without the occupancy masks (the same arrays, shared)."""
        plain = copy.copy(self)
        plain.occupancy = None
        return plain

    def slabs(self, origins: np.ndarray, directions: np.ndarray) -> RaySlabs:
        """The rays' slab-test data, padded as every query of this geometry pads its boxes."""
        return RaySlabs(origins, directions,
                        box_pad(self.box_magnitude, self.origin_bound, origins))

    def next_domain(self, origins: np.ndarray, directions: np.ndarray, after_t: np.ndarray,
                    after_d: np.ndarray, limit: np.ndarray, masks: bool = True
                    ) -> tuple[np.ndarray, np.ndarray]:
        """The first domain after (after_t, after_d) along each ray that starts before ``limit``
        (and, with ``masks``, whose occupied cells the ray crosses before ``limit``).

        Parameters
        ----------
        origins, directions : (n, 3) float32
        after_t, after_d : (n,) the last domain visited (-inf, -1 for none yet)
        limit : (n,) float32, the closest hit so far or the shadow ray's length
        masks : apply the occupancy masks (False: the boxes alone).

        Returns
        -------
        domain : (n,) int32, -1 where there is none
        entry : (n,) float32 its entry distance (the box's)
        """
        slabs = self.slabs(origins, directions)
        domain, entry = self.tree.first_after(slabs, after_t, after_d, limit)
        if masks and self.occupancy is not None:
            self._skip_empty(slabs, origins, directions, limit, domain, entry)
        return domain, entry

    def _skip_empty(self, slabs: RaySlabs, origins, directions, limit, domain, entry) -> None:
        """Replace, in place, each ray's ``domain`` (and ``entry``) whose occupied cells it does
        not cross by the next along it that it does: the box after it in (entry, id) order,
        tested again, until one passes or none is left. One compiled walk per round over the
        rays still looking (a ray skips one more empty box per round)."""
        n = len(origins)
        limit = np.broadcast_to(np.asarray(limit), (n,))
        rows = np.nonzero(domain >= 0)[0]
        while len(rows):
            passed = self.occupancy.crosses(origins, directions, rows, domain[rows], limit,
                                            slabs.pad)
            rows = rows[~passed]
            if not len(rows):
                return
            # the same pad as the whole batch's, so the boxes' distances are the same
            sub = RaySlabs(origins[rows], directions[rows], slabs.pad)
            domain[rows], entry[rows] = self.tree.first_after(
                sub, entry[rows], domain[rows], np.ascontiguousarray(limit[rows]))
            rows = rows[domain[rows] >= 0]

    def crossings(self, origins: np.ndarray, directions: np.ndarray, limit: np.ndarray,
                  masks: bool = True, among: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every (ray, domain) pair whose box the ray enters before ``limit`` (and, with
        ``masks``, whose occupied cells it crosses before ``limit``).

        Parameters
        ----------
        origins, directions : (n, 3) float32
        limit : (n,) float32
        masks : apply the occupancy masks (False: the boxes alone).
        among : (D,) bool, the domains asked about (None: every one). The others' pairs are
            dropped before the occupancy test, which costs far more than the box walk (an
            in-situ node asks about its own domains only: the test of every other domain's
            pairs was about 40 % of its time on rm 128³ at 2 nodes).

        Returns
        -------
        ray, domain : (m,) int64 / int32, sorted by ray, then entry, then domain
        entry : (m,) float32
        rank : (m,) int32, the domain's position along the ray among the domains returned
            (0 = nearest), SpRay's "domain hit depth"
        """
        n = len(origins)
        limit = np.broadcast_to(np.asarray(limit), (n,))
        found = self._box_crossings(origins, directions, limit)
        if among is not None:
            ray, domain, entry, _ = found
            asked = among[domain]
            found = ray[asked], domain[asked], entry[asked], _ranks(ray[asked])
        if not masks or self.occupancy is None:
            return found
        ray, domain, entry, _ = found
        keep = self.occupancy.crosses(origins, directions, ray, domain, limit,
                                      box_pad(self.box_magnitude, self.origin_bound, origins))
        if keep.all():
            return found
        ray, domain, entry = ray[keep], domain[keep], entry[keep]
        return ray, domain, entry, _ranks(ray)

    def _box_crossings(self, origins, directions, limit):
        """``crossings`` of the boxes alone (``limit``: (n,))."""
        # The compiled walk compares in float32: a float64 limit takes the numpy walk.
        if self.tree.compiled and limit.dtype == np.float32:
            return self._crossings_compiled(origins, directions, limit)
        parts = []
        for first, stop, ray, domain, t0, t1 in self.tree.pair_chunks(
                self.slabs(origins, directions), limit):
            entry = np.maximum(t0, np.float32(0))
            entry[(t0 > t1) | (t1 < 0)] = np.inf
            keep = entry < limit[ray]
            parts.append(order_crossings(ray[keep], domain[keep], entry[keep], first, stop))
        if not parts:
            return order_crossings(np.zeros(0, np.int64), np.zeros(0, np.int32),
                            np.zeros(0, np.float32), 0, 0)
        # Chunks hold ascending runs of rays: concatenated, they stay sorted by ray.
        return tuple(np.concatenate(p) for p in zip(*parts, strict=True))

    def _crossings_compiled(self, origins, directions, limit):
        """``crossings`` by ``boxwalk.crossings``: each ray walks the tree in compiled code
        and writes its crossings in order; no sort follows."""
        return self.tree.walk_all(boxwalk.crossings, self.slabs(origins, directions), limit,
                                  (np.int64, np.int32, np.float32, np.int32), per_ray=4)


def _ranks(ray: np.ndarray) -> np.ndarray:
    """(m,) int32: each pair's position among its ray's pairs (``ray``: (m,) sorted).

    In one pass over the runs of equal rays, each pair's index less its run's first index
    (a running maximum of the runs' starts), not a binary search of every pair."""
    m = len(ray)
    if m < 2:
        return np.zeros(m, np.int32)
    position = np.arange(m)
    run_start = np.zeros(m, position.dtype)
    np.multiply(ray[1:] != ray[:-1], position[1:], out=run_start[1:])
    np.maximum.accumulate(run_start, out=run_start)
    return (position - run_start).astype(np.int32)


def order_crossings(ray, domain, entry, first: int = 0, stop: int | None = None):
    """Sort (ray, domain, entry) by ray, entry, domain; add each pair's rank along its ray.

    Rays lie in ``first:stop`` (None: anywhere). With fewer than 2^15 rays and 2^17 domains
    the three keys pack into one integer (the bits of a float32 >= 0 sort as the float does;
    -0.0 sorts as +0.0), so one argsort replaces a three-key lexsort.

    Returns
    -------
    ray : (m,) int64; domain : (m,) int32; entry : (m,) float32; rank : (m,) int32
    """
    if stop is not None and stop - first <= 1 << 15 and (len(domain) == 0
                                                         or domain.max() < 1 << 17):
        bits = (entry + np.float32(0)).view(np.uint32).astype(np.int64)  # entry < inf: < 2^31
        key = ((ray - first) << 48) | (bits << 17) | domain
        order = np.argsort(key)
    else:
        order = np.lexsort((domain, entry, ray))
    ray, domain, entry = ray[order], domain[order], entry[order]
    return ray, domain, entry, _ranks(ray)
