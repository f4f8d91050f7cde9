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
            base, bits, near, min_cell, out):
    """``out[p]`` = False where ray ``ray[p]`` crosses no occupied cell of domain
    ``domain[p]`` (``Occupancy.crosses``); pairs of domains not ``useful`` are left as they
    are (True).

    Every quantity of a pair is a scalar local, not a row of a scratch array: LLVM keeps them
    in registers (1.45x faster than the same arithmetic through (3,) scratch rows, the same
    answers bit for bit; issue 40, the 100 M-triangle store's renders spent 8-11 s here)."""
    for p in range(ray.shape[0]):
        d = domain[p]
        if useful[d]:
            i = ray[p]
            out[p] = _segment_crosses(
                np.float64(origins[i, 0]), np.float64(origins[i, 1]), np.float64(origins[i, 2]),
                np.float64(directions[i, 0]), np.float64(directions[i, 1]),
                np.float64(directions[i, 2]), limit[i], radius,
                lo[d, 0], lo[d, 1], lo[d, 2], hi[d, 0], hi[d, 1], hi[d, 2],
                cell[d, 0], cell[d, 1], cell[d, 2], dims[d, 0], dims[d, 1], dims[d, 2],
                bits, base[d], near, 4.0 * radius < min_cell[d])


@njit(inline="always")
def _clip(o, dv, blo, bhi, t0, t1):
    """``(t0, t1, outside)``: the segment ``[t0, t1]`` clipped to the slab ``[blo, bhi]`` of
    one axis; ``outside`` where the ray runs parallel to the slab outside it."""
    if dv == 0:
        return t0, t1, (o < blo or o > bhi)
    ta = (blo - o) / dv
    tb = (bhi - o) / dv
    if ta > tb:
        ta, tb = tb, ta
    return max(t0, ta), min(t1, tb), False


@njit(inline="always")
def _span(o, dv, ta, tb, radius, lo, cell, n):
    """The cells along one axis that the piece ``[ta, tb]``, grown by ``radius``, meets
    (first, last; -1 where a coordinate is NaN)."""
    a = o + ta * dv
    b = o + tb * dv
    if a > b:
        a, b = b, a
    return _index(a - radius, lo, cell, n), _index(b + radius, lo, cell, n)


@njit(inline="always")
def _segment_crosses(ox, oy, oz, dx, dy, dz, limit, radius, lx, ly, lz, hx, hy, hz,
                     cx, cy, cz, nx, ny, nz, bits, base, near, skip):
    """The DDA of one (ray, domain) pair (see ``Occupancy.crosses``): the origin ``o``, the
    direction ``d``, the grid's corner ``l``, its box's far corner ``h``, its cell size ``c``
    and cells ``n`` along x, y, z; ``near``: ``Occupancy.near``, asked where ``skip`` (``radius``
    is below a quarter of the smallest cell edge)."""
    t1 = np.float64(limit)
    if t1 != t1:  # NaN: keep the pair
        return True
    t1 = t1 + abs(t1) * 2.0 ** -20
    # the segment within the grid's box grown by radius, axis by axis (a ray with a
    # coordinate not finite is kept, unless an earlier axis's slab already excludes it)
    if not (abs(ox) < np.inf and abs(dx) < np.inf):
        return True
    t0, t1, outside = _clip(ox, dx, lx - radius, max(hx, lx + cx * nx) + radius, 0.0, t1)
    if outside:
        return False
    if not (abs(oy) < np.inf and abs(dy) < np.inf):
        return True
    t0, t1, outside = _clip(oy, dy, ly - radius, max(hy, ly + cy * ny) + radius, t0, t1)
    if outside:
        return False
    if not (abs(oz) < np.inf and abs(dz) < np.inf):
        return True
    t0, t1, outside = _clip(oz, dz, lz - radius, max(hz, lz + cz * nz) + radius, t0, t1)
    if outside:
        return False
    if not t0 <= t1:
        return False
    # DDA: the cell at t0 and the next boundary crossed along each axis
    ix = _index(ox + t0 * dx, lx, cx, nx)
    iy = _index(oy + t0 * dy, ly, cy, ny)
    iz = _index(oz + t0 * dz, lz, cz, nz)
    if ix < 0 or iy < 0 or iz < 0:
        return True
    sx, sy, sz = 0, 0, 0
    bx, by, bz = np.inf, np.inf, np.inf
    if nx > 1 and dx != 0:
        sx = 1 if dx > 0 else -1
        bx = _boundary(ox, dx, lx, cx, nx, ix, sx)
    if ny > 1 and dy != 0:
        sy = 1 if dy > 0 else -1
        by = _boundary(oy, dy, ly, cy, ny, iy, sy)
    if nz > 1 and dz != 0:
        sz = 1 if dz > 0 else -1
        bz = _boundary(oz, dz, lz, cz, nz, iz, sz)
    ta = t0
    for _ in range(nx + ny + nz + 4):
        axis, tb = 0, bx
        if by < tb:
            axis, tb = 1, by
        if bz < tb:
            axis, tb = 2, bz
        tb = min(max(tb, ta), t1)
        # The piece lies in the DDA's cell up to rounding, so its box grown by radius (under a
        # quarter cell) meets only that cell and its 26 neighbours: where none of them is
        # occupied, the exact test below would find nothing. (A piece without end, a ray
        # whose direction is zero, is tested: inf * 0 makes its span NaN, and it is kept.)
        if not skip or not tb < np.inf or near[base + (ix * ny + iy) * nz + iz]:
            # a cell meeting the box of the piece [ta, tb] grown by radius is occupied?
            x0, x1 = _span(ox, dx, ta, tb, radius, lx, cx, nx)
            y0, y1 = _span(oy, dy, ta, tb, radius, ly, cy, ny)
            z0, z1 = _span(oz, dz, ta, tb, radius, lz, cz, nz)
            if x0 < 0 or x1 < 0 or y0 < 0 or y1 < 0 or z0 < 0 or z1 < 0:
                return True
            for i in range(x0, x1 + 1):
                for j in range(y0, y1 + 1):
                    row = base + (i * ny + j) * nz
                    for k in range(z0, z1 + 1):
                        if bits[row + k]:
                            return True
        if tb >= t1:
            return False
        ta = tb
        if axis == 0:
            ix += sx
            bx = _boundary(ox, dx, lx, cx, nx, ix, sx)
        elif axis == 1:
            iy += sy
            by = _boundary(oy, dy, ly, cy, ny, iy, sy)
        else:
            iz += sz
            bz = _boundary(oz, dz, lz, cz, nz, iz, sz)
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
