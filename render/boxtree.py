"""A bounding volume hierarchy over domain boxes, traversed by whole ray batches at once.

With thousands of domains, testing every ray against every domain box costs O(domains x rays).
``BoxTree`` answers the same questions while visiting only the tree nodes a ray's path comes
near, so a ray's cost grows with the domains it crosses (and the tree's depth, log2 of the
domain count), not with the domain count. Traversals are vectorised over the rays and breadth
first: the Python loop runs once per tree level, over every (ray, node) pair alive, never once
per ray or per domain. With few boxes (``FLAT_BOXES``) a tree is not worth walking: one
broadcast pass tests every ray against every box instead.

Exactness. A leaf holds one box, and its entry and exit distances are computed with exactly the
float32 operations of ``RaySlabs.intervals`` (same padding, same operation order), so they are
bit-identical to the per-box test. An inner node's box is the union of its children's boxes;
float32 rounding is monotone, so a ray's slab interval through a node contains its interval
through every box below it, and a node is skipped only when no box below it can pass (NaN
distances, from denormal direction components, never prune a node). Callers then apply their
own test to the leaf distances, so what they get is what the per-box loop gave them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from vastray.render import boxwalk

if TYPE_CHECKING:  # the tracer builds a BoxTree: import its RaySlabs for annotations only
    from vastray.render.tracer import RaySlabs

#: Rays per breadth-first sweep: bounds the (ray, node) pairs held at once, and keeps them in
#: cache (measured fastest of 512 to 16,384).
CHUNK_RAYS = 1 << 12
#: Up to this many boxes, every ray is tested against every box in one broadcast pass (no
#: Python loop either): cheaper than walking a tree that shallow. Measured, a 128x96, 4 spp
#: path-traced render of the bumpy test scene on one thread (flat / tree / the former
#: per-domain loop): 27 domains 0.26 / 0.37 / 0.26 s, 58 domains 0.36 / 0.42 / 0.39 s,
#: 128 domains 0.60 / 0.55 / 0.65 s, 256 domains 1.26 / 0.70 / 1.14 s.
FLAT_BOXES = 64
#: Ray-box pairs per chunk of the flat pass (its temporaries stay in cache).
FLAT_PAIRS = 1 << 15


class BoxTree:
    """A binary BVH over boxes (one box per leaf), split at the median of box centres along
    the axis where the centres spread most (k-d like for grid and k-d partitions, and still
    sound when boxes overlap).

    Parameters
    ----------
    lo, hi : (D, 3) boxes (float64 as stores give them; the dtype is kept, so padded boxes
        round exactly as in ``RaySlabs.intervals``).
    ids : (m,) int, the boxes to put in the tree (e.g. the non-empty domains); default all.

    Attributes
    ----------
    node_lo, node_hi : (N, 3) node boxes, N = 2m - 1 (node 0 is the root; children come after
        their parent).
    child : (N, 2) int32 children of inner nodes, -1 at leaves.
    box : (N,) int32 box id of leaves, -1 at inner nodes.
    height : int, nodes on the longest root-to-leaf path (a balanced tree: leaves lie on its
        last two levels).
    size : int, m.
    first_leaf_level : int, the level (root = 1) of the shallowest leaf.
    flat : bool, few boxes (``FLAT_BOXES``): queries test every box at once instead of
        walking the tree (set it to choose).
    flat_ids : (m,) int32, the box ids in ascending order (the flat pass's box order).
    """

    def __init__(self, lo: np.ndarray, hi: np.ndarray, ids: np.ndarray | None = None):
        lo, hi = np.asarray(lo), np.asarray(hi)
        ids = np.arange(len(lo)) if ids is None else np.asarray(ids, np.int64)
        m = len(ids)
        self.size = m
        n_nodes = max(2 * m - 1, 0)
        self.node_lo = np.zeros((n_nodes, 3), lo.dtype)
        self.node_hi = np.zeros((n_nodes, 3), hi.dtype)
        self.child = np.full((n_nodes, 2), -1, np.int32)
        self.box = np.full(n_nodes, -1, np.int32)
        self.height = 0
        self.first_leaf_level = 0
        #: Walk each ray in compiled code (``render.boxwalk``) for ``first_after`` and
        #: ``DomainGeometry.crossings``; False: the numpy walks (the same answers, bit for bit).
        self.compiled = True
        self._padded: dict = {}  # pad (or ("nodes", pad)) -> padded boxes
        if m == 0:
            self._finish()
            return
        center = (lo[ids].astype(np.float64) + hi[ids]) / 2.0
        # Level by level. Every node owns a contiguous run of ``perm`` (the boxes in tree
        # order); the runs of a level, leaves included, cover 0..m in ascending order.
        perm = np.arange(m)
        start = np.zeros(1, np.int64)
        count = np.full(1, m, np.int64)
        node = np.zeros(1, np.int64)
        next_node = 1
        while True:
            self.height += 1
            self.node_lo[node] = np.minimum.reduceat(lo[ids[perm]], start, axis=0)
            self.node_hi[node] = np.maximum.reduceat(hi[ids[perm]], start, axis=0)
            leaf = count == 1
            self.box[node[leaf]] = ids[perm[start[leaf]]]
            if leaf.any() and not self.first_leaf_level:
                self.first_leaf_level = self.height
            if leaf.all():
                break
            # Sort each run along its widest axis of box centres (stable: ties keep order).
            c = center[perm]
            spread = np.maximum.reduceat(c, start, axis=0) - np.minimum.reduceat(c, start, axis=0)
            axis = np.argmax(spread, axis=1)
            run = np.repeat(np.arange(len(start)), count)
            perm = perm[np.lexsort((c[np.arange(m), axis[run]], run))]
            # Split inner runs at the median into two new nodes; leaf runs stay as they are.
            inner = ~leaf
            left = (count + 1) // 2
            kids = np.zeros(len(node), np.int64)
            kids[inner] = next_node + 2 * np.arange(np.count_nonzero(inner))
            next_node += 2 * np.count_nonzero(inner)
            self.child[node[inner], 0] = kids[inner]
            self.child[node[inner], 1] = kids[inner] + 1
            width = np.where(leaf, 1, 2)
            pos = np.cumsum(width) - width
            total = int(width.sum())
            new_start, new_count, new_node = (np.empty(total, np.int64) for _ in range(3))
            new_start[pos] = start
            new_count[pos] = np.where(leaf, count, left)
            new_node[pos] = np.where(leaf, node, kids)
            pos = pos[inner]
            new_start[pos + 1] = start[inner] + left[inner]
            new_count[pos + 1] = count[inner] - left[inner]
            new_node[pos + 1] = kids[inner] + 1
            start, count, node = new_start, new_count, new_node
        self._finish()

    def _finish(self) -> None:
        # The compiled walks keep a fixed stack of _STACK nodes (a depth-first walk holds at
        # most height + 1); a deeper tree, which a median split never builds below 2^62
        # boxes, takes the numpy walks rather than writing past it.
        self.compiled = self.compiled and self.height + 1 <= boxwalk._STACK
        self._is_leaf = self.box >= 0
        self._flat_nodes = np.nonzero(self._is_leaf)[0][np.argsort(self.box[self._is_leaf])]
        self.flat_ids = self.box[self._flat_nodes]
        self.flat = self.size <= FLAT_BOXES
        #: Leaf node of each box id (-1: not in the tree).
        self._leaf_of = np.full(int(self.box.max(initial=-1)) + 1, -1, np.int32)
        self._leaf_of[self.box[self._is_leaf]] = np.nonzero(self._is_leaf)[0]

    # -- per query ----------------------------------------------------------------------------
    def padded(self, pad: float) -> np.ndarray:
        """Node boxes grown by ``pad`` in float32, rounded as ``RaySlabs.intervals`` rounds them.

        Returns
        -------
        (6, N) float32: rows 0-2 the low corners, rows 3-5 the high ones.
        """
        got = self._padded.get(pad)
        if got is None:
            got = np.ascontiguousarray(np.concatenate(
                [(self.node_lo - pad).astype(np.float32), (self.node_hi + pad).astype(np.float32)],
                axis=1).T)
            if len(self._padded) > 8:  # a render keeps one pad (``box_pad``): a few suffice
                self._padded.clear()
            self._padded[pad] = got
        return got

    def padded_nodes(self, pad: float) -> np.ndarray:
        """``padded(pad)`` node by node, for the compiled walks (``render.boxwalk``).

        Returns
        -------
        (N, 6) float32, C-contiguous: columns 0-2 a node's low corner, 3-5 its high one.
        """
        key = ("nodes", pad)
        got = self._padded.get(key)
        if got is None:
            got = np.ascontiguousarray(self.padded(pad).T)
            self._padded[key] = got
        return got

    @staticmethod
    def _rays(slabs: RaySlabs) -> np.ndarray:
        """(6, n) float32, C-contiguous: rows 0-2 the ray origins, rows 3-5 the inverse
        directions. (``take`` copies a non-contiguous array whole before gathering, which
        would cost O(n) per tree level; the flat pass's arithmetic runs along the rows.)"""
        rays = getattr(slabs, "rays", None)
        if rays is not None:  # RaySlabs keeps them so
            return rays
        return np.ascontiguousarray(np.concatenate([slabs.origin, slabs.inv]))

    @staticmethod
    def _intervals(rays: np.ndarray, boxes: np.ndarray, ray: np.ndarray, node: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Entry and exit distances of rays ``ray`` through nodes ``node`` ((k,) each), with the
        operations of ``RaySlabs.intervals`` in its order.

        Parameters
        ----------
        rays : (6, n) from ``_rays``; boxes : (6, N) from ``padded``.

        Returns
        -------
        t_enter, t_exit : (k,) float32
        """
        r = rays.take(ray, axis=1)  # (6, k); take: several times faster than [:, ray]
        ab = boxes.take(node, axis=1).reshape(2, 3, -1)  # (lo, hi) x (x, y, z) x k
        ab -= r[:3]  # overflow to inf and 0 * inf = NaN are expected: callers silence them
        ab *= r[3:]
        lower = np.minimum(ab[0], ab[1])
        upper = np.maximum(ab[0], ab[1], out=r[:3])
        near = np.maximum(lower[0], lower[1], out=ab[0, 0])
        np.maximum(near, lower[2], out=near)
        far = np.minimum(upper[0], upper[1], out=ab[1, 0])
        np.minimum(far, upper[2], out=far)
        return near, far

    def _flat_intervals(self, rays: np.ndarray, boxes: np.ndarray, first: int, stop: int
                        ) -> tuple[np.ndarray, np.ndarray]:
        """Entry and exit distances of rays ``first:stop`` through every box (ascending ids),
        with the operations of ``RaySlabs.intervals`` in its order.

        Returns
        -------
        t_enter, t_exit : (m, stop - first) float32
        """
        r = rays[:, None, first:stop]  # (6, 1, c): rays run along the fast axis
        ab = boxes[:, self._flat_nodes, None]  # (6, m, 1)
        with np.errstate(over="ignore", invalid="ignore"):
            a = ab[:3] - r[:3]
            a *= r[3:]
            b = ab[3:] - r[:3]
            b *= r[3:]
            lower = np.minimum(a, b)
            upper = np.maximum(a, b, out=b)
            near = np.maximum(lower[0], lower[1], out=a[0])
            np.maximum(near, lower[2], out=near)
            far = np.minimum(upper[0], upper[1], out=lower[0])
            np.minimum(far, upper[2], out=far)
        return near, far

    def flat_intervals(self, slabs: RaySlabs) -> tuple[np.ndarray, np.ndarray]:
        """Entry and exit distances of every ray through every box, for trees with few boxes.

        Returns
        -------
        t_enter, t_exit : (m, n) float32, boxes in ``flat_ids`` order (ascending ids),
            bit-identical to ``slabs.intervals``.
        """
        n = slabs.origin.shape[1]
        near = np.empty((self.size, n), np.float32)
        far = np.empty((self.size, n), np.float32)
        if self.size and n:
            boxes, rays = self.padded(slabs.pad), self._rays(slabs)
            chunk = max(FLAT_PAIRS // self.size, 1)
            for first in range(0, n, chunk):
                stop = min(first + chunk, n)
                near[:, first:stop], far[:, first:stop] = self._flat_intervals(rays, boxes,
                                                                              first, stop)
        return near, far

    def pairs(self, slabs: RaySlabs, limit: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every (ray, box) pair whose slab interval may pass ``t_enter <= t_exit``,
        ``t_exit >= 0`` and ``t_enter < limit``: a superset of the pairs that do (it may keep
        pairs with NaN distances), with their exact distances. Within each box, rays ascend
        (a box's leaf lies on one level, and every level keeps its pairs in ray order).

        Parameters
        ----------
        slabs : the rays (n of them).
        limit : (n,) or None (no limit).

        Returns
        -------
        ray : (m,) int64
        box : (m,) int32
        t_enter, t_exit : (m,) float32, bit-identical to ``slabs.intervals(lo[box], hi[box])``.
        """
        parts = [p[2:] for p in self.pair_chunks(slabs, limit)]
        if not parts:
            return _no_pairs()
        if len(parts) == 1:
            return parts[0]
        return tuple(np.concatenate(p) for p in zip(*parts, strict=True))

    def entered(self, slabs: RaySlabs, limit: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The (ray, box) pairs where ``t_enter <= t_exit``, ``t_exit >= 0`` and
        ``t_enter < limit``, through the compiled walk (``boxwalk.entered``): what ``pairs``
        and that test give, bit for bit.

        Parameters
        ----------
        slabs : the rays (n of them); limit : (n,) float32.

        Returns
        -------
        ray : (m,) int64, ascending; box : (m,) int32; t_enter : (m,) float32
        """
        return self.walk_all(boxwalk.entered, slabs, limit, (np.int64, np.int32, np.float32),
                             per_ray=2)

    def walk_all(self, kernel, slabs: RaySlabs, limit: np.ndarray, dtypes: tuple,
                 per_ray: int) -> tuple[np.ndarray, ...]:
        """Run a compiled walk (``boxwalk.crossings`` or ``boxwalk.entered``) over every ray,
        growing its output where a ray's answer does not fit.

        Parameters
        ----------
        kernel : called as ``kernel(rays, nodes, child, box, limit, first, *out)``, returning
            (the first ray not written, entries written).
        slabs : the rays (n of them); limit : (n,) float32.
        dtypes : of the output arrays, in the kernel's order.
        per_ray : output entries to allow per ray at first.

        Returns
        -------
        The output arrays, trimmed (empty ones for no rays or no boxes).
        """
        n = slabs.origin.shape[1]
        if not self.size or n == 0:
            return tuple(np.zeros(0, t) for t in dtypes)
        limit = np.ascontiguousarray(np.broadcast_to(limit, (n,)), np.float32)
        nodes, rays = self.padded_nodes(slabs.pad), self._rays(slabs)
        cap = per_ray * n + 64
        parts, first = [], 0
        while first < n:
            out = tuple(np.empty(cap, t) for t in dtypes)
            first, count = kernel(rays, nodes, self.child, self.box, limit, first, *out)
            parts.append(tuple(a[:count] for a in out))
            cap *= 2  # a ray's answer did not fit: the rest gets more room
        if len(parts) == 1:
            return parts[0]
        return tuple(np.concatenate(p) for p in zip(*parts, strict=True))

    def pair_chunks(self, slabs: RaySlabs, limit: np.ndarray | None = None,
                    chunk: int = CHUNK_RAYS):
        """``pairs``, one chunk of rays after the other.

        Breadth first: one loop iteration per tree level, over all (ray, node) pairs alive in
        the chunk; the chunk bounds the pairs held at once (and keeps them in cache).

        Yields
        ------
        first, stop : int, the chunk's rays.
        ray, box, t_enter, t_exit : (m,) as ``pairs`` returns them, ray in ``first:stop``.
        """
        n = slabs.origin.shape[1]
        if limit is not None:  # contiguous: ``take`` copies other arrays whole
            limit = np.ascontiguousarray(np.broadcast_to(np.asarray(limit), (n,)))
            if np.isposinf(limit).all():
                limit = None  # nothing to prune by: save the walk a comparison per pair
        if not self.size or n == 0:
            return
        boxes, rays = self.padded(slabs.pad), self._rays(slabs)
        if self.flat:
            chunk = min(chunk, max(FLAT_PAIRS // self.size, 1))
        for first in range(0, n, chunk):
            stop = min(first + chunk, n)
            if self.flat:
                t0, t1 = self._flat_intervals(rays, boxes, first, stop)
                drop = t0 > t1
                drop |= t1 < 0
                if limit is not None:
                    drop |= t0 >= limit[None, first:stop]
                col, row = np.nonzero(~drop)
                yield (first, stop, row + first, self.flat_ids[col], t0[col, row],
                       t1[col, row])
            else:
                yield (first, stop,
                       *self._walk(rays, boxes, np.arange(first, stop, dtype=np.int64), limit))

    def _walk(self, rays, boxes, ray, limit=None, after_t=None, window=None):
        """Breadth first from the root, for rays ``ray`` ((k,) int64, indices into ``rays``).

        A node is dropped where ``t_enter > t_exit``, ``t_exit < 0``, ``t_enter >= limit``,
        ``t_exit < after_t`` (no box below it can start after ``after_t``) or ``t_enter >
        window`` (no box below it starts within the window); comparisons with NaN are false,
        so NaN never drops a node.

        Returns
        -------
        ray, box, t_enter, t_exit : (m,) the leaves reached.
        """
        node = np.zeros(len(ray), np.int32)
        out = []
        level = 1
        with np.errstate(over="ignore", invalid="ignore"):
            while len(ray):
                t0, t1 = self._intervals(rays, boxes, ray, node)
                drop = t0 > t1
                drop |= t1 < 0
                if limit is not None:
                    drop |= t0 >= limit.take(ray)
                if after_t is not None:
                    drop |= t1 < after_t.take(ray)
                if window is not None:
                    drop |= t0 > window.take(ray)
                keep = np.logical_not(drop, out=drop)
                if level >= self.first_leaf_level:
                    leaf = self._is_leaf.take(node)
                    at_leaf = keep & leaf
                    if at_leaf.any():
                        out.append((ray[at_leaf], self.box.take(node[at_leaf]), t0[at_leaf],
                                    t1[at_leaf]))
                    keep &= ~leaf
                # Both children of each node, next to each other: rays stay in order.
                ray = np.repeat(ray[keep], 2)
                node = self.child.take(node[keep], axis=0).ravel()
                level += 1
        if not out:
            return _no_pairs()
        return tuple(np.concatenate(p) for p in zip(*out, strict=True))

    def first_after(self, slabs: RaySlabs, after_t: np.ndarray, after_d: np.ndarray,
                    limit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The box with the least (entry, id) after (``after_t``, ``after_d``) whose entry is
        below ``limit``, for each ray.

        A box's entry is ``max(t_enter, 0)``, or ``inf`` where ``t_enter > t_exit`` or
        ``t_exit < 0`` (as in ``DomainGeometry``). Breadth first, like ``pairs``, skipping
        nodes the ray leaves before ``after_t`` or enters at or beyond ``limit``; then the
        least (entry, id) per ray among the boxes left. A ray with a current box (``after_d``)
        first looks only as far as that box's exit, where the next box usually starts; only
        rays with nothing there search on to ``limit``. The work per ray grows with the boxes
        it crosses in the part searched, not with the box count. (A depth-first, nearest-first
        walk with a stack per ray was tried first: it makes a round of numpy calls per
        traversal step rather than per level, and made the image schedule at 1,143 domains,
        whose batches are the few rays just traced in one domain, four times slower.)

        Parameters
        ----------
        slabs : the rays (n of them).
        after_t : (n,) float32, entry of the last box visited (``-inf`` for none).
        after_d : (n,) int, its id (-1 for none).
        limit : (n,) float32

        Returns
        -------
        box : (n,) int32, -1 where there is none.
        entry : (n,) float32, its entry (``inf`` where there is none).
        """
        n = slabs.origin.shape[1]
        best_d = np.full(n, -1, np.int32)
        best_e = np.full(n, np.inf, np.float32)
        if not self.size or n == 0:
            return best_d, best_e
        if self.compiled and _exact_dtypes(after_t, after_d, limit):
            boxwalk.first_after(self._rays(slabs), self.padded_nodes(slabs.pad), self.child,
                                self.box, *(np.ascontiguousarray(np.broadcast_to(a, (n,)), t)
                                            for a, t in ((after_t, np.float32),
                                                         (after_d, np.int64),
                                                         (limit, np.float32))),
                                best_d, best_e)
            return best_d, best_e
        boxes, rays = self.padded(slabs.pad), self._rays(slabs)
        # Inputs keep their dtypes: comparisons promote exactly as the per-box loop's did.
        # (contiguous: ``take`` copies other arrays whole)
        after_t, after_d, limit = (np.ascontiguousarray(np.broadcast_to(np.asarray(a), (n,)))
                                   for a in (after_t, after_d, limit))
        if self.flat:
            chunk = max(FLAT_PAIRS // self.size, 1)
            for first in range(0, n, chunk):
                stop = min(first + chunk, n)
                self._flat_first_after(rays, boxes, after_t, after_d, limit, first, stop,
                                       best_d, best_e)
            return best_d, best_e
        # Most calls continue a walk: the next box usually starts where the current one ends
        # (boxes of neighbouring cells touch or overlap), so look there first. Boxes entered
        # by the end of the current box are a window: when it holds a candidate, that is the
        # answer, as every box outside starts later. Rays whose window is empty search up to
        # their limit, and so do rays that have no current box.
        window = None
        cursor = np.nonzero((after_d >= 0) & (after_d < len(self._leaf_of)))[0]
        if len(cursor):
            leaf = self._leaf_of[after_d[cursor]]
            cursor, leaf = cursor[leaf >= 0], leaf[leaf >= 0]
            with np.errstate(over="ignore", invalid="ignore"):
                _, exit_ = self._intervals(rays, boxes, cursor, leaf)
            window = np.full(n, np.inf, np.float32)
            window[cursor] = exit_
        least = np.full(n, np.iinfo(np.int64).max)
        self._least_after(rays, boxes, np.arange(n), after_t, after_d, limit, window, least,
                          best_d, best_e)
        if window is not None:
            retry = np.nonzero((window != np.inf) & (best_d < 0))[0]  # NaN windows retry too
            if len(retry):
                self._least_after(rays, boxes, retry, after_t, after_d, limit, None, least,
                                  best_d, best_e)
        return best_d, best_e

    def _least_after(self, rays, boxes, ray, after_t, after_d, limit, window, least, best_d,
                     best_e) -> None:
        """``first_after`` for rays ``ray``, within ``window`` (or up to ``limit``): the least
        (entry, id) per ray into ``best_d``, ``best_e``; ``least`` is (n,) int64 scratch."""
        unlimited = bool(np.isposinf(limit[ray]).all())
        for first in range(0, len(ray), CHUNK_RAYS):
            r, box, t0, t1 = self._walk(rays, boxes, ray[first:first + CHUNK_RAYS],
                                        None if unlimited else limit, after_t, window)
            entry = np.maximum(t0, np.float32(0))
            entry[(t0 > t1) | (t1 < 0)] = np.inf
            at = after_t[r]
            ok = (entry > at) | ((entry == at) & (box > after_d[r]))
            ok &= entry < limit[r]
            if window is not None:
                ok &= entry <= window[r]
            r, box, entry = r[ok], box[ok], entry[ok]
            # The least (entry, id) per ray as one integer: a float32 >= 0 orders as its bits
            # (-0.0 counted as +0.0, which it equals); ids fit in 31 bits.
            key = ((entry + np.float32(0)).view(np.uint32).astype(np.int64) << 32) | box
            np.minimum.at(least, r, key)
            won = key == least[r]  # one box per ray: (ray, box) pairs are unique
            best_d[r[won]] = box[won]
            best_e[r[won]] = entry[won]

    def _flat_first_after(self, rays, boxes, after_t, after_d, limit, first, stop,
                          best_d, best_e) -> None:
        """``first_after`` for rays ``first:stop`` in one pass over all boxes: the least
        entry among the boxes that qualify, the lowest id among equal entries, into
        ``best_d``, ``best_e``."""
        t0, t1 = self._flat_intervals(rays, boxes, first, stop)  # (m, c)
        m = len(self.flat_ids)
        entry = np.maximum(t0, np.float32(0))
        entry[(t0 > t1) | (t1 < 0)] = np.inf
        ids = self.flat_ids[:, None]
        at = after_t[None, first:stop]
        ok = (entry > at) | ((entry == at) & (ids > after_d[None, first:stop]))
        ok &= entry < limit[None, first:stop]
        entry[~ok] = np.inf
        least = entry.min(axis=0)  # (c,); inf where no box qualifies
        # The first (lowest id) box at the least entry; reductions along axis 0 stay vectorised
        # over the rays (an argmin along it would not).
        col = np.where(entry == least, np.arange(m)[:, None], m).min(axis=0)
        col = np.minimum(col, m - 1)
        found = least < np.inf  # a qualifying entry is below its limit: finite
        best_d[first:stop] = np.where(found, self.flat_ids[col], -1)
        best_e[first:stop] = np.where(found, entry[col, np.arange(stop - first)],
                                      np.float32(np.inf))


def _exact_dtypes(after_t, after_d, limit) -> bool:
    """Whether the compiled ``first_after`` compares as the numpy walk would: float32
    distances (a float64 ``after_t`` or ``limit`` would compare the float32 entries in
    float64) and integer ids."""
    return (np.asarray(after_t).dtype == np.float32 and np.asarray(limit).dtype == np.float32
            and np.asarray(after_d).dtype.kind in "iu")


def _no_pairs() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return (np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0, np.float32),
            np.zeros(0, np.float32))
