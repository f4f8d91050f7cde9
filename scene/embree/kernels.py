"""The query kernels: serial ``@njit(nogil=True, cache=True)`` loops over structure-of-arrays
batches of rays, one Embree call per ray, and the tie filter of closest hits.

They run without the GIL and are loaded from numba's on-disk cache by a warm process (about
2-3 s of compilation per process before). Every buffer a kernel hands Embree (ray, hit,
context, arguments) is that call's own, aligned as Embree's headers declare. The kernels do
not check bounds: ``launch.rays`` checks their inputs.

Queries: 8-ray packets
----------------------
Closest hits use ``rtcIntersect8`` (``intersect_nearest8``) with an argument filter
(``_tie_filter``) that keeps, of equally near hits, the lowest (instance, primitive) id: the hit
of a ray does not depend on the order Embree meets tied candidates in, so a domain queried
directly and the same domain met as an instance of a top-level scene give the same hit (without
it, rays through a shared edge kept different triangles on the two paths: issue 20), and a ray's
hit does not depend on the rays it shares a packet with. Occlusion uses ``rtcOccluded8``
(``occluded8``). The 1-ray kernels (``intersect_nearest``, ``occluded1``) give the same answers
bit for bit (``tests/test_embree.py``) and stay for measurements (``VASTRAY_QUERIES=single``).

Packets were dropped once (9dd359d) after a heap corruption seen with them in session 4
(``bench/README.md``) that no later attempt reproduced, neither the packet path as committed nor
a rebuild of that experiment (``docs/DESIGN.md``, render workers), and stayed out while they
measured no faster (2026-11-29, ``bench/README.md#peerspy``). On an AVX-512 machine (2026-12-01)
16-ray packets traced camera rays 1.3-1.7x and shadow rays 1.3x as fast as single rays, and
bounce rays no slower; renders took 10 % less. 8-ray packets (2026-12-04) trace camera rays
13-18 %, bounce rays 10-14 % and shadow rays 5-12 % faster than 16-ray ones there
(``bench/README.md#peerspy``), and are native wherever Embree runs AVX or AVX2 kernels too,
where 16-ray packets are traced ray by ray (``library``).

Everything the kernels compile in is defined here except the Embree calls and memory access
of ``intrinsics`` (numba's cache sees changes to this file only: see there).
"""

from __future__ import annotations

import threading

import numba
import numpy as np
from numba import njit, types

from vastray.scene.embree.intrinsics import (
    load_f32,
    load_i32,
    load_i64,
    rtc_intersect1,
    rtc_intersect8,
    rtc_occluded1,
    rtc_occluded8,
    store_f32,
    store_i32,
)

# The layouts the kernels hard-code: Embree 4.3 and 4.4's public headers
# (include/embree4/rtcore_ray.h, rtcore_common.h, rtcore_scene.h) for a library built with
# RTC_MAX_INSTANCE_LEVEL_COUNT 1 (with or without instance arrays), as the embreex wheels are.
# ``probe.check_layouts`` verifies every one of them against the library loaded before the
# binding is used. Defined here, not in ``library``, so that every constant the kernels compile
# in lives in this file (numba's cache sees changes to this file only).

