"""Fused numba kernels for the shading hot path (issue 9).

``render.integrators.shade`` used to be a chain of numpy passes over the batch (hit point,
facing normal, spawned origin, one ``light.sample`` per light, cosines, masks, takes,
concatenations, the continuation bounce), each allocating its temporaries. Here the same
arithmetic runs in one serial ``nogil`` kernel per batch, row by row, writing the shadow rays
and continuation rays straight into their output arrays. Serial on purpose: the render workers
call shading side by side on their own threads while another worker's Embree launch uses all
the cores (``scene/embree/launch.py`` runs launches one at a time).

Bit for bit the numpy path's results
------------------------------------
Every float operation is the one numpy performs, in the same order and precision:

- the counter-based RNG (``render.rng``) is ported as is (uint64 arithmetic wraps the same);
- ``np.einsum("ij,ij->i", a, b)`` over 3 columns sums ``(a0 b0 + a2 b2) + a1 b1`` (its SIMD
  tail: products in vector lanes, then a horizontal sum; measured equal on 1 M rows), and
  ``np.linalg.norm(v, axis=1)`` is ``sqrt((v0^2 + v1^2) + v2^2)``: the kernels use those orders;
- two things numpy computes with its own SIMD routines that libm does not reproduce (float32
  ``cos``/``sin``: 17 % of values differ in the last bit; float64 ``pow``: 5 %) stay in numpy:
  the cosine-hemisphere angles are drawn by ``hemisphere_uniforms`` and their cos/sin taken
  by numpy before the shading kernel runs, and the Blinn-Phong power is applied afterwards
  (``integrators._shade_fused`` through ``materials.blinn_phong_lobe_of_cos``).

The light kinds are the four of ``render.lights``; ``integrators.shade`` refuses any other.
The numpy chain itself is the tests' oracle (``tests/oracles.py``: ``oracles.*`` below), not
part of the package.

Compilation: ``cache=True``, so a process loads them from ``__pycache__``; the very first use
compiles them (measured: a fresh numba cache made the first tiny render take 13.9 s instead of
6.4 s before these kernels, on the shared machine under load; 0.4-0.6 s once cached).

``error_model="numpy"``: a float division by zero gives inf or nan, as numpy's does, instead
of numba's default check that raises ``ZeroDivisionError``. That check is a branch out of the
loop on every division by a value computed in the loop, and it kept LLVM from vectorising
the loops (``camera_rays``: 12.5 -> 8.1 ms for 2^20 rays, AVX-512). Vectorised float
arithmetic is still IEEE, lane by lane (no ``fastmath``: nothing is reassociated), so the
results are the same bits.
"""

from __future__ import annotations

import contextlib
import math
import sys

import numpy as np
from numba import njit

# render.rng's constants, as numpy scalars so numba types them as uint64 / float32.
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_S8, _S27, _S30, _S31 = np.uint64(8), np.uint64(27), np.uint64(30), np.uint64(31)
_TOP24, _MID24 = np.uint64(40), np.uint64(16)
_MASK24 = np.uint64(0xFFFFFF)
_INV24 = np.float32(1.0 / (1 << 24))

#: Light kinds in the light table (``integrators._light_table``).
POINT, DIRECTIONAL, QUAD, AMBIENT = 0, 1, 2, 3
#: Columns of the light table's parameter rows.
LIGHT_PARAMS = 16

_PI = math.pi
#: Shadow rays to a light at distance r stop at ``r * (1 - SPAWN_EPSILON)``, short of geometry
#: that touches the light. Re-exported by ``render.integrators``.
SPAWN_EPSILON = 4e-6
_SHORTEN = 1.0 - SPAWN_EPSILON
#: Error bound of a reconstructed hit point, relative to the float32 coordinates the query
#: used: 32 units of float32 roundoff (2^-24), about 4.5 times pbrt-v4's gamma(7) bound for a
#: barycentric point, since Embree's own float32 ray-triangle test, not ours, decides whether
#: a spawned ray re-hits its surface (``hit_points``).
HIT_ERROR = 2.0 ** -19
#: 1 / sin of the triangle angle below which ``hit_points`` treats a triangle as a sliver.
_SLIVER = 2.0 ** 12
_F32_ZERO = np.float32(0.0)
_F32_ONE = np.float32(1.0)


# ---------------------------------------------------------------------------------------------
# Counter-based RNG (render.rng, bit for bit)
# ---------------------------------------------------------------------------------------------

@njit(inline="always")
def _mix(h):
    """splitmix64 finaliser of one uint64."""
    h ^= h >> _S30
    h *= _M1
    h ^= h >> _S27
    h *= _M2
    h ^= h >> _S31
    return h


@njit(inline="always")
def key_start(seed, purpose):
    """The part of ``rng.hash_keys`` that depends on (seed, purpose) only."""
    return _mix(np.uint64(seed) * _GOLDEN + np.uint64(purpose))


@njit(inline="always")
def hash_key(start, pixel, sample, bounce, index):
    """``rng.hash_keys`` of one key, from ``key_start(seed, purpose)``."""
    h = start ^ np.uint64(pixel)
    h = _mix(h + _GOLDEN)
    h ^= np.uint64(sample)
    h = _mix(h + _GOLDEN)
    h ^= np.uint64(bounce) | (np.uint64(index) << _S8)
    return _mix(h + _GOLDEN)


@njit(inline="always")
def _uniform_pair(h):
    """``rng.uniform2``'s two float32 uniforms from one hash."""
    u = np.float32(h >> _TOP24) * _INV24
    v = np.float32((h >> _MID24) & _MASK24) * _INV24
    return u, v


@njit(nogil=True, cache=True, error_model="numpy")
def uniform2(seed, purpose, pixel, sample, bounce, index):
    """``rng.uniform2`` for arrays of keys (tests compare the two).

    Parameters
    ----------
    seed, purpose : uint64 scalars.
    pixel, sample, bounce, index : (n,) unsigned integer arrays.

    Returns
    -------
    u, v : (n,) float32 each
    """
    n = pixel.shape[0]
    u = np.empty(n, np.float32)
    v = np.empty(n, np.float32)
    start = key_start(seed, purpose)
    for i in range(n):
        u[i], v[i] = _uniform_pair(hash_key(start, pixel[i], sample[i], bounce[i], index[i]))
    return u, v


