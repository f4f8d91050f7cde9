"""The compiled halves of :mod:`vastray.scene.occupancy` (imported on first use, so opening a
store does not import numba): marking a domain's cells, and the DDA of the query."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(inline="always")
def _index(x, lo, cell, n):
    """The cell along one axis holding coordinate ``x`` (float64), clamped to ``0..n - 1``;
    monotone in ``x``. NaN: -1 (the caller marks or tests everything)."""
    if n == 1:
        return 0
    f = (x - lo) / cell
    if f != f:
        return -1
    if f <= 0:
        return 0
    if f >= n - 1:
        return n - 1
    i = int(np.floor(f))
    return min(max(i, 0), n - 1)


@njit(nogil=True, cache=True)
def mark(vertices, indices, lo, cell, dims, out):
    """Set ``out[(i * b + j) * c + k]`` for every cell a triangle's box meets."""
    ny, nz = dims[1], dims[2]
    rng = np.empty(6, np.int64)
    for t in range(indices.shape[0]):
        for k in range(3):
            a = np.float64(vertices[indices[t, 0], k])
            b = a
            for v in range(1, 3):
                x = np.float64(vertices[indices[t, v], k])
                a = min(a, x)
                b = max(b, x)
            rng[k] = _index(a, lo[k], cell[k], dims[k])
            rng[3 + k] = _index(b, lo[k], cell[k], dims[k])
            if rng[k] < 0 or rng[3 + k] < 0:  # not finite: every cell
                rng[k] = 0
                rng[3 + k] = dims[k] - 1
        for i in range(rng[0], rng[3] + 1):
            for j in range(rng[1], rng[4] + 1):
                for k in range(rng[2], rng[5] + 1):
                    out[(i * ny + j) * nz + k] = 1


@njit(nogil=True, cache=True)
def crosses(origins, directions, ray, domain, limit, radius, lo, hi, cell, dims, useful,
            base, bits, out):
    """``out[p]`` = False where ray ``ray[p]`` crosses no occupied cell of domain
    ``domain[p]`` (``Occupancy.crosses``); pairs of domains not ``useful`` are left as they
    are (True)."""
    scratch = np.empty((3, 3), np.float64)  # origin, direction, next boundary
    cells = np.empty((3, 3), np.int64)  # cell, step, and (scratch) the piece's index range
    span = np.empty(6, np.int64)
    no_marks = np.zeros(0, np.uint8)  # a query that only tests
    for p in range(ray.shape[0]):
        d = domain[p]
        if useful[d]:
            i = ray[p]
            out[p] = _segment_crosses(origins[i], directions[i], limit[i], radius, lo[d], hi[d],
                                      cell[d], dims[d], bits, base[d], scratch, cells, span,
                                      no_marks)


@njit(inline="always")
def _piece_hits(o, dv, ta, tb, radius, lo, cell, dims, bits, base, rng, marks):
    """Whether a cell meeting the box of the segment's piece ``[ta, tb]`` grown by
    ``radius`` is occupied (``rng``: (6,) int64 scratch). With ``marks`` (not empty), sets
    ``marks`` at every such cell instead and returns False (the walk goes on to the end)."""
    marking = marks.shape[0] > 0
    for k in range(3):
        a = o[k] + ta * dv[k]
        b = o[k] + tb * dv[k]
        if a > b:
            a, b = b, a
        lo_k = _index(a - radius, lo[k], cell[k], dims[k])
        hi_k = _index(b + radius, lo[k], cell[k], dims[k])
        if lo_k < 0 or hi_k < 0:
            if marking:  # not finite: every cell
                marks[:] = 1
                return False
            return True
        rng[k] = lo_k
        rng[3 + k] = hi_k
    ny, nz = dims[1], dims[2]
    for i in range(rng[0], rng[3] + 1):
        for j in range(rng[1], rng[4] + 1):
            for k in range(rng[2], rng[5] + 1):
                if marking:
                    marks[(i * ny + j) * nz + k] = 1
                elif bits[base + (i * ny + j) * nz + k]:
                    return True
    return False