#: RTCRayHit as 32-bit words: RTCRay (org_x, org_y, org_z, tnear, dir_x, dir_y, dir_z, time,
#: tfar, mask, id, flags: 48 bytes), then RTCHit (Ng_x, Ng_y, Ng_z, u, v, primID, geomID,
#: instID[1], instPrimID[1] with instance arrays).
RAYHIT_TFAR = 8
RAYHIT_NG = 12  # Ng_x, Ng_y, Ng_z at 12, 13, 14
RAYHIT_U = 15
RAYHIT_V = 16
RAYHIT_PRIM = 17
RAYHIT_GEOM = 18
RAYHIT_INST = 19  # instID[0]; instPrimID[0] at 20 where the library has instance arrays
#: float32 words of our RTCRayHit buffer (96 bytes, 16-byte aligned: rtcIntersect1's rule).
RAYHIT_WORDS = 24
#: Byte offsets of RTCFilterFunctionNArguments' fields: valid (int*), geometryUserPtr,
#: context (RTCRayQueryContext*), ray (RTCRayN*), hit (RTCHitN*), N (unsigned int).
ARG_VALID = 0
ARG_CONTEXT = 16
ARG_RAY = 24
ARG_HIT = 32
ARG_N = 40
#: RTCRayN / RTCHitN (structures of arrays of N lanes): field k of lane i is 32-bit word
#: k * N + i (rtcore_ray.h's RTCRayN_tfar, RTCHitN_primID, RTCHitN_instID at level 0).
RAYN_TFAR = 8
HITN_PRIM = 5
HITN_GEOM = 6
HITN_INST = 7
#: Byte offset, in the ray query context, of our per-lane records (best t: float32, its
#: instance: int32, its primitive: int32, padding): past ``RTCRayQueryContext``'s instID[1]
#: and instPrimID[1] (8 bytes with one instance level), with room to spare.
CTX_RECORD = 16

_INVALID = -1  # RTC_INVALID_GEOMETRY_ID as int32
#: Triangles of each geometry (piece) of a mesh built as several (``scenes.Scene``'s
#: ``piece_triangles``): piece g holds the mesh's triangles ``g * PIECE_TRIANGLES ..`` in order,
#: so a hit's (geomID, primID) is the mesh's triangle ``geomID * PIECE_TRIANGLES + primID``,
#: and a mesh of one geometry (geomID 0) reads as its own primID. The kernels and the tie
#: filter report and compare that id. Why pieces: a domain built in pieces takes about half the
#: time of one mesh's Morton build, which barely uses a second thread, mostly because a piece's
#: blocks come from the C heap and reuse the pages earlier builds freed (``scene.heap``).
PIECE_TRIANGLES = 1 << 17
#: (include/embree4/rtcore_common.h)
RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER = 1 << 1