@njit(nogil=True, cache=True, error_model="numpy")
def hemisphere_uniforms(seed, purpose, pixel, sample, path, bounce, m):
    """The uniforms of ``m`` cosine-hemisphere samples per vertex, vertex-major.

    Parameters
    ----------
    seed, purpose : uint64 scalars.
    pixel, sample : (P,) uint32 keys of the batch's paths.
    path : (k,) int64 path of each vertex; bounce : (k,) its bounce (path vertex) index.
    m : samples per vertex; sample ``j`` of vertex ``i`` is row ``i * m + j``, index ``j``.

    Returns
    -------
    u, v : (k * m,) float32 each
    """
    k = path.shape[0]
    u = np.empty(k * m, np.float32)
    v = np.empty(k * m, np.float32)
    start = key_start(seed, purpose)
    for i in range(k):
        p = path[i]
        for j in range(m):
            u[i * m + j], v[i * m + j] = _uniform_pair(
                hash_key(start, pixel[p], sample[p], bounce[i], j))
    return u, v


def hemisphere_angles(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of the azimuths ``2 pi v`` ((n,) float32 each), with numpy's float32
    routines, exactly as ``oracles.cosine_hemisphere`` takes them."""
    phi = 2.0 * np.pi * v
    return np.cos(phi), np.sin(phi)


# ---------------------------------------------------------------------------------------------
# Row helpers (numpy's operation order; see the module docstring)
# ---------------------------------------------------------------------------------------------

@njit(inline="always")
def _maximum(a, b):
    """``np.maximum`` of two scalars (NaN in ``a`` propagates)."""
    return a if (a >= b or a != a) else b


@njit(inline="always")
def _dot(a0, a1, a2, b0, b1, b2):
    """``np.einsum("ij,ij->i")`` of one 3-row."""
    return (a0 * b0 + a2 * b2) + a1 * b1


@njit(inline="always")
def _hemisphere(n0, n1, n2, u, c, s):
    """``oracles.cosine_hemisphere`` of one normal, uniform ``u`` and azimuth cos/sin."""
    r = np.sqrt(u)
    x = r * c
    y = r * s
    z = np.sqrt(_maximum(_F32_ZERO, _F32_ONE - u))
    sign = 1.0 if n2 >= 0 else -1.0
    a = -1.0 / (sign + n2)
    b_ = n0 * n1 * a
    t0 = 1.0 + sign * n0 * n0 * a
    t1 = sign * b_
    t2 = -sign * n0
    b1 = sign + n1 * n1 * a
    b2 = -n1
    xf, yf, zf = np.float64(x), np.float64(y), np.float64(z)
    return (t0 * xf + b_ * yf + n0 * zf, t1 * xf + b1 * yf + n1 * zf, t2 * xf + b2 * yf + n2 * zf)


@njit(inline="always")
def _frame(dirs, point, error, normal, i):
    """Direction, facing normal, hit point and spawned origin of row ``i`` (``integrators.shade``'s
    first lines and ``oracles.spawn``): returns (d0, d1, d2, nf0, nf1, nf2, p0, p1, p2, o0, o1, o2).

    The origin is the hit point moved ``error[i]`` along the facing normal (pbrt-v4's
    ``OffsetRayOrigin``): far enough that Embree cannot find the surface again, and
    independent of the distance the hit was reached from."""
    d0, d1, d2 = np.float64(dirs[i, 0]), np.float64(dirs[i, 1]), np.float64(dirs[i, 2])
    p0, p1, p2 = point[i, 0], point[i, 1], point[i, 2]
    g0, g1, g2 = normal[i, 0], normal[i, 1], normal[i, 2]
    side = -1.0 if _dot(g0, g1, g2, d0, d1, d2) > 0 else 1.0
    nf0, nf1, nf2 = g0 * side, g1 * side, g2 * side
    e = error[i]
    return (d0, d1, d2, nf0, nf1, nf2, p0, p1, p2, p0 + nf0 * e, p1 + nf1 * e, p2 + nf2 * e)


@njit(nogil=True, cache=True, error_model="numpy")
def hit_points(rows, prim, u, v, vertices, indices, point, error):
    """Hit points rebuilt from Embree's barycentrics, with a bound on their error.

    ``p = v0 + u (v1 - v0) + v (v2 - v0)`` in float64 from the float32 vertices lies on the
    triangle's plane up to float64 rounding, whatever the distance the ray travelled (its
    float32 ``tfar`` would put ``o + t d`` up to ``t`` float32 ulps off the surface). The bound
    ``HIT_ERROR * (M + L / sin)`` covers what the float32 query itself gets wrong: roundoff of
    coordinates of magnitude ``M`` (the largest vertex coordinate) and the tilt of the float32
    normal of a thin triangle (longest edge ``L``, ``sin`` of its angle at ``v0``, capped at
    ``1 / _SLIVER``).

    Parameters
    ----------
    rows : (k,) int64 rows of ``point``/``error`` to write; prim : (k,) int32 triangles.
    u, v : (k,) float32 Embree's barycentrics of ``v1`` and ``v2``.
    vertices : (V, 3) float32; indices : (T, 3) uint32 the domain's triangles.
    point : (n, 3) float64 out; error : (n,) float64 out.
    """
    corners = np.empty((_BLOCK, 9), np.float32)
    for first in range(0, rows.shape[0], _BLOCK):
        last = min(first + _BLOCK, rows.shape[0])
        _gather_corners(prim, first, last, vertices, indices, corners)
        for k in range(first, last):
            _rebuild_point(rows[k], np.float64(u[k]), np.float64(v[k]), corners, k - first,
                           point, error)


#: Hits a kernel gathers the triangle corners of before it rebuilds their points: the
#: gathers, cache misses for incoherent rays, then overlap (a loop of loads only keeps many in
#: flight; interleaved with the arithmetic they took 91 against 26-42 ns a ray, issue 39).
_BLOCK = 64


@njit(inline="always")
def _gather_corners(prim, first, last, vertices, indices, corners):
    """The corners of triangles ``prim[first:last]`` (skipping misses, ``prim < 0``) into rows
    ``0 .. last - first`` of ``corners`` ((_BLOCK, 9) float32: v0, v1, v2)."""
    for k in range(first, last):
        p = prim[k]
        if p < 0:
            continue
        j = k - first
        a, b, c = indices[p, 0], indices[p, 1], indices[p, 2]
        corners[j, 0], corners[j, 1], corners[j, 2] = vertices[a, 0], vertices[a, 1], vertices[a, 2]
        corners[j, 3], corners[j, 4], corners[j, 5] = vertices[b, 0], vertices[b, 1], vertices[b, 2]
        corners[j, 6], corners[j, 7], corners[j, 8] = vertices[c, 0], vertices[c, 1], vertices[c, 2]


@njit(inline="always")
def _rebuild_point(i, uk, vk, corners, j, point, error):
    """``hit_points`` for one hit: row ``i`` of ``point``/``error`` from the triangle whose
    corners are row ``j`` of ``corners``, at barycentrics ``uk, vk`` (float64)."""
    # scalars, not small arrays: two np.empty(3) a hit were a third of this kernel's time
    a0, a1, a2 = (np.float64(corners[j, 0]), np.float64(corners[j, 1]),
                  np.float64(corners[j, 2]))
    b0, b1, b2 = (np.float64(corners[j, 3]), np.float64(corners[j, 4]),
                  np.float64(corners[j, 5]))
    c0, c1, c2 = (np.float64(corners[j, 6]), np.float64(corners[j, 7]),
                  np.float64(corners[j, 8]))
    e10, e11, e12 = b0 - a0, b1 - a1, b2 - a2
    e20, e21, e22 = c0 - a0, c1 - a1, c2 - a2
    point[i, 0] = a0 + uk * e10 + vk * e20
    point[i, 1] = a1 + uk * e11 + vk * e21
    point[i, 2] = a2 + uk * e12 + vk * e22
    magnitude = max(0.0, abs(a0), abs(b0), abs(c0))
    magnitude = max(magnitude, abs(a1), abs(b1), abs(c1))
    magnitude = max(magnitude, abs(a2), abs(b2), abs(c2))
    n0 = e11 * e22 - e12 * e21
    n1 = e12 * e20 - e10 * e22
    n2 = e10 * e21 - e11 * e20
    area2 = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    l1 = np.sqrt(e10 * e10 + e11 * e11 + e12 * e12)
    l2 = np.sqrt(e20 * e20 + e21 * e21 + e22 * e22)
    l3 = np.sqrt((e20 - e10) ** 2 + (e21 - e11) ** 2 + (e22 - e12) ** 2)
    longest = max(l1, l2, l3)
    product = l1 * l2
    tilt = longest * _SLIVER if area2 * _SLIVER <= product else longest * product / area2
    error[i] = HIT_ERROR * (magnitude + tilt)


@njit(nogil=True, cache=True, error_model="numpy")
def one_domain_hits(prim, tfar, u, v, ng, vertices, indices, t, normal, point, error):
    """The final hits of rays queried in one domain only, in one pass: what
    ``ClosestHits.offer`` (into an empty record) and then ``ClosestHits.hits`` give, bit for
    bit, without the record between them.

    Parameters
    ----------
    prim : (n,) int32 (-1: a miss); tfar, u, v : (n,) float32; ng : (n, 3) float32 Embree's
        output for the n rays.
    vertices : (V, 3) float32; indices : (T, 3) uint32 the domain's triangles.
    t : (n,) float64 out (inf: a miss); normal : (n, 3) float64 out, unit (0 for a miss);
    point : (n, 3) float64 out and error : (n,) float64 out (``hit_points``; 0 for a miss).
    """
    corners = np.empty((_BLOCK, 9), np.float32)
    for first in range(0, prim.shape[0], _BLOCK):
        last = min(first + _BLOCK, prim.shape[0])
        _gather_corners(prim, first, last, vertices, indices, corners)
        for i in range(first, last):
            if prim[i] < 0:
                t[i] = np.inf
                normal[i, 0], normal[i, 1], normal[i, 2] = 0.0, 0.0, 0.0
                point[i, 0], point[i, 1], point[i, 2] = 0.0, 0.0, 0.0
                error[i] = 0.0
                continue
            t[i] = np.float64(tfar[i])
            normal[i, 0], normal[i, 1], normal[i, 2] = _unit(ng[i, 0], ng[i, 1], ng[i, 2])
            _rebuild_point(i, np.float64(u[i]), np.float64(v[i]), corners, i - first, point,
                           error)


@njit(nogil=True, cache=True, error_model="numpy")
def scalar_colors(prim, u, v, indices, scalars, lo, hi, table, nan_color, out):
    """``tracer.vertex_color`` of a scalar-coloured domain in one pass: the vertex scalars
    interpolated at Embree's barycentrics, then ``materials.colormap``, bit for bit.

    Parameters
    ----------
    prim : (k,) int32 triangles hit; u, v : (k,) float32 their barycentrics.
    indices : (T, 3) uint32; scalars : (V,) float32 per vertex.
    lo, hi : float64 the range mapped to the table's ends; table : (m, 3) float64, m >= 2.
    nan_color : (3,) float64, the colour of a NaN scalar; out : (k, 3) float64.
    """
    span = hi - lo if hi > lo else 1.0
    top = table.shape[0] - 1
    for k in range(prim.shape[0]):
        p = prim[k]
        w0 = np.float64(_F32_ONE - u[k] - v[k])  # float32 arithmetic, as numpy's
        s0 = np.float64(scalars[indices[p, 0]])
        s1 = np.float64(scalars[indices[p, 1]])
        s2 = np.float64(scalars[indices[p, 2]])
        x = (_dot(w0, np.float64(u[k]), np.float64(v[k]), s0, s1, s2) - lo) / span
        if np.isnan(x):
            out[k, 0], out[k, 1], out[k, 2] = nan_color[0], nan_color[1], nan_color[2]
            continue
        x = min(max(x, 0.0), 1.0) * top
        i = min(np.int64(x), top - 1)
        f = x - i
        g = 1.0 - f
        for c in range(3):
            out[k, c] = table[i, c] * g + table[i + 1, c] * f


@njit(nogil=True, cache=True, error_model="numpy")
def first_hits(path, t, normal, dirs, start, first_t, first_normal):
    """``PathResult.record_camera_hits``' layers in one pass: for camera ray k of path
    ``path[k]``, ``first_t = t + start`` and ``first_normal`` the normal facing the ray
    (``tracer.facing``, whose ``einsum`` sums in ``_dot``'s order), both stored as float32.

    Parameters
    ----------
    path : (k,) int64; t : (k,) float64; normal : (k, 3) float64; dirs : (k, 3) float32.
    start : float64, how far from the camera the rays started.
    first_t : (P,) float32 out; first_normal : (P, 3) float32 out.
    """
    for k in range(path.shape[0]):
        i = path[k]
        first_t[i] = t[k] + start
        g0, g1, g2 = normal[k, 0], normal[k, 1], normal[k, 2]
        side = -1.0 if _dot(g0, g1, g2, np.float64(dirs[k, 0]), np.float64(dirs[k, 1]),
                            np.float64(dirs[k, 2])) > 0 else 1.0
        first_normal[i, 0], first_normal[i, 1], first_normal[i, 2] = (g0 * side, g1 * side,
                                                                      g2 * side)


@njit(nogil=True, cache=True, error_model="numpy")
def ray_points(org, dirs, t, point, error):
    """Hit points ``o + t d`` (float64) with the bound ``HIT_ERROR * (max|p| + t)``: for hit
    records that carry no rebuilt point (``Hits.point`` None; tests build such hits).

    Parameters
    ----------
    org, dirs : (k, 3) float32; t : (k,) float64; point : (k, 3) float64 out;
    error : (k,) float64 out.
    """
    for i in range(org.shape[0]):
        ti = t[i]
        p0 = np.float64(org[i, 0]) + np.float64(dirs[i, 0]) * ti
        p1 = np.float64(org[i, 1]) + np.float64(dirs[i, 1]) * ti
        p2 = np.float64(org[i, 2]) + np.float64(dirs[i, 2]) * ti
        point[i, 0], point[i, 1], point[i, 2] = p0, p1, p2
        error[i] = HIT_ERROR * (max(abs(p0), abs(p1), abs(p2)) + abs(ti))


# ---------------------------------------------------------------------------------------------
# Ambient occlusion
# ---------------------------------------------------------------------------------------------

@njit(nogil=True, cache=True, error_model="numpy")
def shade_ao(rows, dirs, point, error, normal, color, has_color, m, hu, hc, hs, s_org, s_dir,
             s_contrib):
    """``oracles._ambient_occlusion_rays``: ``m`` cosine-weighted rays per hit.

    Parameters
    ----------
    rows : (k,) int64 the rows of the inputs below to shade, in order (the hits: reading
        them in place spares the caller a take of every array).
    dirs : (n, 3) float32 radiance ray directions; point : (n, 3) float64 hit points;
    error : (n,) float64 their error bounds; normal : (n, 3) float64.
    color : (n, 3) float64 (read only when ``has_color``).
    m : rays per hit (>= 1); hu, hc, hs : (k * m,) float32 uniform u and azimuth cos/sin.
    s_org, s_dir : (k * m, 3) float32 out; s_contrib : (k * m, 3) float64 out.
    """
    k = rows.shape[0]
    for i in range(k):
        q = rows[i]
        _, _, _, nf0, nf1, nf2, _, _, _, o0, o1, o2 = _frame(dirs, point, error, normal, q)
        if has_color:
            c0, c1, c2 = color[q, 0] / m, color[q, 1] / m, color[q, 2] / m
        else:
            c0 = c1 = c2 = 1.0 / m
        for j in range(m):
            r = i * m + j
            w0, w1, w2 = _hemisphere(nf0, nf1, nf2, hu[r], hc[r], hs[r])
            s_org[r, 0], s_org[r, 1], s_org[r, 2] = o0, o1, o2
            s_dir[r, 0], s_dir[r, 1], s_dir[r, 2] = w0, w1, w2
            s_contrib[r, 0], s_contrib[r, 1], s_contrib[r, 2] = c0, c1, c2


# ---------------------------------------------------------------------------------------------
# Path tracing: next-event estimation and the continuation bounce
# ---------------------------------------------------------------------------------------------

@njit(inline="always")
def _sample_light(kind, prm, o0, o1, o2, nf0, nf1, nf2, su, sv, hu, hc, hs):
    """``oracles.sample_light`` for one row: (wi0, wi1, wi2, dist, inc0, inc1, inc2).

    ``su, sv``: the row's quad-light uniforms; ``hu, hc, hs``: its ambient hemisphere sample.
    """
    if kind == POINT:
        l0, l1, l2 = prm[0] - o0, prm[1] - o1, prm[2] - o2
        dist = np.sqrt((l0 * l0 + l1 * l1) + l2 * l2)
        inv = _maximum(dist, 1e-300)
        d2 = _maximum(dist * dist, 1e-300)
        return l0 / inv, l1 / inv, l2 / inv, dist, prm[3] / d2, prm[4] / d2, prm[5] / d2
    if kind == DIRECTIONAL:
        return prm[0], prm[1], prm[2], np.inf, prm[3], prm[4], prm[5]
    if kind == QUAD:
        s, tt = np.float64(su), np.float64(sv)
        l0 = (prm[0] + s * prm[3]) + tt * prm[6] - o0
        l1 = (prm[1] + s * prm[4]) + tt * prm[7] - o1
        l2 = (prm[2] + s * prm[5]) + tt * prm[8] - o2
        dist2 = _dot(l0, l1, l2, l0, l1, l2)
        dist = np.sqrt(dist2)
        inv = _maximum(dist, 1e-300)
        w0, w1, w2 = l0 / inv, l1 / inv, l2 / inv
        area = prm[15]
        facing = (w0 * prm[12] + w1 * prm[13]) + w2 * prm[14]  # lights.QuadLight._cos_area
        cos_light = _maximum(0.0, -facing / area)
        g = cos_light * area / _maximum(dist2, 1e-300)
        return w0, w1, w2, dist, prm[9] * g, prm[10] * g, prm[11] * g
    # AMBIENT
    w0, w1, w2 = _hemisphere(nf0, nf1, nf2, hu, hc, hs)
    cos = _maximum(_dot(w0, w1, w2, nf0, nf1, nf2), 1e-12)
    g = _PI / cos
    return w0, w1, w2, np.inf, prm[0] * g, prm[1] * g, prm[2] * g


@njit(nogil=True, cache=True, error_model="numpy")
def shade_pt(rows, path, depth, dirs, beta, point, error, normal, material, color, has_color,
             pixel, sample, seed, bounces, diffuse, has_specular,
             kinds, counts, purposes, params, hem_slot, hem_u, hem_c, hem_s, bu, bc, bs,
             s_path, s_depth, s_org, s_dir, s_tmax, s_contrib, s_vertex, s_weight, s_cos_h,
             c_path, c_depth, c_org, c_dir, c_beta):
    """``integrators.shade`` for path tracing: next-event rays to every light, then the
    continuation bounce. Rows come out in the numpy path's order: light by light, vertex-major
    within a light (sample ``j`` innermost), unoccluded-useless samples left out.

    Parameters
    ----------
    rows : (k,) int64 the rows of the per-ray inputs below to shade, in order (the rays that
        hit: reading them in place spares the caller a take of every array).
    path : (n,) int64; depth : (n,) uint8; dirs : (n, 3) float32; beta : (n, 3) float64
        the radiance rays.
    point : (n, 3) float64 hit points and error : (n,) float64 their bounds
        (``hit_points``); lights are sampled from the point, rays leave from it offset.
    normal : (n, 3) float64 unit geometric normals; material : (n,) int64;
        color : (n, 3) float64 (read only when ``has_color``).
    pixel, sample : (P,) uint32 path keys; seed : uint64; bounces : the last vertex that
        continues is ``bounces - 1``.
    diffuse : (M, 3) float64 albedo per material; has_specular : also fill ``s_vertex``,
        ``s_weight`` and ``s_cos_h`` for the Blinn-Phong term (added afterwards in numpy).
    kinds, counts : (L,) int64 light kind and samples per vertex (0: skipped);
        purposes : (L,) uint64 each light's RNG purpose (``Purpose.LIGHT_SAMPLE + 16 * l``);
        params : (L, LIGHT_PARAMS) float64 (``integrators._light_table``).
    hem_slot : (L,) int64 row of ``hem_u/c/s`` holding an ambient light's hemisphere samples;
        hem_u, hem_c, hem_s : (A, k * m) float32 uniform u and azimuth cos/sin.
    bu, bc, bs : (k,) float32 the continuation bounce's u and azimuth cos/sin (read only for
        rows with ``depth < bounces``).
    s_* : shadow-ray outputs with room for every sample: path, depth, origin, direction,
        t_max, contribution; s_vertex (int64: the shaded row, an index into ``rows``),
        s_weight ((., 3) float64), s_cos_h (float64).
    c_* : continuation outputs with room for k rows: path, depth, origin, direction, beta.

    Returns
    -------
    (shadow rays written, continuation rays written)
    """
    k = rows.shape[0]
    n_shadow = 0
    for li in range(kinds.shape[0]):
        m = counts[li]
        if m == 0:
            continue
        kind = kinds[li]
        prm = params[li]
        start = key_start(seed, purposes[li])
        slot = hem_slot[li]
        for i in range(k):
            q = rows[i]
            d0, d1, d2, nf0, nf1, nf2, p0, p1, p2, o0, o1, o2 = _frame(dirs, point, error,
                                                                       normal, q)
            a0, a1, a2 = diffuse[material[q], 0], diffuse[material[q], 1], diffuse[material[q], 2]
            if has_color:
                a0, a1, a2 = a0 * color[q, 0], a1 * color[q, 1], a2 * color[q, 2]
            td0 = beta[q, 0] * a0 / _PI
            td1 = beta[q, 1] * a1 / _PI
            td2 = beta[q, 2] * a2 / _PI
            p = path[q]
            dq = depth[q]
            for j in range(m):
                su = sv = hu = hc = hs = _F32_ZERO
                if kind == QUAD:
                    su, sv = _uniform_pair(hash_key(start, pixel[p], sample[p], dq, j))
                elif kind == AMBIENT:
                    r = i * m + j
                    hu, hc, hs = hem_u[slot, r], hem_c[slot, r], hem_s[slot, r]
                w0, w1, w2, dist, e0, e1, e2 = _sample_light(kind, prm, p0, p1, p2,
                                                             nf0, nf1, nf2, su, sv, hu, hc, hs)
                cos_i = _dot(nf0, nf1, nf2, w0, w1, w2)
                if not (cos_i > 0 and (e0 + e1) + e2 > 0):
                    continue
                c = cos_i / m
                g0, g1, g2 = c * e0, c * e1, c * e2
                n = n_shadow
                s_path[n] = p
                s_depth[n] = dq
                s_org[n, 0], s_org[n, 1], s_org[n, 2] = o0, o1, o2
                s_dir[n, 0], s_dir[n, 1], s_dir[n, 2] = w0, w1, w2
                s_tmax[n] = dist * _SHORTEN
                s_contrib[n, 0], s_contrib[n, 1], s_contrib[n, 2] = td0 * g0, td1 * g1, td2 * g2
                if has_specular:
                    h0, h1, h2 = -d0 + w0, -d1 + w1, -d2 + w2
                    hn = _maximum(np.sqrt((h0 * h0 + h1 * h1) + h2 * h2), 1e-300)
                    s_vertex[n] = i
                    s_weight[n, 0], s_weight[n, 1], s_weight[n, 2] = g0, g1, g2
                    s_cos_h[n] = _maximum(0.0, _dot(nf0, nf1, nf2, h0 / hn, h1 / hn, h2 / hn))
                n_shadow += 1
    n_cont = 0
    for i in range(k):
        q = rows[i]
        if depth[q] >= bounces:
            continue
        _, _, _, nf0, nf1, nf2, _, _, _, o0, o1, o2 = _frame(dirs, point, error, normal, q)
        a0, a1, a2 = diffuse[material[q], 0], diffuse[material[q], 1], diffuse[material[q], 2]
        if has_color:
            a0, a1, a2 = a0 * color[q, 0], a1 * color[q, 1], a2 * color[q, 2]
        b0, b1, b2 = beta[q, 0] * a0, beta[q, 1] * a1, beta[q, 2] * a2
        if not (b0 > 0 or b1 > 0 or b2 > 0):
            continue
        w0, w1, w2 = _hemisphere(nf0, nf1, nf2, bu[i], bc[i], bs[i])
        n = n_cont
        c_path[n] = path[q]
        c_depth[n] = depth[q] + 1
        c_org[n, 0], c_org[n, 1], c_org[n, 2] = o0, o1, o2
        c_dir[n, 0], c_dir[n, 1], c_dir[n, 2] = w0, w1, w2
        c_beta[n, 0], c_beta[n, 1], c_beta[n, 2] = b0, b1, b2
        n_cont += 1
    return n_shadow, n_cont


@njit(nogil=True, cache=True, error_model="numpy")
def add_unoccluded(radiance, path, contribution, lit):
    """``radiance[path[r]] += contribution[r]`` for the rows ``r`` with ``lit[r]``, summed per
    path in row order first (as ``np.bincount`` does), then added.

    Parameters
    ----------
    radiance : (P, 3) float64, updated; path : (n,) int64; contribution : (n, 3) float64;
    lit : (n,) bool
    """
    # Only the paths with a lit row are summed and added: a path's sum starts at 0.0 when its
    # first row comes, and adding 0.0 to the others would change no bit (a sum that started
    # at +0.0 is never -0.0). Nothing of size P is zeroed or walked (1.5 MB a 65,536-path batch).
    acc = np.empty(radiance.shape)
    seen = np.zeros(radiance.shape[0], np.bool_)
    for r in range(path.shape[0]):
        if lit[r]:
            p = path[r]
            if not seen[p]:
                seen[p] = True
                acc[p, 0], acc[p, 1], acc[p, 2] = 0.0, 0.0, 0.0
            acc[p, 0] += contribution[r, 0]
            acc[p, 1] += contribution[r, 1]
            acc[p, 2] += contribution[r, 2]
    for r in range(path.shape[0]):
        if lit[r]:
            p = path[r]
            if seen[p]:  # once per path
                seen[p] = False
                radiance[p, 0] += acc[p, 0]
                radiance[p, 1] += acc[p, 1]
                radiance[p, 2] += acc[p, 2]


@njit(nogil=True, cache=True, error_model="numpy")
def add_to_rows(radiance, rows, value):
    """``radiance[rows] += value`` in one pass, bit for bit numpy's (each element's one
    float64 addition), without numpy's gather and scatter of the rows (45 ns a row there).

    Parameters
    ----------
    radiance : (n, 3) float64, added to in place; rows : (n,) bool; value : (3,) float64.
    """
    for i in range(radiance.shape[0]):
        if rows[i]:
            radiance[i, 0] += value[0]
            radiance[i, 1] += value[1]
            radiance[i, 2] += value[2]


@njit(nogil=True, cache=True, error_model="numpy")
def film_add(total, batch, count, pixel, radiance, counted, sample):
    """``Film.add``'s sums over the batch's pixel run: per pixel, the rows' radiance, and per
    batch the rows' radiance again (per channel), summed in row order from zero (as
    ``np.bincount`` sums its weights), then added to the film's.

    Parameters
    ----------
    total : (P, 3) float64, updated; batch : (P, B, 3) float64, updated; count : (P,) int64,
        updated.
    pixel : (n,) uint32 (an ``IndexError`` past the film's P pixels); radiance : (n, 3)
        float64.
    counted : (n,) bool, the rows that count as samples, or (0,): every row counts.
    sample : (n,) uint32, each row's sample number (its batch: the number mod B), or (0,):
        every row in batch 0.
    """
    n = pixel.shape[0]
    if n == 0:
        return
    lo = np.int64(pixel[0])
    hi = lo
    ascending = True
    for r in range(n):
        p = np.int64(pixel[r])
        ascending = ascending and p >= hi
        lo = min(lo, p)
        hi = max(hi, p)
    if hi >= total.shape[0]:  # (the keys are unsigned: lo >= 0)
        raise IndexError("film_add: a pixel outside the film")
    nb = batch.shape[1]
    every_row = counted.shape[0] == 0
    batch_zero = sample.shape[0] == 0
    if ascending:  # a render's batches: each pixel's rows in one run
        _film_add_runs(total, batch, count, pixel, radiance, counted, sample, every_row,
                       batch_zero)
        return
    m = hi - lo + 1
    acc = np.zeros((m, 3))
    acc_batch = np.zeros((m, nb, 3))
    hits = np.zeros(m, np.int64)
    for r in range(n):
        p = np.int64(pixel[r]) - lo
        b = 0 if batch_zero else np.int64(sample[r] % nb)
        for c in range(3):
            acc[p, c] += radiance[r, c]
            acc_batch[p, b, c] += radiance[r, c]
        if every_row or counted[r]:
            hits[p] += 1
    for p in range(m):
        for c in range(3):
            total[lo + p, c] += acc[p, c]
        for b in range(nb):
            for c in range(3):
                batch[lo + p, b, c] += acc_batch[p, b, c]
        count[lo + p] += hits[p]


@njit(nogil=True, cache=True, error_model="numpy")
def _film_add_runs(total, batch, count, pixel, radiance, counted, sample, every_row,
                   batch_zero):
    """``film_add``'s sums where the rows' pixels never decrease (each pixel's rows are one
    run): the same sums, each pixel's and batch's rows added in row order from zero and then
    to the film's, bit for bit, without a temporary over the pixel run. A row of zero
    radiance (either sign) adds nothing to a sum started at +0.0 (such a sum is never -0.0),
    so only its count is taken."""
    n = pixel.shape[0]
    nb = batch.shape[1]
    acc = np.zeros(3)
    acc_batch = np.zeros((nb, 3))
    hits = 0
    for r in range(n):
        p = np.int64(pixel[r])
        if every_row or counted[r]:
            hits += 1
        r0, r1, r2 = radiance[r, 0], radiance[r, 1], radiance[r, 2]
        if r0 != 0.0 or r1 != 0.0 or r2 != 0.0:
            b = 0 if batch_zero else np.int64(sample[r] % nb)
            acc[0] += r0
            acc[1] += r1
            acc[2] += r2
            acc_batch[b, 0] += r0
            acc_batch[b, 1] += r1
            acc_batch[b, 2] += r2
        if r + 1 == n or np.int64(pixel[r + 1]) != p:  # the run's last row: into the film
            for c in range(3):
                total[p, c] += acc[c]
                acc[c] = 0.0
            for b in range(nb):
                for c in range(3):
                    batch[p, b, c] += acc_batch[b, c]
                    acc_batch[b, c] = 0.0
            count[p] += hits
            hits = 0


@njit(nogil=True, cache=True, error_model="numpy")
def film_first_hits(depth, normal, pixel, sample, first_t, first_normal):
    """``Film.add_paths``' depth and normal layers: each row of sample 0 sets its pixel's
    (rows in order: a later row of the same pixel wins, as numpy's assignment).

    Parameters
    ----------
    depth : (P,) float32, updated; normal : (P, 3) float32, updated.
    pixel, sample : (n,) uint32 (an ``IndexError`` for a pixel past the film); first_t : (n,)
        float32; first_normal : (n, 3) float32.
    """
    for r in range(pixel.shape[0]):
        if sample[r] == 0:
            p = pixel[r]
            if p >= depth.shape[0]:
                raise IndexError("film_first_hits: a pixel outside the film")
            depth[p] = first_t[r]
            normal[p, 0] = first_normal[r, 0]
            normal[p, 1] = first_normal[r, 1]
            normal[p, 2] = first_normal[r, 2]


@njit(nogil=True, cache=True, error_model="numpy")
def path_keys(first, s0, per_pixel, pixel, sample):
    """The keys of paths ``first``, ``first + 1``, ...: path ``i`` is pixel ``i // per_pixel``,
    sample ``s0 + i % per_pixel`` (``driver.path_context``), counted on from the first path
    (one division per batch, not one per path).

    Parameters
    ----------
    first, s0, per_pixel : non-negative ints, ``per_pixel`` >= 1.
    pixel, sample : (n,) uint32 out.
    """
    p = first // per_pixel
    k = first - p * per_pixel
    for i in range(pixel.shape[0]):
        pixel[i] = p
        sample[i] = s0 + k
        k += 1
        if k == per_pixel:
            k = 0
            p += 1


# ---------------------------------------------------------------------------------------------
# Camera rays and hit records
# ---------------------------------------------------------------------------------------------

#: Rays a chunk of ``camera_rays``' vectorised loop.
_CAMERA_CHUNK = 64


@njit(nogil=True, cache=True, error_model="numpy")
def camera_rays(pixel, sample, seed, purpose, width, height, tan_half, aspect, position,
                forward, right, up, advance, origin, direction):
    """``Camera.generate`` cast to float32, as ``integrators.camera_rays`` uses it, each ray
    starting ``advance`` along its float64 direction from the camera (``Camera.start``: 0
    unless the camera is far from the scene).

    Parameters
    ----------
    pixel, sample : (n,) uint32; seed, purpose : uint64 (``Purpose.CAMERA_JITTER``).
    width, height : image size; tan_half, aspect : ``tan(fov / 2)`` and ``width / height``
        as ``Camera.generate`` computes them.
    position, forward, right, up : (3,) float64 (``Camera.frame``); advance : float64.
    origin, direction : (n, 3) float32 out.
    """
    start = key_start(seed, purpose)
    n = pixel.shape[0]
    # directions a chunk at a time into contiguous columns (a loop LLVM vectorises), then
    # stored into the (n, 3) rows
    dx, dy, dz = np.empty(_CAMERA_CHUNK), np.empty(_CAMERA_CHUNK), np.empty(_CAMERA_CHUNK)
    for base in range(0, n, _CAMERA_CHUNK):
        m = min(_CAMERA_CHUNK, n - base)
        _camera_directions(pixel, sample, start, base, m, width, height, tan_half, aspect,
                           forward, right, up, dx, dy, dz)
        for k in range(m):
            _store_camera_ray(base + k, dx[k], dy[k], dz[k], position, advance, origin,
                              direction)


@njit(nogil=True, cache=True, error_model="numpy")
def camera_rays_in_box(pixel, sample, seed, purpose, width, height, tan_half, aspect,
                       position, forward, right, up, advance, lo, hi, seen, rows, origin,
                       direction):
    """``camera_rays``' rays, bit for bit, of the paths whose float32 ray enters the box
    ``[lo, hi]`` through a pixel ``seen`` keeps, only (the others cannot hit anything in it):
    their rows of the batch into ``rows`` and the rays into the first rows of ``origin`` and
    ``direction``, in order.

    Parameters
    ----------
    pixel ... advance : as ``camera_rays``.
    lo, hi : (3,) float64 the box, grown by the caller so that rounding cannot drop a ray
        that enters it (``integrators.seen_camera_rays``).
    seen : (width * height,) bool, the pixels whose rays can meet something
        (``render.seen_pixels``), or (0,): every pixel.
    rows : (n,) int64 out; origin, direction : (n, 3) float32 out.

    Returns
    -------
    int, the number of rays kept.
    """
    start = key_start(seed, purpose)
    n = pixel.shape[0]
    dx, dy, dz = np.empty(_CAMERA_CHUNK), np.empty(_CAMERA_CHUNK), np.empty(_CAMERA_CHUNK)
    inside = np.empty(_CAMERA_CHUNK, np.bool_)
    at = np.empty(_CAMERA_CHUNK, np.int64)  # the chunk's rows whose pixel is seen
    every_pixel = seen.shape[0] == 0
    if not every_pixel and seen.shape[0] != width * height:
        raise IndexError("camera_rays_in_box: seen is not one flag per pixel")
    w, h = np.float64(width), np.float64(height)
    # the origins as _store_camera_ray makes them: moved by ``advance`` only where positive
    reach = advance if advance > 0 else 0.0
    kept = 0
    for base in range(0, n, _CAMERA_CHUNK):
        m = min(_CAMERA_CHUNK, n - base)
        if every_pixel:
            _camera_directions(pixel, sample, start, base, m, width, height, tan_half, aspect,
                               forward, right, up, dx, dy, dz)
            for k in range(m):
                at[k] = base + k
        else:  # only the rays of pixels seen are made at all
            count = 0
            for k in range(m):
                p = pixel[base + k]
                if p >= seen.shape[0]:
                    raise IndexError("camera_rays_in_box: a pixel outside the image")
                if seen[p]:
                    at[count] = base + k
                    count += 1
            m = count
            for k in range(m):
                i = at[k]
                dx[k], dy[k], dz[k] = _camera_direction(pixel[i], sample[i], start, w, h,
                                                        tan_half, aspect, forward, right, up)
        # no stores but one column, no branch: a loop LLVM vectorises
        for k in range(m):
            n0, f0 = _slab(position[0] + dx[k] * reach, dx[k], lo[0], hi[0])
            n1, f1 = _slab(position[1] + dy[k] * reach, dy[k], lo[1], hi[1])
            n2, f2 = _slab(position[2] + dz[k] * reach, dz[k], lo[2], hi[2])
            inside[k] = _overlap(n0, f0, n1, f1, n2, f2)
        for k in range(m):
            if inside[k]:
                _store_camera_ray(kept, dx[k], dy[k], dz[k], position, advance, origin,
                                  direction)
                rows[kept] = at[k]
                kept += 1
    return kept


@njit(inline="always", nogil=True, error_model="numpy")
def _camera_directions(pixel, sample, start, base, m, width, height, tan_half, aspect,
                       forward, right, up, dx, dy, dz):
    """The float64 unit directions of the camera rays ``base .. base + m`` into the columns
    ``dx, dy, dz`` ((``_CAMERA_CHUNK``,) float64)."""
    w, h = np.float64(width), np.float64(height)
    for k in range(m):
        i = base + k
        dx[k], dy[k], dz[k] = _camera_direction(pixel[i], sample[i], start, w, h, tan_half,
                                                aspect, forward, right, up)


@njit(inline="always", nogil=True, error_model="numpy")
def _camera_direction(pixel, sample, start, w, h, tan_half, aspect, forward, right, up):
    """The float64 unit direction of the camera ray of ``pixel`` and ``sample`` (uint32) on
    an image ``w`` x ``h`` (float64), as ``Camera.generate`` makes it."""
    jx, jy = _uniform_pair(hash_key(start, pixel, sample, 0, 0))
    fp = np.float64(pixel)
    # pixel // width and pixel % width, exactly: (pixel + 0.5) / width lies at least
    # 0.5 / width from an integer, far beyond float64 rounding for pixel < 2^32
    q = np.floor((fp + 0.5) / w)
    column = (fp - q * w) + np.float64(jx)
    row = q + np.float64(jy)
    sx = (2.0 * column / w - 1.0) * tan_half * aspect
    sy = (1.0 - 2.0 * row / h) * tan_half
    d0 = forward[0] + sx * right[0] + sy * up[0]
    d1 = forward[1] + sx * right[1] + sy * up[1]
    d2 = forward[2] + sx * right[2] + sy * up[2]
    length = np.sqrt((d0 * d0 + d1 * d1) + d2 * d2)
    return d0 / length, d1 / length, d2 / length


@njit(inline="always", nogil=True, error_model="numpy")
def _store_camera_ray(i, d0, d1, d2, position, advance, origin, direction):
    """Row ``i`` of ``origin`` and ``direction`` (float32): the unit direction (d0, d1, d2)
    and the camera ``position``, moved ``advance`` along it where that is positive."""
    direction[i, 0], direction[i, 1], direction[i, 2] = d0, d1, d2
    if advance > 0:
        origin[i, 0] = position[0] + d0 * advance
        origin[i, 1] = position[1] + d1 * advance
        origin[i, 2] = position[2] + d2 * advance
    else:
        origin[i, 0], origin[i, 1], origin[i, 2] = position[0], position[1], position[2]


@njit(inline="always", nogil=True, error_model="numpy")
def _overlap(n0, f0, n1, f1, n2, f2):
    """Whether three slabs' distance intervals share a t >= 0: the ray meets their box."""
    near, far = max(max(n0, n1), n2), min(min(f0, f1), f2)
    return (near <= far) & (far >= 0.0)


@njit(inline="always", nogil=True, error_model="numpy")
def _slab(o, d, lo, hi):
    """Entry and exit distances of the ray ``o + t d`` (each rounded to float32 first)
    through the slab ``lo <= x <= hi``; a ray parallel to it (``d`` 0) is in it for every t
    or for none (selects, not branches: the caller's loop stays vectorised)."""
    o, d = np.float64(np.float32(o)), np.float64(np.float32(d))
    parallel = d == 0.0
    step = 1.0 if parallel else d
    t0, t1 = (lo - o) / step, (hi - o) / step
    outside = 1.0 - 2.0 * ((o >= lo) & (o <= hi))  # -1 within the slab, 1 outside it
    near = outside * np.inf if parallel else min(t0, t1)
    far = -outside * np.inf if parallel else max(t0, t1)
    return near, far


@njit(nogil=True, cache=True, error_model="numpy")
def unit_normals(ng, out):
    """``ClosestHits.hits``' normals: float32 ``ng`` ((n, 3)) to float64 unit vectors in
    ``out`` (rows of length 0 stay 0), as ``ng / norm(ng)`` in numpy."""
    for i in range(ng.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = _unit(ng[i, 0], ng[i, 1], ng[i, 2])


@njit(inline="always")
def _unit(x32, y32, z32):
    """One float32 normal as a float64 unit vector, ``ng / norm(ng)`` as numpy computes it (a
    zero normal stays 0)."""
    x, y, z = np.float64(x32), np.float64(y32), np.float64(z32)
    length = np.sqrt((x * x + y * y) + z * z)
    if not length > 0:
        length = 1.0
    return x / length, y / length, z / length


@njit(nogil=True, cache=True, error_model="numpy")
def offer(rows, domain, prim, tfar, ng, best_t, best_domain, best_ng, got):
    """``ClosestHits.offer``'s comparison and stores: ray ``rows[k]`` takes hit ``k`` of
    ``domain`` where it hit (``prim[k] >= 0``) nearer than its best so far, or as near in a
    lower domain; ``got[k]`` says whether it did.

    Parameters
    ----------
    rows : (k,) int64 distinct rays; domain : int64.
    prim : (k,) int32; tfar : (k,) float32; ng : (k, 3) float32 Embree's output.
    best_t : (n,) float32; best_domain : (n,) int32; best_ng : (n, 3) float32, updated.
    got : (k,) bool out.
    """
    for k in range(rows.shape[0]):
        i = rows[k]
        t = tfar[k]
        ok = prim[k] >= 0 and (t < best_t[i] or (t == best_t[i] and domain < best_domain[i]))
        got[k] = ok
        if ok:
            best_t[i] = t
            best_domain[i] = domain
            best_ng[i, 0], best_ng[i, 1], best_ng[i, 2] = ng[k, 0], ng[k, 1], ng[k, 2]


@njit(nogil=True, cache=True, error_model="numpy")
def _first_dispatch(x):
    return x + 1


def warm_up() -> float:
    """Pay numba's once-a-process set-up now: the first call of any compiled kernel loads the
    compiler's registries (numba imports its numpy support): 0.5-0.8 s of CPU measured in a
    fresh node process on the 2-core machine, 80 % of a small job's busy span (0.2-0.4 s
    since it runs without numba's BLAS probe, ``_without_numba_blas``). A node calls it
    (``actors.node_warm_up``, which then calls every kernel once) on a thread as it starts,
    while it makes its sockets, and finishes it before its first hello, so no frame pays it.

    Returns
    -------
    float
        The seconds it took (about 0 in a process that has called a kernel already).
    """
    import time

    start = time.perf_counter()
    with _without_numba_blas():
        _first_dispatch(1)
    return time.perf_counter() - start


#: The module numba's numpy support imports as it loads, to see whether ``np.dot`` and
#: ``np.linalg`` can be compiled: it imports all of ``scipy.linalg`` (and through it
#: ``numpy.f2py``), 0.25 s of a fresh process's start, which no kernel here uses.
NUMBA_BLAS_PROBE = "scipy.linalg.cython_blas"


@contextlib.contextmanager
def _without_numba_blas():
    """While numba loads its numpy support for the first time, its BLAS probe finds nothing
    (``sys.modules`` maps ``NUMBA_BLAS_PROBE`` to None, so its import fails at once without
    importing ``scipy.linalg``); numba then compiles no BLAS call in this process, which none
    of the kernels makes (a test compiles every kernel after it). Afterwards the probe's
    module imports as usual. Where numba's numpy support or the probe's module is loaded
    already, nothing changes."""
    if "numba.np.arraymath" in sys.modules or NUMBA_BLAS_PROBE in sys.modules:
        yield
        return
    sys.modules[NUMBA_BLAS_PROBE] = None
    try:
        yield
    finally:
        if NUMBA_BLAS_PROBE in sys.modules and sys.modules[NUMBA_BLAS_PROBE] is None:
            del sys.modules[NUMBA_BLAS_PROBE]
