"""Compiled ray-domain enumeration: each ray walks the ``BoxTree`` depth first in a numba kernel.

``BoxTree`` walks whole batches breadth first in numpy (one Python iteration per tree level);
these kernels walk one ray at a time with a stack, in compiled code, and write each ray's
answer in its final order, so no pass over all (ray, box) pairs and no sort of them follows.
The answers are those of the numpy walk bit for bit:

* every node's slab distances are computed with the float32 operations of
  ``RaySlabs.intervals`` in its order (numba keeps float32 arithmetic in float32, and
  ``(x - y) * z`` leaves nothing to contract into a fused multiply-add);
* ``_min``/``_max`` are numpy's ``minimum``/``maximum``: NaN if either operand is NaN, else
  the first operand where it is strictly smaller (larger) and the second otherwise, which
  decides the sign of a zero result as numpy does;
* nodes are pruned by the same tests as ``BoxTree._walk`` (comparisons with NaN are false, so
  NaN never prunes), and leaves are accepted by the callers' own tests.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Deepest stack a walk can need: a tree of 2^31 boxes is at most this high.
_STACK = 64


@njit(inline="always")
def _min(a, b):
    """``np.minimum`` of two float32 scalars."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a < b else b


@njit(inline="always")
def _max(a, b):
    """``np.maximum`` of two float32 scalars."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a > b else b


@njit(inline="always")
def _interval(nodes, node, ray):
    """Entry and exit distance of the ray (``_ray``: origin ``o*``, inverse direction
    ``i*``, ``finite``) through node ``node``, with the operations of ``RaySlabs.intervals``
    in its order.

    ``finite`` (``_finite``: a finite origin, inverse direction components finite and
    non-zero): no distance can be NaN (an overflow gives an infinity, never a NaN), and plain
    comparisons are numpy's minimum and maximum; else (e.g. a denormal direction component,
    whose inverse overflowed) the NaN-aware ones.
    """
    ox, oy, oz, ix, iy, iz, finite = ray
    a = (nodes[node, 0] - ox) * ix
    b = (nodes[node, 3] - ox) * ix
    c = (nodes[node, 1] - oy) * iy
    d = (nodes[node, 4] - oy) * iy
    e = (nodes[node, 2] - oz) * iz
    f = (nodes[node, 5] - oz) * iz
    if finite:
        near = a if a < b else b
        far = a if a > b else b
        lower = c if c < d else d
        upper = c if c > d else d
        near = near if near > lower else lower
        far = far if far < upper else upper
        lower = e if e < f else f
        upper = e if e > f else f
        return (near if near > lower else lower), (far if far < upper else upper)
    near = _max(_min(a, b), _min(c, d))
    far = _min(_max(a, b), _max(c, d))
    return _max(near, _min(e, f)), _min(far, _max(e, f))


@njit(inline="always")
def _ray(rays, i):
    """Ray ``i`` of ``rays`` ((6, n)) as the walks read it: origin, inverse direction and
    ``_finite``."""
    return (rays[0, i], rays[1, i], rays[2, i], rays[3, i], rays[4, i], rays[5, i],
            _finite(rays, i))


@njit(inline="always")
def _pop(stack, sp, nodes, ray):
    """Pop a node off the walk's stack (``sp`` nodes on it): the new size, the node, the ray's
    entry and exit distances, and whether the ray may overlap it (not ``t_enter > t_exit``
    nor ``t_exit < 0``: NaN never rules a node out)."""
    sp -= 1
    node = stack[sp]
    near, far = _interval(nodes, node, ray)
    return sp, node, near, far, not (near > far or far < np.float32(0))


@njit(inline="always")
def _push_children(stack, sp, child, node):
    """Push both children of ``node`` (the first on top); returns the new stack size."""
    stack[sp] = child[node, 1]
    stack[sp + 1] = child[node, 0]
    return sp + 2


@njit(inline="always")
def _finite(rays, i):
    """Whether ray ``i``'s origin is finite and its inverse direction finite and non-zero:
    then none of its slab distances can be NaN."""
    for k in range(3):
        if not abs(rays[k, i]) < np.inf or not 0 < abs(rays[3 + k, i]) < np.inf:
            return False
    return True


@njit(nogil=True, cache=True)
def crossings(rays, nodes, child, box, limit, first, out_ray, out_box, out_entry, out_rank):
    """Every box each ray enters before its limit, ordered by (entry, box id) along the ray.

    Parameters
    ----------
    rays : (6, n) float32, origins then inverse directions (``RaySlabs.rays``).
    nodes : (N, 6) float32 node boxes, padded (``BoxTree.padded`` transposed).
    child : (N, 2) int32; box : (N,) int32 (``BoxTree``).
    limit : (n,) float32.
    first : the ray to start from.
    out_ray : (cap,) int64; out_box, out_rank : (cap,) int32; out_entry : (cap,) float32.

    Returns
    -------
    stop : the first ray not written (``n`` when every ray was); the caller grows the output
        and calls again from there.
    count : entries written.

    A box's entry is ``max(t_enter, 0)``; the ray enters it where ``t_enter <= t_exit``,
    ``t_exit >= 0`` and ``entry < limit`` (``DomainGeometry.crossings``).
    """
    n = rays.shape[1]
    cap = out_ray.shape[0]
    stack = np.empty(_STACK, np.int32)
    got_box = np.empty(max(box.shape[0], 1), np.int32)
    got_entry = np.empty(max(box.shape[0], 1), np.float32)
    zero = np.float32(0)
    count = 0
    for i in range(first, n):
        lim = limit[i]
        ray = _ray(rays, i)
        m = 0
        stack[0] = 0  # the root
        sp = 1
        while sp:
            sp, node, near, far, overlaps = _pop(stack, sp, nodes, ray)
            if not overlaps:
                continue
            if box[node] >= 0:
                entry = _max(near, zero)
                if entry < lim:
                    # insertion by (entry, box): boxes already held that come later move up
                    b = box[node]
                    j = m
                    while j > 0 and (got_entry[j - 1] > entry
                                     or (got_entry[j - 1] == entry and got_box[j - 1] > b)):
                        got_entry[j] = got_entry[j - 1]
                        got_box[j] = got_box[j - 1]
                        j -= 1
                    got_entry[j] = entry
                    got_box[j] = b
                    m += 1
            elif not near >= lim:  # (NaN compares false: kept, as in the numpy walk)
                sp = _push_children(stack, sp, child, node)
        if count + m > cap:
            return i, count
        for j in range(m):
            out_ray[count] = i
            out_box[count] = got_box[j]
            out_entry[count] = got_entry[j]
            out_rank[count] = j
            count += 1
    return n, count


@njit(nogil=True, cache=True)
def first_after(rays, nodes, child, box, after_t, after_d, limit, best_box, best_entry):
    """The box with the least (entry, id) after (``after_t``, ``after_d``) whose entry is below
    ``limit``, for each ray (``BoxTree.first_after``).

    Parameters
    ----------
    rays, nodes, child, box : as for ``crossings``.
    after_t : (n,) float32; after_d : (n,) int64; limit : (n,) float32.
    best_box : (n,) int32 out, -1 where there is none; best_entry : (n,) float32 out (inf).

    A box qualifies where its entry ``max(t_enter, 0)`` (``t_enter <= t_exit``,
    ``t_exit >= 0``) is greater than ``after_t``, or equal with a greater id than
    ``after_d``, and below ``limit``. A node is skipped where the ray leaves it before
    ``after_t``, enters it at or beyond ``limit``, or enters it beyond the best entry so far
    (every box below it enters later still); NaN distances skip nothing.
    """
    n = rays.shape[1]
    stack = np.empty(_STACK, np.int32)
    zero = np.float32(0)
    for i in range(n):
        at, ad, lim = after_t[i], after_d[i], limit[i]
        ray = _ray(rays, i)
        got_box = np.int32(-1)
        got_entry = np.float32(np.inf)
        stack[0] = 0  # the root
        sp = 1
        while sp:
            sp, node, near, far, overlaps = _pop(stack, sp, nodes, ray)
            if not overlaps:
                continue
            b = box[node]
            if b >= 0:
                entry = _max(near, zero)
                if ((entry > at or (entry == at and b > ad)) and entry < lim
                        and (entry < got_entry or (entry == got_entry and b < got_box))):
                    got_box = b
                    got_entry = entry
            elif not (far < at or near >= lim or _max(near, zero) > got_entry):
                sp = _push_children(stack, sp, child, node)
        best_box[i] = got_box
        best_entry[i] = got_entry


@njit(nogil=True, cache=True)
def entered(rays, nodes, child, box, limit, first, out_ray, out_box, out_enter):
    """Every (ray, box) pair with ``t_enter <= t_exit``, ``t_exit >= 0`` and
    ``t_enter < limit`` (``DomainTracer``'s test: ``t_enter`` not clamped at 0), by ray.

    Parameters
    ----------
    rays, nodes, child, box, limit, first : as for ``crossings``.
    out_ray : (cap,) int64; out_box : (cap,) int32; out_enter : (cap,) float32 ``t_enter``.

    Returns
    -------
    stop, count : as for ``crossings``.
    """
    n = rays.shape[1]
    cap = out_ray.shape[0]
    stack = np.empty(_STACK, np.int32)
    count = 0
    for i in range(first, n):
        lim = limit[i]
        ray = _ray(rays, i)
        start = count
        stack[0] = 0  # the root
        sp = 1
        while sp:
            sp, node, near, far, overlaps = _pop(stack, sp, nodes, ray)
            if not overlaps or near >= lim:
                continue
            if box[node] < 0:
                sp = _push_children(stack, sp, child, node)
            elif near <= far and near < lim:  # (a NaN distance fails here)
                if count == cap:
                    return i, start  # this ray's pairs did not fit: it starts the next call
                out_ray[count] = i
                out_box[count] = box[node]
                out_enter[count] = near
                count += 1
    return n, count