@njit(inline="always")
def _aligned(raw, align_words, n_words):
    """A view of ``n_words`` words of ``raw`` starting on an ``align_words`` x itemsize byte
    boundary (``raw`` has ``align_words`` spare words)."""
    size = raw.itemsize
    addr = raw.ctypes.data
    mis = (addr // size) % align_words
    off = (align_words - mis) % align_words
    return raw[off:off + n_words]


@njit(inline="always")
def _set_ray1(f, i32, org, dirs, tfar, i):
    # RTCRay: org_x, org_y, org_z, tnear, dir_x, dir_y, dir_z, time, tfar, mask, id, flags
    f[0] = org[i, 0]
    f[1] = org[i, 1]
    f[2] = org[i, 2]
    f[3] = 0.0
    f[4] = dirs[i, 0]
    f[5] = dirs[i, 1]
    f[6] = dirs[i, 2]
    f[7] = 0.0
    f[RAYHIT_TFAR] = tfar[i]
    i32[9] = -1
    i32[10] = 0
    i32[11] = 0


@njit(nogil=True, cache=True)
def occluded1(scene, org, dirs, tfar_in, out):
    """Occlusion of rays ``org + t dirs``, ``0 <= t <= tfar_in``, one ``rtcOccluded1`` per ray;
    ``out`` (n,) bool (``occluded8``'s answers; for measurements).

    The ray buffer is a whole RTCRayHit (96 bytes, 16-byte aligned), though Embree reads and
    writes only its RTCRay part.
    """
    n = org.shape[0]
    raw = np.empty(RAYHIT_WORDS + 4, np.float32)
    f = _aligned(raw, 4, RAYHIT_WORDS)
    i32 = f.view(np.int32)
    for i in range(n):
        _set_ray1(f, i32, org, dirs, tfar_in, i)
        rtc_occluded1(scene, f.ctypes.data, 0)
        out[i] = f[RAYHIT_TFAR] < 0  # Embree sets tfar to -inf on a hit


# ---------------------------------------------------------------------------------------------
# Closest hits: queries whose ties an argument filter breaks by id
# ---------------------------------------------------------------------------------------------

_RECORD_BYTES = 16
#: int32 words of the context buffer: Embree's 16 bytes, then one record per lane of the
#: widest call Embree can make (16), whatever lane a call uses.
_CTX_WORDS = (CTX_RECORD + 16 * _RECORD_BYTES) // 4
#: int64 words of RTCIntersectArguments: flags and feature_mask, context, filter, intersect,
#: (minWidthDistanceFactor where built with it), spare.
_ARGS_WORDS = 6
_NO_ID = np.int32(0x7FFFFFFF)


def _tie_filter(args):
    """Embree filter (``RTCFilterFunctionN``) that makes the closest hit independent of the
    order in which Embree meets equally near candidates.

    Embree accepts a triangle hit when ``t <= tfar`` (inclusive), so of equally near hits the
    one kept depends on the traversal: the leaf order, and, inside a leaf, whether a filter
    runs (without one, the first of the leaf's tied lanes; with one, every tied lane is offered
    in turn). A direct query of a domain and the same domain met as an instance of a top-level
    scene could thus keep different triangles (issue 20: one pixel in 65,536 differed). This
    filter accepts a candidate only if it is nearer than the best so far, or as near with a
    lower (instance, primitive) id, so the same ray always ends with the same hit: the lowest
    domain (instances are attached in ascending domain id; a direct query has no instance,
    id -1) and, within it, the lowest primitive id among the nearest. A mesh built in pieces
    (``PIECE_TRIANGLES``) is compared by its own triangle ids (geomID * PIECE_TRIANGLES +
    primID), so the pieces change nothing of the rule.

    ``args`` is the address of ``RTCFilterFunctionNArguments``: valid (int*), geometryUserPtr,
    context, ray (RTCRayN*), hit (RTCHitN*), N (unsigned int). The candidate's distance is in
    the ray's tfar, its primitive in the hit's primID and geomID, its instance in instID[0].
    The best so far is kept per lane in our part of the ray query context (16 records, one per
    possible lane: no lane indexes past it).
    """
    valid = load_i64(args + ARG_VALID)
    ctx = load_i64(args + ARG_CONTEXT)
    ray = load_i64(args + ARG_RAY)
    hit = load_i64(args + ARG_HIT)
    n = min(load_i32(args + ARG_N), 16)
    for lane in range(n):
        if load_i32(valid + 4 * lane) == 0:
            continue
        t = load_f32(ray + 4 * (RAYN_TFAR * n + lane))
        prim = (load_i32(hit + 4 * (HITN_GEOM * n + lane)) * PIECE_TRIANGLES
                + load_i32(hit + 4 * (HITN_PRIM * n + lane)))
        inst = load_i32(hit + 4 * (HITN_INST * n + lane))
        record = ctx + CTX_RECORD + _RECORD_BYTES * lane
        best_t = load_f32(record)
        best_inst = load_i32(record + 4)
        best_prim = load_i32(record + 8)
        if t < best_t or (t == best_t and (inst < best_inst or (
                inst == best_inst and prim < best_prim))):
            store_f32(record, t)
            store_i32(record + 4, inst)
            store_i32(record + 8, prim)
        else:
            store_i32(valid + 4 * lane, 0)


_filter_cfunc = None
_filter_lock = threading.Lock()


def filter_address() -> int:
    """Address of the compiled ``_tie_filter`` (compiled, or loaded from numba's cache, on
    first use; the cfunc object is kept for the life of the process, so the address stays
    valid)."""
    global _filter_cfunc
    with _filter_lock:
        if _filter_cfunc is None:
            _filter_cfunc = numba.cfunc(types.void(types.int64), nogil=True, cache=True)(
                _tie_filter)
        return _filter_cfunc.address


@njit(inline="always")
def _store_hit(f, i32, prim, tfar, u, v, ng, i):
    """Copy ray ``i``'s hit out of an RTCRayHit buffer: tfar at word 8, then the hit's Ng_x,
    Ng_y, Ng_z, u, v, primID, geomID at words 12-18 (the mesh's triangle: geomID *
    PIECE_TRIANGLES + primID). A miss reads as primID -1, zero u, v and Ng."""
    p = i32[RAYHIT_PRIM]
    tfar[i] = f[RAYHIT_TFAR]
    if p == _INVALID:
        prim[i] = -1
        u[i] = 0.0
        v[i] = 0.0
        ng[i, 0] = 0.0
        ng[i, 1] = 0.0
        ng[i, 2] = 0.0
    else:
        prim[i] = i32[RAYHIT_GEOM] * PIECE_TRIANGLES + p
        ng[i, 0] = f[RAYHIT_NG]
        ng[i, 1] = f[RAYHIT_NG + 1]
        ng[i, 2] = f[RAYHIT_NG + 2]
        u[i] = f[RAYHIT_U]
        v[i] = f[RAYHIT_V]


@njit(inline="always")
def _query_buffers():
    """A kernel call's own ray query context (int32 words ``context`` and their float32 view
    ``cf``: Embree's 16 bytes, then the tie filter's per-lane records) and
    RTCIntersectArguments (int64 words ``arguments`` and their int32 view ``a32``), zeroed
    and 16-byte aligned."""
    raw_context = np.zeros(_CTX_WORDS + 4, np.int32)
    context = _aligned(raw_context, 4, _CTX_WORDS)
    raw_arguments = np.zeros(_ARGS_WORDS + 2, np.int64)
    arguments = _aligned(raw_arguments, 2, _ARGS_WORDS)
    return context, context.view(np.float32), arguments, arguments.view(np.int32)


@njit(inline="always")
def _query_set_up(arguments, a32, context, filt, flags):
    """Before each call: RTCIntersectArguments (query ``flags``, incoherent; every feature;
    this call's context; the argument filter ``filt``) and the context's Embree part as
    ``rtcInitRayQueryContext`` leaves it with one instance level (instID[0] and, where
    present, instPrimID[0] invalid). Set in the query loop, so the buffers Embree reads stay
    referenced through it."""
    a32[0] = flags
    a32[1] = -1  # feature_mask: RTC_FEATURE_FLAG_ALL
    arguments[1] = context.ctypes.data
    arguments[2] = filt
    context[0] = _INVALID
    context[1] = _INVALID


@njit(inline="always")
def _fresh_records(context, cf, tfar_in, start, m):
    """The tie filter's records of lanes ``0 .. m`` (rays ``start ..``): the best distance so far
    each ray's ``tfar_in``, no instance and no primitive (lane k's record: int32 words
    ``CTX_RECORD // 4 + 4k`` .. ``+ 2`` of ``context``, ``cf`` their float32 view)."""
    record = CTX_RECORD // 4
    for lane in range(m):
        cf[record + 4 * lane] = tfar_in[start + lane]
        context[record + 4 * lane + 1] = _NO_ID
        context[record + 4 * lane + 2] = _NO_ID


@njit(nogil=True, cache=True)
def intersect_nearest(scene, filt, org, dirs, tfar_in, prim, tfar, u, v, ng, inst):
    """Closest hits, one ``rtcIntersect1`` per ray with the tie filter ``filt`` (for
    measurements: ``intersect_nearest8``'s answers): the outputs are (n,) each (``ng``
    (n, 3)); ``inst`` receives the instance (top-level geometry id) of each hit, -1 for a miss
    or a scene without instances.

    The ray, the context and the arguments Embree reads live in this call's own buffers, all
    16-byte aligned: RTCRayHit must be (rtcIntersect1's manual; RTCRay is ``RTC_ALIGN(16)``),
    RTCRayQueryContext and RTCIntersectArguments are plain structures (4- and 8-byte alignment
    suffice). The context's first 8 bytes are Embree's (instID[0], instPrimID[0]), initialised
    as ``rtcInitRayQueryContext`` does with one instance level.
    """
    n = org.shape[0]
    raw = np.empty(RAYHIT_WORDS + 4, np.float32)
    f = _aligned(raw, 4, RAYHIT_WORDS)
    i32 = f.view(np.int32)
    context, cf, arguments, a32 = _query_buffers()
    for i in range(n):
        _query_set_up(arguments, a32, context, filt, RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER)
        _set_ray1(f, i32, org, dirs, tfar_in, i)
        i32[RAYHIT_PRIM] = _INVALID
        i32[RAYHIT_GEOM] = _INVALID
        i32[RAYHIT_INST] = _INVALID  # instID[0]
        _fresh_records(context, cf, tfar_in, i, 1)  # lane 0's: a 1-ray call has one lane
        rtc_intersect1(scene, f.ctypes.data, arguments.ctypes.data)
        _store_hit(f, i32, prim, tfar, u, v, ng, i)
        inst[i] = i32[RAYHIT_INST] if prim[i] >= 0 else -1


# ---------------------------------------------------------------------------------------------
# 8-ray packets: the same queries, 8 consecutive rays a call
# ---------------------------------------------------------------------------------------------

#: Lanes of a packet query (``rtcIntersect8``, ``rtcOccluded8``).
PACKET = 8
#: 32-bit fields of RTCRayHit8 (``RTC_ALIGN(32)``): RTCRay8's 12, then RTCHit8's Ng_x, Ng_y,
#: Ng_z, u, v, primID, geomID, instID[1] and instPrimID[1] (with instance arrays). Field k is
#: RTCRayHit's word k (``RAYHIT_*``); lane i of it is word ``k * PACKET + i``.
PACKET_FIELDS = 21


@njit(inline="always")
def _packet_constants(f, i32):
    """The RTCRay8 fields Embree reads and never writes, the same for every ray: tnear 0,
    time 0, mask all ones, id 0, flags 0 (set once per kernel call, not per packet)."""
    for lane in range(PACKET):
        f[3 * PACKET + lane] = 0.0
        f[7 * PACKET + lane] = 0.0
        i32[9 * PACKET + lane] = -1
        i32[10 * PACKET + lane] = 0
        i32[11 * PACKET + lane] = 0


@njit(inline="always")
def _packet_rays(f, valid, org, dirs, tfar, start, m):
    """Rays ``start .. start + m`` into lanes ``0 .. m`` of the packet (origin, direction,
    tfar), the lanes past ``m`` invalid."""
    for lane in range(PACKET):
        valid[lane] = -1 if lane < m else 0
    for lane in range(m):
        i = start + lane
        f[lane] = org[i, 0]
        f[PACKET + lane] = org[i, 1]
        f[2 * PACKET + lane] = org[i, 2]
        f[4 * PACKET + lane] = dirs[i, 0]
        f[5 * PACKET + lane] = dirs[i, 1]
        f[6 * PACKET + lane] = dirs[i, 2]
        f[RAYHIT_TFAR * PACKET + lane] = tfar[i]


@njit(inline="always")
def _no_hits(i32, m):
    """Lanes ``0 .. m`` of an RTCRayHit8 buffer hit nothing yet (primID, geomID and instID[0]
    invalid), as Embree requires of a closest-hit query."""
    for lane in range(m):
        i32[RAYHIT_PRIM * PACKET + lane] = _INVALID
        i32[RAYHIT_GEOM * PACKET + lane] = _INVALID
        i32[RAYHIT_INST * PACKET + lane] = _INVALID


@njit(inline="always")
def _packet_buffers():
    """A kernel call's own RTCRayHit8 buffer (float32 words ``f`` and their int32 view
    ``i32``) and ``valid`` mask, each 64-byte aligned (Embree requires 32 bytes of 8-wide
    packets; the views keep their allocations alive as long as they are used)."""
    raw = np.empty(PACKET_FIELDS * PACKET + 16, np.float32)
    f = _aligned(raw, 16, PACKET_FIELDS * PACKET)
    raw_valid = np.empty(PACKET + 16, np.int32)
    return f, f.view(np.int32), _aligned(raw_valid, 16, PACKET)


@njit(nogil=True, cache=True)
def occluded8(scene, org, dirs, tfar_in, out):
    """``occluded1``'s answers, 8 rays a ``rtcOccluded8`` (the last call's missing lanes
    invalid); ``out`` (n,) bool.

    The packet (RTCRay8 in an RTCRayHit8-sized buffer) and its ``valid`` mask are this call's
    own, 64-byte aligned (Embree requires 32 bytes of 8-wide packets). Rays that stay together
    cross the same BVH nodes (camera rays of a pixel, shadow rays towards one point light):
    Embree traverses those 8 at a time, and falls back to single rays inside a packet that
    scatters.
    """
    n = org.shape[0]
    f, i32, valid = _packet_buffers()
    _packet_constants(f, i32)
    for start in range(0, n, PACKET):
        m = min(PACKET, n - start)
        _packet_rays(f, valid, org, dirs, tfar_in, start, m)
        rtc_occluded8(valid.ctypes.data, scene, f.ctypes.data, 0)
        for lane in range(m):
            out[start + lane] = f[RAYHIT_TFAR * PACKET + lane] < 0


@njit(nogil=True, cache=True)
def intersect_nearest8(scene, filt, org, dirs, tfar_in, prim, tfar, u, v, ng, inst):
    """``intersect_nearest``'s closest hits, bit for bit, 8 rays a ``rtcIntersect8`` with
    the tie filter ``filt`` (each lane keeps its own record in the context: Embree calls the
    filter with the packet's lanes, or with one lane valid where it traces a lane alone).

    Embree's packet and single-ray triangle tests compute the same distances and
    barycentrics, and the tie filter picks among equally near candidates by id whatever order
    they come in, so a ray's hit does not depend on the rays it shares a packet with
    (``tests/test_embree.py`` compares the two kernels on coherent and scattered rays, with
    ties and through instances).
    """
    n = org.shape[0]
    f, i32, valid = _packet_buffers()
    context, cf, arguments, a32 = _query_buffers()
    _packet_constants(f, i32)
    for start in range(0, n, PACKET):
        m = min(PACKET, n - start)
        _query_set_up(arguments, a32, context, filt, RTC_RAY_QUERY_FLAG_INVOKE_ARGUMENT_FILTER)
        _packet_rays(f, valid, org, dirs, tfar_in, start, m)
        _no_hits(i32, m)
        _fresh_records(context, cf, tfar_in, start, m)
        rtc_intersect8(valid.ctypes.data, scene, f.ctypes.data, arguments.ctypes.data)
        for lane in range(m):  # a miss reads as primID -1, zero u, v and Ng (as _store_hit)
            i = start + lane
            p = i32[RAYHIT_PRIM * PACKET + lane]
            hit = p != _INVALID
            tfar[i] = f[RAYHIT_TFAR * PACKET + lane]
            prim[i] = i32[RAYHIT_GEOM * PACKET + lane] * PIECE_TRIANGLES + p if hit else -1
            inst[i] = i32[RAYHIT_INST * PACKET + lane] if hit else -1
            u[i] = f[RAYHIT_U * PACKET + lane] if hit else np.float32(0.0)
            v[i] = f[RAYHIT_V * PACKET + lane] if hit else np.float32(0.0)
            ng[i, 0] = f[RAYHIT_NG * PACKET + lane] if hit else np.float32(0.0)
            ng[i, 1] = f[(RAYHIT_NG + 1) * PACKET + lane] if hit else np.float32(0.0)
            ng[i, 2] = f[(RAYHIT_NG + 2) * PACKET + lane] if hit else np.float32(0.0)
