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
    for p in range(ray.shape[0]):
        d = domain[p]
        if useful[d]:
            i = ray[p]
            out[p] = _segment_crosses(origins[i], directions[i], limit[i], radius, lo[d], hi[d],
                                      cell[d], dims[d], bits, base[d], scratch, cells, span)


@njit(inline="always")
def _piece_hits(o, dv, ta, tb, radius, lo, cell, dims, bits, base, rng):
    """Whether a cell meeting the box of the segment's piece ``[ta, tb]`` grown by
    ``radius`` is occupied (``rng``: (6,) int64 scratch)."""
    for k in range(3):
        a = o[k] + ta * dv[k]
        b = o[k] + tb * dv[k]
        if a > b:
            a, b = b, a
        lo_k = _index(a - radius, lo[k], cell[k], dims[k])
        hi_k = _index(b + radius, lo[k], cell[k], dims[k])
        if lo_k < 0 or hi_k < 0:
            return True
        rng[k] = lo_k
        rng[3 + k] = hi_k
    ny, nz = dims[1], dims[2]
    for i in range(rng[0], rng[3] + 1):
        for j in range(rng[1], rng[4] + 1):
            for k in range(rng[2], rng[5] + 1):
                if bits[base + (i * ny + j) * nz + k]:
                    return True
    return False


@njit(inline="always")
def _segment_crosses(origin, direction, limit, radius, lo, hi, cell, dims, bits, base,
                     scratch, cells, span):
    """The DDA of one (ray, domain) pair (see ``Occupancy.crosses``)."""
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
        if _piece_hits(o, dv, ta, tb, radius, lo, cell, dims, bits, base, span):
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