@njit(inline="always")
def _segment_crosses(origin, direction, limit, radius, lo, hi, cell, dims, bits, base,
                     scratch, cells, span, marks):
    """The DDA of one (ray, domain) pair (see ``Occupancy.crosses``). With ``marks`` (not
    empty): marks every cell it would test (``_piece_hits``) and returns False, or True where
    it gives up (a coordinate not finite: the caller must take every cell)."""
    o, dv, nxt = scratch[0], scratch[1], scratch[2]
    idx, step = cells[0], cells[1]
    t0 = 0.0
    t1 = np.float64(limit)
    if t1 != t1:  # NaN: keep the pair
        return True
    t1 = t1 + abs(t1) * 2.0 ** -20
    for k in range(3):
        o[k] = np.float64(origin[k])
        dv[k] = np.float64(direction[k])
        if not (abs(o[k]) < np.inf and abs(dv[k]) < np.inf):
            return True
        # the segment within the grid's box grown by radius
        blo = lo[k] - radius
        bhi = max(hi[k], lo[k] + cell[k] * dims[k]) + radius
        if dv[k] == 0:
            if o[k] < blo or o[k] > bhi:
                return False
            continue
        ta = (blo - o[k]) / dv[k]
        tb = (bhi - o[k]) / dv[k]
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
    if not t0 <= t1:
        return False
    # DDA: the cell at t0 and the next boundary crossed along each axis
    for k in range(3):
        idx[k] = _index(o[k] + t0 * dv[k], lo[k], cell[k], dims[k])
        if idx[k] < 0:
            return True
        step[k] = 0
        nxt[k] = np.inf
        if dims[k] > 1 and dv[k] != 0:
            step[k] = 1 if dv[k] > 0 else -1
            nxt[k] = _boundary(o[k], dv[k], lo[k], cell[k], dims[k], idx[k], step[k])
    ta = t0
    for _ in range(dims[0] + dims[1] + dims[2] + 4):
        k = 0
        if nxt[1] < nxt[k]:
            k = 1
        if nxt[2] < nxt[k]:
            k = 2
        tb = min(max(nxt[k], ta), t1)
        if _piece_hits(o, dv, ta, tb, radius, lo, cell, dims, bits, base, span, marks):
            return True
        if tb >= t1:
            return False
        ta = tb
        idx[k] += step[k]
        nxt[k] = _boundary(o[k], dv[k], lo[k], cell[k], dims[k], idx[k], step[k])
    return True  # (never: each step leaves a cell) kept, to be safe


@njit(inline="always")
def _boundary(o, dv, lo, cell, n, i, step):
    """Where the ray crosses the boundary it leaves cell ``i`` through along one axis (inf
    past the grid's last cell that way)."""
    if step > 0:
        if i >= n - 1:
            return np.inf
        return (lo + (i + 1) * cell - o) / dv
    if i <= 0:
        return np.inf
    return (lo + i * cell - o) / dv


@njit(nogil=True, cache=True)
def mark_segments(origins, directions, limit, radius, lo, hi, cell, dims, marks):
    """Set ``marks[(i * b + j) * c + k]`` at every cell of one domain's grid (box ``[lo, hi]``,
    ``dims`` cells of ``cell``) that the query of ``crosses`` would test for any of the rays'
    segments ``[0, limit]``: every point a hit on the segments can be reported at lies in a
    marked cell. Returns False where a ray's numbers are not finite (then every cell counts).
    """
    scratch = np.empty((3, 3), np.float64)
    cells = np.empty((3, 3), np.int64)
    span = np.empty(6, np.int64)
    for i in range(origins.shape[0]):
        if _segment_crosses(origins[i], directions[i], limit[i], radius, lo, hi, cell, dims,
                            marks, 0, scratch, cells, span, marks):
            return False
    return True


@njit(nogil=True, cache=True)
def select_triangles(vertices, indices, lo, cell, dims, marked, out):
    """``out[t]`` = 1 where triangle ``t``'s box meets a cell set in ``marked`` (the
    summed-area table of the marks, ``(a + 1, b + 1, c + 1)`` int64: the marks in any block of
    cells in 8 reads). A triangle whose coordinates are not finite is kept."""
    rng = np.empty(6, np.int64)
    for t in range(indices.shape[0]):
        keep = False
        for k in range(3):
            a = np.float64(vertices[indices[t, 0], k])
            b = a
            for v in range(1, 3):
                x = np.float64(vertices[indices[t, v], k])
                a = min(a, x)
                b = max(b, x)
            rng[k] = _index(a, lo[k], cell[k], dims[k])
            rng[3 + k] = _index(b, lo[k], cell[k], dims[k])
            if rng[k] < 0 or rng[3 + k] < 0:
                keep = True
        if not keep:
            i0, j0, k0 = rng[0], rng[1], rng[2]
            i1, j1, k1 = rng[3] + 1, rng[4] + 1, rng[5] + 1
            count = (marked[i1, j1, k1] - marked[i0, j1, k1] - marked[i1, j0, k1]
                     - marked[i1, j1, k0] + marked[i0, j0, k1] + marked[i0, j1, k0]
                     + marked[i1, j0, k0] - marked[i0, j0, k0])
            keep = count > 0
        out[t] = 1 if keep else 0
